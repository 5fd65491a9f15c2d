"""A slimmer FeatureNet for large inputs, distilled from a trained one: strided stem, fewer channels.

At the drone camera's 480x752 the shipped network takes 25-32 ms a frame on one x86 core (onnxruntime), so the
whole VO cannot reach 30 frames a second. Two changes cut the graph to ~0.7 of its time (measured side by side,
random weights, docs/compression.md): the stem conv gets stride 2 (no conv and max-pool at full resolution) and
every group of channels loses a share (`prune_channels`, DepGraph). The student starts from the teacher's own
weights (`restem` keeps them) and learns to reproduce the teacher's heads, the 65-way cell distribution and the
descriptors, on real images under the training's photometric and low-light augmentation (`distill_slim`).

It needs a long run to recover what the cut removed: on a GPU (`device="cuda"`) a few minutes give tens of
thousands of images; on a CPU the same code runs, slowly (`toolkit prune` is the CPU path).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from models.featurenet import FeatureNet, FeatureNetConfig
from toolkit.compression.distill import (distillation_loss, log_losses, optimiser_step, restore_sampling,
                                         steps_within, train_with_grid_sample)
from toolkit.compression.images import find_images
from toolkit.errors import ToolkitError
from toolkit.training.augment import AugmentConfig, photometric_augment
from toolkit.training.config import warmup_cosine
from vo_runtime.image_decode import decode_image


def restem(model: FeatureNet) -> FeatureNet:
    """``model`` with a stride-2 stem conv instead of a stride-1 conv and a 2x2 max-pool; same weights.

    The strided conv samples the stride-1 conv's outputs at even pixels, where the max-pool took the largest of
    four: the closest start the old weights give. [B, 1, H, W] -> heads as before (H, W divisible by 8).
    """
    config = FeatureNetConfig(**{**model.config.to_dict(), "stem_stride": 2})
    slim = FeatureNet(config)
    slim.load_state_dict(model.state_dict(), strict=True)  # the Identity holds no weights: the keys are the same
    return slim


@dataclass
class SlimDistillConfig:
    steps: int = 2000            # upper bound; ``minutes`` may stop earlier
    minutes: float = 0.0         # wall-clock budget for the steps (0: none); the schedule is fitted to it
    batch: int = 32
    lr: float = 5e-4
    lr_final_fraction: float = 0.02
    temperature: float = 1.0     # sharp: the positions inside a cell are what the VO needs
    sizes: list[tuple[int, int]] = field(default_factory=lambda: [(192, 256), (240, 320), (240, 376)])
    zoom: tuple[float, float] = (0.6, 1.4)  # scale of the stored image before the crop (log-uniform)
    device: str = "cpu"
    seed: int = 0
    checkpoint_every: int = 500
    workers: int = 0             # DataLoader processes preparing batches (0: in this process)


def _load_gray(paths: list[Path]) -> list[np.ndarray]:
    images = []
    for path in paths:
        image, _native = decode_image(np.fromfile(str(path), dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is not None:  # an unreadable file is skipped, as toolkit label does
            images.append(image)
    if not images:
        raise ToolkitError("no readable image among the distillation images")
    return images


def _view(image: np.ndarray, size: tuple[int, int], rng: np.random.Generator, zoom: tuple[float, float]) -> np.ndarray:
    """A random crop of ``size`` (height, width) of ``image`` resized by a log-uniform zoom, mirrored at random;
    an image smaller than the crop is scaled up to cover it."""
    height, width = size
    factor = math.exp(rng.uniform(math.log(zoom[0]), math.log(zoom[1])))
    factor = max(factor, height / image.shape[0], width / image.shape[1])
    scaled = cv2.resize(image, (max(width, round(image.shape[1] * factor)), max(height, round(image.shape[0] * factor))),
                        interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
    top = int(rng.integers(0, scaled.shape[0] - height + 1))
    left = int(rng.integers(0, scaled.shape[1] - width + 1))
    crop = scaled[top : top + height, left : left + width]
    return crop[:, ::-1] if rng.random() < 0.5 else crop


def make_batch(images: list[np.ndarray], step: int, config: SlimDistillConfig, augment: AugmentConfig) -> torch.Tensor:
    """Batch ``step``: [B, 1, H, W] in [0, 1], a pure function of (config.seed, step); sizes cycle with the step."""
    size = config.sizes[step % len(config.sizes)]
    rng = np.random.default_rng([config.seed, step])
    generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
    views = []
    for index in rng.integers(0, len(images), config.batch):
        view = torch.from_numpy(np.ascontiguousarray(_view(images[index], size, rng, config.zoom))).float()[None] / 255.0
        views.append(photometric_augment(view, augment, generator))
    return torch.stack(views)


class _Batches(torch.utils.data.Dataset):
    """Batch ``step`` of `make_batch` as a dataset item, so DataLoader workers prepare batches ahead."""

    def __init__(self, images: list[np.ndarray], config: SlimDistillConfig) -> None:
        self.images, self.config, self.augment = images, config, AugmentConfig()

    def __len__(self) -> int:
        return self.config.steps

    def __getitem__(self, step: int) -> torch.Tensor:
        return make_batch(self.images, step, self.config, self.augment)


def _learning_rate(config: SlimDistillConfig, step: int, total: int) -> float:
    return warmup_cosine(config.lr, step, total, min(200, total // 10), config.lr_final_fraction)


def distill_slim(student: FeatureNet, teacher: nn.Module, image_dir: str | Path, config: SlimDistillConfig,
                 save=None, log=print) -> list[dict]:
    """Train ``student`` to reproduce ``teacher``'s dense heads; returns the loss log (one row per 50 steps).

    BatchNorm trains (its statistics follow the new architecture); the teacher stays in eval mode.
    ``save(student, step)``, when given, is called every ``checkpoint_every`` steps and at the end.
    """
    device = torch.device(config.device)
    images = _load_gray(find_images(image_dir))
    batches = torch.utils.data.DataLoader(_Batches(images, config), batch_size=None, shuffle=False,
                                          num_workers=config.workers, pin_memory=device.type == "cuda",
                                          persistent_workers=config.workers > 0)
    strategies = train_with_grid_sample([student, teacher])
    teacher = teacher.to(device).eval().requires_grad_(False)
    student = student.to(device).train().requires_grad_(True)
    optimizer = torch.optim.Adam(student.parameters(), lr=config.lr)
    total, began, rows, running = config.steps, time.perf_counter(), [], []
    for step, inputs in enumerate(batches):
        if step == 10:
            warm = time.perf_counter()  # workers started, kernels chosen: the pace from here on is the run's
        if step == 40 and config.minutes > 0:  # fit the schedule to the time budget
            total, pace = steps_within(config.minutes, config.steps, step, began, warm, 30)
            log(f"{pace * 1000:.0f} ms a step: {total} steps in {config.minutes:g} min")
        if step >= total:
            break
        for group in optimizer.param_groups:
            group["lr"] = _learning_rate(config, step, total)
        inputs = inputs.to(device, non_blocking=True)
        with torch.no_grad():
            target = teacher(inputs)
        loss = distillation_loss(student(inputs), target, config.temperature)
        running.append(optimiser_step(optimizer, loss, step, "slim distillation"))
        log_losses(rows, running, step, 50, _learning_rate(config, step, total), began, log)
        if save is not None and (step + 1) % config.checkpoint_every == 0:
            save(student, step + 1)
    student.eval().requires_grad_(False)
    restore_sampling(strategies)  # the caller's models sample as they did before
    if save is not None:
        save(student, min(total, config.steps))
    return rows


def main(argv: list[str] | None = None) -> int:
    """python -m toolkit.compression.slim --checkpoint C --ratio R --images DIR -o OUT.safetensors [--device cuda]"""
    import argparse

    from models.checkpoint import checkpoint_metadata, load_checkpoint, save_checkpoint
    from models.weights import resolve_checkpoint

    parser = argparse.ArgumentParser(prog="python -m toolkit.compression.slim", description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="default-relu")
    parser.add_argument("--ratio", type=float, default=0.25, help="share of channels removed per group")
    parser.add_argument("--images", type=Path, required=True)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--minutes", type=float, default=0.0)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--workers", type=int, default=0, help="processes preparing batches")
    parser.add_argument("--student", help="start from this checkpoint (a stride-2 stem) instead of pruning the teacher")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    teacher, info = load_checkpoint(resolve_checkpoint(args.checkpoint))
    if args.student:
        student = load_checkpoint(args.student)[0]
    else:
        from toolkit.compression.prune import prune_channels  # torch-pruning: only where the student is made

        student = restem(prune_channels(teacher, args.ratio)) if args.ratio > 0 else restem(teacher)
    config = SlimDistillConfig(steps=args.steps, minutes=args.minutes, batch=args.batch, lr=args.lr, device=args.device,
                               workers=args.workers)
    def count_parameters(model: nn.Module) -> int:
        return sum(p.numel() for p in model.parameters())

    print(f"teacher {count_parameters(teacher):,} parameters, student {count_parameters(student):,} "
          f"(widths {student.config.widths}, heads {student.config.head_channels}, stem stride 2)", flush=True)
    if args.output.suffix != ".safetensors":
        raise ToolkitError(f"-o must name a .safetensors checkpoint, got {args.output}")
    if args.output.exists() and "slim_distillation" not in (checkpoint_metadata(args.output) or {}):
        raise ToolkitError(f"{args.output} exists and was not written by this command: it is never replaced")

    def save(model: FeatureNet, step: int) -> None:  # atomic: a run cut short leaves its last whole checkpoint
        save_checkpoint(model, args.output, {"slim_distillation": {
            "teacher": Path(info.path).name, "teacher_sha256": info.sha256, "ratio": args.ratio, "step": step,
            "batch": config.batch, "lr": config.lr, "sizes": config.sizes, "temperature": config.temperature}})

    distill_slim(student, teacher, args.images, config, save=save, log=lambda text: print(text, flush=True))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    from toolkit.errors import run_module_main

    run_module_main(main)
