"""Training configuration: one dataclass tree, read from JSON/TOML, every field checked by name."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from models.keypoints import is_score_window
from toolkit.errors import ToolkitError
from toolkit.training.augment import AugmentConfig
from toolkit.training.distill_losses import DistillLossConfig
from toolkit.training.distill_pairs import MultiScaleConfig
from toolkit.training.homographies import HomographyConfig
from toolkit.training.losses import LossConfig
from toolkit.training.validation import ValidationConfig

RECIPES = ("distill", "paper")
LR_SCHEDULES = ("cosine", "constant")


@dataclass
class TrainConfig:
    """Everything a run depends on; ``--config FILE`` (JSON or TOML) sets any field, nested by section."""

    recipe: str = "distill"  # "distill" (teacher keypoints + descriptors) or "paper" (SuperPoint's CE + hinge)
    arch: str = "featurenet"  # or "superpoint"
    model: dict = field(default_factory=dict)  # FeatureNetConfig / SuperPointConfig fields
    # Module names of the parts that learn (e.g. ["pixel_head", "detector"]); empty: the whole model.
    # The rest keeps its weights and stays in eval mode (`toolkit.training.freezing`).
    train_only: list = field(default_factory=list)
    init: str = ""  # start from these weights: a run folder (model + projection) or a .safetensors checkpoint
    steps: int = 20000
    batch: int = 8  # pairs per step and per process
    lr: float = 1e-3  # peak learning rate (Adam)
    lr_schedule: str = "cosine"  # "cosine": linear warm-up, then cosine decay to lr_final_fraction * lr
    warmup_steps: int = 200
    lr_final_fraction: float = 0.05
    threads: int = 0  # torch CPU threads; 0 leaves torch's default (set it: 2 threads on a busy 2-core box are ~4x slower)
    # bfloat16 autocast on a CPU with native bfloat16 (AVX512_BF16 / AMX: 1.4-1.7x); other CPUs train in float32,
    # where bfloat16 is emulated and 4.6x slower (`toolkit.training.cpu_precision`)
    cpu_bf16: bool = True
    train_sampler: str = "grid_sample"  # deformable sampler while training: "grid_sample" (fast) or "torch" (gather)
    seed: int = 0
    checkpoint_every: int = 500
    validate_every: int = 1000
    log_every: int = 10
    val_fraction: float = 0.05  # of the images, held back by image hash
    val_max_images: int = 64
    num_workers: int = -1  # DataLoader workers (-1: 4 per process on CUDA, 0 on CPU); samples do not depend on it
    device: str = "auto"  # "auto" (CUDA when available), "cuda" or "cpu" (gloo for several processes)
    amp: bool = True  # float16 autocast + GradScaler, on CUDA only
    homography: HomographyConfig = field(default_factory=HomographyConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    loss: LossConfig = field(default_factory=LossConfig)  # the paper recipe
    distill: DistillLossConfig = field(default_factory=DistillLossConfig)  # the distill recipe
    scales: MultiScaleConfig = field(default_factory=MultiScaleConfig)  # the distill recipe's sizes and zoom
    validation: ValidationConfig = field(default_factory=ValidationConfig)

    def __post_init__(self) -> None:
        if self.recipe not in RECIPES:
            raise ValueError(f"recipe must be one of {RECIPES}, not {self.recipe!r}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, not {self.lr_schedule!r}")
        if self.train_sampler not in ("grid_sample", "torch"):
            raise ValueError(f"train_sampler must be grid_sample or torch, not {self.train_sampler!r}")
        if not self.lr > 0 or not 0 <= self.lr_final_fraction <= 1:
            raise ValueError("lr must be > 0 and lr_final_fraction within [0, 1]")
        for name in ("warmup_steps", "threads", "checkpoint_every", "validate_every", "log_every", "val_max_images"):
            minimum = 1 if name in ("checkpoint_every", "validate_every", "log_every", "val_max_images") else 0
            if getattr(self, name) < minimum:
                raise ValueError(f"{name} must be >= {minimum}")
        if not 0 < self.val_fraction < 1:
            raise ValueError("val_fraction must be within (0, 1)")
        if self.num_workers < -1:
            raise ValueError("num_workers must be >= 0 (or -1 for the default)")
        if not is_score_window(self.validation.score_window):
            raise ValueError("validation.score_window must be an odd number of pixels")

    def learning_rate(self, step: int) -> float:
        """The learning rate of optimisation step ``step`` (0-based): a pure function, so resume needs no state."""
        if self.lr_schedule == "constant":
            return self.lr
        warmup = min(self.warmup_steps, self.steps // 10)  # a short run keeps most of its steps at full rate
        return warmup_cosine(self.lr, step, self.steps, warmup, self.lr_final_fraction)


def warmup_cosine(lr: float, step: int, total: int, warmup: int, final_fraction: float) -> float:
    """Learning rate of step ``step`` (0-based) of ``total``: linear warm-up over ``warmup`` steps, then cosine
    decay from ``lr`` to ``final_fraction * lr``."""
    if step < warmup:
        return lr * (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return lr * (final_fraction + (1.0 - final_fraction) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def _type_name(value: Any) -> str:
    return {bool: "true/false", int: "an integer", float: "a number", str: "a string", list: "a list",
            tuple: "a list", dict: "a table"}.get(type(value), type(value).__name__)


def _check_type(name: str, value: Any, default: Any) -> Any:
    """``value`` converted to the default's type, or a ToolkitError naming the key and the type it needs."""
    expected = type(default)
    if expected is bool:
        ok = isinstance(value, bool)
    elif expected is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        value = float(value) if ok else value
    elif expected in (list, tuple):
        ok = isinstance(value, (list, tuple))
    else:
        ok = isinstance(value, expected)
    if not ok:
        raise ToolkitError(f"config key {name} must be {_type_name(default)}, not {value!r}")
    return value


