"""Target profiles: one TOML per deployment target (runtime, opset, ops, precision, hardware figures).

Profiles ship inside the package (package data), so an installed, non-editable copy finds them too.
`load_profile` accepts a profile name (``tx2``, ``x86-cpu``) or a path to a TOML file.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from profiles.errors import ProfileError
from profiles.fields import MAX_KEYPOINTS, MAX_OPSET, MIN_OPSET, PRECISIONS, Fields, check_finite_numbers

__all__ = ["ProfileError", "TargetProfile", "available_profiles", "load_profile"]

PROFILE_DIR = Path(__file__).resolve().parent


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
    # onnxruntime channel blocks (NCHWc) that get a graph of their own, padded with zero channels around its
    # max-pools to a multiple of the block (`export.block_graphs`); empty: the traced graph only.
    channel_blocks: tuple[int, ...] = ()

    @property
    def elu_form(self) -> str:
        """How ELU is traced for this target (`models.featurenet.ELU`): onnxruntime runs max(x, exp(min(x, 0))
        - 1) faster than its own Elu op; TensorRT fuses Elu into the conv."""
        return "max_exp" if self.runtime.startswith("onnxruntime") else "native"


def available_profiles() -> list[str]:
    """Names of the profiles shipped with the toolkit."""
    return sorted(path.stem for path in PROFILE_DIR.glob("*.toml"))


def _profile_path(name_or_path: str | Path) -> Path:
    """The TOML file a ``--target`` names: a shipped profile's name, or a path ending in .toml."""
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise ProfileError(f"a profile is a name or a .toml path, got {type(name_or_path).__name__}")
    candidate = Path(name_or_path)
    if candidate.suffix != ".toml":
        path = PROFILE_DIR / f"{name_or_path}.toml"
        if not path.is_file():
            raise ProfileError(f"unknown target {str(name_or_path)!r} (known: {', '.join(available_profiles())})")
        return path
    if candidate.exists() and not candidate.is_file():
        raise ProfileError(f"profile {candidate} is not a file")
    if not candidate.is_file():
        raise ProfileError(f"profile file not found: {candidate}")
    return candidate


def _read_table(path: Path) -> dict[str, Any]:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ProfileError(f"profile {path} is not UTF-8 text") from None
    except RecursionError:
        raise ProfileError(f"profile {path} nests its tables too deeply to be a profile") from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ProfileError(f"{path} is not valid TOML ({exc})") from None


def _channel_blocks(fields: Fields) -> tuple[int, ...]:
    """``channel_blocks``; a profile of the releases before it names one block as ``channel_multiple``."""
    if "channel_blocks" in fields.table:
        return tuple(block for block in fields.wholes("channel_blocks", 1, 256) if block > 1)
    if "channel_multiple" in fields.table:
        block = fields.whole("channel_multiple", 1, 256)
        return (block,) if block > 1 else ()
    return ()


def load_profile(name_or_path: str | Path) -> TargetProfile:
    """Load a shipped profile by name or a TOML file by path. Every field is checked here, once (`profiles.fields`):
    a missing or invalid one raises `ProfileError` naming it."""
    path = _profile_path(name_or_path)
    fields = Fields(_read_table(path), str(path))
    precisions = fields.texts("precisions", PRECISIONS, empty=False)
    default_precision = fields.text("default_precision")
    if default_precision not in precisions:
        raise ProfileError(f"profile {path}: default_precision is not one of its precisions")
    hardware = fields.table_of("hardware")
    check_finite_numbers(hardware, "hardware", str(path))
    constraints = fields.table_of("ops.constraints")
    if not all(isinstance(value, str) for value in constraints.values()):
        raise ProfileError(f"profile {path}: ops.constraints values must be strings")
    return TargetProfile(
        name=fields.text("name"),
        description=fields.text("description"),
        runtime=fields.text("runtime"),
        max_opset=fields.whole("max_opset", MIN_OPSET, MAX_OPSET),
        deform_strategy=fields.text("deform_strategy", ("native", "portable")),
        precisions=precisions,
        default_precision=default_precision,
        default_input_size=fields.input_size("default_input_size"),
        default_max_keypoints=fields.whole("default_max_keypoints", 1, MAX_KEYPOINTS),
        allowed_ops=frozenset(fields.texts("ops.allowed")),
        op_constraints=dict(constraints),
        hardware=dict(hardware),
        source=str(path),
        channel_blocks=_channel_blocks(fields),
    )
