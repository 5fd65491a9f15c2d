"""Target profiles: one TOML per deployment target (runtime, opset, ops, precision, hardware figures).

Profiles ship inside the package (package data), so an installed, non-editable copy finds them too.
`load_profile` accepts a profile name (``tx2``, ``x86-cpu``) or a path to a TOML file.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from toolkit.errors import ToolkitError

PROFILE_DIR = Path(__file__).resolve().parent
REQUIRED_FIELDS = (
    "name", "description", "runtime", "max_opset", "deform_strategy", "precisions",
    "default_precision", "default_input_size", "default_max_keypoints", "ops.allowed",
)


@dataclass(frozen=True)
class TargetProfile:
    """What one deployment target accepts. ``allowed_ops`` empty means: anything its runtime implements."""

    name: str
    description: str
    runtime: str
    max_opset: int
    deform_strategy: str
    precisions: tuple[str, ...]
    default_precision: str
    default_input_size: tuple[int, int]
    default_max_keypoints: int
    allowed_ops: frozenset[str]
    op_constraints: dict[str, str] = field(default_factory=dict)
    hardware: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def elu_form(self) -> str:
        """How ELU is traced for this target (`models.featurenet.ELU`): onnxruntime runs max(x, exp(min(x, 0))
        - 1) faster than its own Elu op; TensorRT fuses Elu into the conv."""
        return "max_exp" if self.runtime.startswith("onnxruntime") else "native"


def available_profiles() -> list[str]:
    """Names of the profiles shipped with the toolkit."""
    return sorted(path.stem for path in PROFILE_DIR.glob("*.toml"))


def _lookup(table: dict[str, Any], dotted: str) -> Any:
    node: Any = table
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def load_profile(name_or_path: str | Path) -> TargetProfile:
    """Load a shipped profile by name or a TOML file by path; a missing field is named in the error."""
    candidate = Path(name_or_path)
    if candidate.suffix == ".toml":
        path = candidate
    else:
        path = PROFILE_DIR / f"{name_or_path}.toml"
        if not path.is_file():
            raise ToolkitError(f"unknown target {str(name_or_path)!r} (known: {', '.join(available_profiles())})")
    if not path.is_file():
        raise ToolkitError(f"profile file not found: {path}")
    try:
        table = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ToolkitError(f"{path} is not valid TOML ({exc})") from None
    for dotted in REQUIRED_FIELDS:
        try:
            _lookup(table, dotted)
        except KeyError:
            raise ToolkitError(f"profile {path} is missing the field '{dotted}'") from None
    if table["deform_strategy"] not in ("native", "portable"):
        raise ToolkitError(f"profile {path}: deform_strategy must be 'native' or 'portable'")
    if table["default_precision"] not in table["precisions"]:
        raise ToolkitError(f"profile {path}: default_precision is not one of its precisions")
    ops = table["ops"]
    return TargetProfile(
        name=str(table["name"]),
        description=str(table["description"]),
        runtime=str(table["runtime"]),
        max_opset=int(table["max_opset"]),
        deform_strategy=str(table["deform_strategy"]),
        precisions=tuple(table["precisions"]),
        default_precision=str(table["default_precision"]),
        default_input_size=(int(table["default_input_size"][0]), int(table["default_input_size"][1])),
        default_max_keypoints=int(table["default_max_keypoints"]),
        allowed_ops=frozenset(ops["allowed"]),
        op_constraints=dict(ops.get("constraints", {})),
        hardware=dict(table.get("hardware", {})),
        source=str(path),
    )
