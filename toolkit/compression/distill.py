"""Fine-tuning a pruned network by distillation from the unpruned one.

Loss = KL(teacher || student) over the 65 classes of every cell (temperature T, scaled by T^2)
     + mean (1 - cosine) between student and teacher descriptors
     [+ the training pipeline's SuperPoint loss on warped labelled pairs, when a label folder is given].
BatchNorm statistics stay frozen (eval mode): a short fine-tune on a few small batches would only make
them noisier, and the teacher's statistics are the ones the pruned channels were chosen under.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from toolkit.compression.images import load_images
from toolkit.errors import ToolkitError
from vo_runtime.progress import progress_bar


@dataclass
class DistillConfig:
    steps: int = 200
    batch: int = 4
    lr: float = 1e-4
    temperature: float = 2.0
    size: tuple[int, int] = (240, 320)
    images: int = 64  # distinct images drawn from the folder (without labels)
    seed: int = 0


@dataclass
class DistillResult:
    steps: int
    first_loss: float
    last_loss: float
    seconds: float
    used_labels: bool


def distillation_loss(student: dict[str, torch.Tensor], teacher: dict[str, torch.Tensor], temperature: float) -> torch.Tensor:
    """Scalar loss matching student heads to teacher heads.

    Args:
        student, teacher: {"logits": [B, 65, h, w], "descriptors": [B, D, h, w] unit-norm}.
    """
    log_student = F.log_softmax(student["logits"] / temperature, dim=1)
    log_teacher = F.log_softmax(teacher["logits"] / temperature, dim=1)
    detector = (log_teacher.exp() * (log_teacher - log_student)).sum(1).mean() * temperature**2
    descriptor = (1.0 - (student["descriptors"] * teacher["descriptors"]).sum(1)).mean()
    return detector + descriptor


def optimiser_step(optimizer: torch.optim.Optimizer, loss: torch.Tensor, step: int, what: str = "distillation") -> float:
    """One optimiser step on ``loss``; returns its value. A non-finite loss is a `ToolkitError` naming the step."""
    if not torch.isfinite(loss):
        raise ToolkitError(f"{what} diverged at step {step} (loss {float(loss)}); try a lower learning rate")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return float(loss.detach())


def log_losses(rows: list[dict], running: list[float], step: int, every: int, lr: float, began: float, log) -> None:
    """Every ``every`` steps: one row of the loss log (mean of ``running``, which is emptied) and its line."""
    if (step + 1) % every:
        return
    rows.append({"step": step + 1, "loss": float(np.mean(running)), "lr": lr,
                 "seconds": round(time.perf_counter() - began, 1)})
    running.clear()
    log(f"step {step + 1} loss {rows[-1]['loss']:.4f} ({rows[-1]['seconds']:.0f} s)")


def steps_within(minutes: float, max_steps: int, step: int, began: float, warm: float, measured: int) -> tuple[int, float]:
    """Fit a run to a wall-clock budget at ``step``: (total steps, seconds a step), the pace read off the
    ``measured`` steps since ``warm`` (workers started, kernels chosen), the run began at ``began``."""
    now = time.perf_counter()
    pace = (now - warm) / measured
    return max(step + 1, min(max_steps, step + int((minutes * 60 - (now - began)) / pace))), pace


def train_with_grid_sample(models: list[nn.Module]) -> dict[nn.Module, set[str]]:
    """Switch every deformable conv of ``models`` to grid_sample (the gather sampler's values, faster to train);
    returns what each used, for `restore_sampling`."""
    from models.deform import DeformableConv, set_deform_strategy

    used = {model: {layer.strategy for layer in model.modules() if isinstance(layer, DeformableConv)}
            for model in models}
    for model in models:
        set_deform_strategy(model, "grid_sample")
    return used


def restore_sampling(used: dict[nn.Module, set[str]]) -> None:
    """The caller's models sample as they did before `train_with_grid_sample`."""
    from models.deform import set_deform_strategy

    for model, strategies in used.items():
        if len(strategies) == 1:
            set_deform_strategy(model, next(iter(strategies)))


def _labelled_pairs(images: Path, labels: Path, seed: int):
    try:
        from toolkit.training.homographies import HomographyConfig
        from toolkit.training.label_store import LabelStore
        from toolkit.training.losses import LossConfig, superpoint_loss
        from toolkit.training.pairs import WarpedPairs, load_labelled_images
    except ImportError as exc:
        raise ToolkitError(f"--labels needs the training package, which does not import here ({exc})") from None
    store = LabelStore.open(labels)
    records, _ = load_labelled_images(images, store)
    pairs = WarpedPairs(records, store.size, HomographyConfig(), None, seed)
    return pairs, superpoint_loss, LossConfig()


def distill(
    student: nn.Module,
    teacher: nn.Module,
    images: str | Path,
    config: DistillConfig,
    labels: str | Path | None = None,
    progress: bool = True,
) -> DistillResult:
    """Fine-tune ``student`` in place for ``config.steps`` Adam steps; ``teacher`` stays frozen.

    Without ``labels``: batches of real images from ``images`` (random picks and horizontal flips).
    With ``labels`` (a `toolkit label` folder for ``images``): warped pairs, SuperPoint loss + distillation.
    """
    if config.steps < 0:
        raise ToolkitError(f"--steps must be >= 0, got {config.steps}")
    teacher.eval().requires_grad_(False)
    student.eval().requires_grad_(True)  # eval: frozen BatchNorm statistics, see the module docstring
    generator = torch.Generator().manual_seed(config.seed)
    optimizer = torch.optim.Adam(student.parameters(), lr=config.lr)
    pairs = task_loss = loss_config = None
    if labels is not None:
        pairs, task_loss, loss_config = _labelled_pairs(Path(images), Path(labels), config.seed)
    else:
        pool = torch.from_numpy(load_images(images, config.images, config.size)[0])
    losses: list[float] = []
    tick = time.perf_counter()
    for step in progress_bar(range(config.steps), desc="distil", unit="step", enabled=progress, leave=False):
        if pairs is not None:
            samples = [pairs[step * config.batch + i] for i in range(config.batch)]
            batch = {key: torch.stack([s[key] for s in samples]) for key in samples[0]}
            inputs = torch.cat([batch["image_a"], batch["image_b"]])
        else:
            picks = torch.randint(len(pool), (config.batch,), generator=generator)
            inputs = pool[picks]
            flips = torch.rand(config.batch, generator=generator) < 0.5
            inputs = torch.where(flips[:, None, None, None], inputs.flip(-1), inputs)
        with torch.no_grad():
            target = teacher(inputs)
        outputs = student(inputs)
        loss = distillation_loss(outputs, target, config.temperature)
        if pairs is not None:
            count = batch["image_a"].shape[0]
            split_a = {key: value[:count] for key, value in outputs.items()}
            split_b = {key: value[count:] for key, value in outputs.items()}
            loss = loss + task_loss(split_a, split_b, batch, loss_config)["loss"]
        losses.append(optimiser_step(optimizer, loss, step))
    student.requires_grad_(False).eval()
    return DistillResult(
        steps=config.steps,
        first_loss=losses[0] if losses else float("nan"),
        last_loss=float(np.mean(losses[-max(1, len(losses) // 10):])) if losses else float("nan"),
        seconds=time.perf_counter() - tick,
        used_labels=labels is not None,
    )