def _build_dataclass(kind: type, values: dict[str, Any], where: str) -> Any:
    known = {f.name: f for f in fields(kind)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ToolkitError(f"unknown config key {where}{unknown[0]} (known: {', '.join(known)})")
    built = {}
    for name, value in values.items():
        default = getattr(kind(), name)
        if is_dataclass(default):
            if not isinstance(value, dict):
                raise ToolkitError(f"config key {where}{name} must be a table of settings")
            value = _build_dataclass(type(default), value, f"{where}{name}.")
        else:
            value = _check_type(f"{where}{name}", value, default)
            if isinstance(default, tuple):
                value = tuple(value)
        built[name] = value
    try:
        return kind(**built)
    except (TypeError, ValueError) as exc:
        raise ToolkitError(f"config {where.rstrip('.') or 'settings'}: {exc}") from None


def config_from_dict(values: dict[str, Any]) -> TrainConfig:
    """Nested dict (e.g. parsed JSON/TOML) -> TrainConfig; unknown keys are an error, missing ones default."""
    return _build_dataclass(TrainConfig, values, "")


def read_config_file(path: str | Path) -> TrainConfig:
    """``.toml`` or ``.json`` file -> TrainConfig."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ToolkitError(f"config {path} is not UTF-8 text") from None
    except OSError as exc:
        raise ToolkitError(f"cannot read config {path}: {exc.strerror}") from None
    try:
        if path.suffix == ".toml":
            import tomllib

            values = tomllib.loads(text)
        else:
            values = json.loads(text)
    except RecursionError:
        raise ToolkitError(f"config {path} nests too deeply to be a training config") from None
    except ValueError as exc:
        raise ToolkitError(f"cannot parse config {path}: {exc}") from None
    if not isinstance(values, dict):
        raise ToolkitError(f"config {path} holds a {type(values).__name__}, not a table of TrainConfig fields")
    return config_from_dict(values)


