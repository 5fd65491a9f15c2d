"""Distillation across lighting: a network taught to see in the dark what it sees in good light.

The VO's dark rows lose to ORB on how precisely the learned keypoints land and how well they match from frame to
frame (docs/vo_euroc.md): in a dark frame the network's detections follow the sensor noise more than the scene.
Here the student sees a crop darkened the way the VO's tests darken a camera (`vo_runtime.lowlight`: a global
gamma, gain and Gaussian noise, or a light riding on the camera with vignetting, shot and read noise and motion
blur), with every parameter drawn from a range around those presets, and learns to reproduce what a frozen teacher
(by default the same weights) outputs on the *clean* crop: the 65-way cell distribution and the dense
descriptors (`distillation_loss`). A share of the crops stays clean, so good light keeps its targets.

BatchNorm stays in eval mode: its running statistics come from the long distillation the weights were made by
(477k crops); a CPU batch of 16 would only make them noisier.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.featurenet import FeatureNet
from toolkit.compression.distill import (distillation_loss, log_losses, optimiser_step, restore_sampling,
                                         steps_within, train_with_grid_sample)
from toolkit.compression.images import find_images
from toolkit.compression.slim import _load_gray, _view
from toolkit.training.config import warmup_cosine
from vo_runtime.lowlight import Darkening, GlobalDark, OnboardLight


@dataclass
class DarkDistillConfig:
    steps: int = 3000            # upper bound; ``minutes`` may stop earlier
    minutes: float = 0.0         # wall-clock budget (0: none); the schedule is fitted to it after 20 steps
    batch: int = 16
    lr: float = 1e-4             # a fine-tune: the weights start trained
    lr_final_fraction: float = 0.05
    temperature: float = 1.0
    sizes: list[tuple[int, int]] = field(default_factory=lambda: [(240, 376), (192, 256), (240, 320)])
    zoom: tuple[float, float] = (0.6, 1.4)
    dark_share: float = 0.75     # crops the student sees darkened; the rest it sees as the teacher does
    onboard_share: float = 0.5   # of the darkened crops, those under an onboard light (the rest: global dark)
    seed: int = 0
    checkpoint_every: int = 100


def random_darkening(rng: np.random.Generator, onboard_share: float) -> Darkening:
    """A darkening drawn around the VO's presets (`vo_runtime.lowlight.PRESETS`: dark = gamma 2, noise 3, gain
    0.3; onboard = its defaults), wide enough that no single preset is what the network learns."""
    if rng.random() < onboard_share:
        return OnboardLight(gamma=rng.uniform(1.3, 2.0), ambient=rng.uniform(0.02, 0.10), spot=rng.uniform(0.4, 0.9),
                            spot_width=rng.uniform(0.2, 0.4), spot_offset=rng.uniform(-0.1, 0.15),
                            vignette=rng.uniform(0.4, 0.8), photons_per_level=rng.uniform(2.0, 8.0),
                            read_sigma=rng.uniform(1.0, 3.0))
    return GlobalDark(gamma=rng.uniform(1.5, 2.6), sigma=rng.uniform(1.0, 5.0), gain=rng.uniform(0.15, 0.5))


def make_pair_batch(images: list[np.ndarray], step: int, config: DarkDistillConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch ``step`` as (clean [B, 1, H, W], student's view [B, 1, H, W]) in [0, 1]; a pure function of
    (config.seed, step). The student's view is the clean crop darkened (``dark_share`` of the crops) or itself."""
    size = config.sizes[step % len(config.sizes)]
    rng = np.random.default_rng([config.seed, step])
    clean, seen = [], []
    for index in rng.integers(0, len(images), config.batch):
        crop = np.ascontiguousarray(_view(images[index], size, rng, config.zoom))
        view = crop
        if rng.random() < config.dark_share:
            view = random_darkening(rng, config.onboard_share)(crop, seed=int(rng.integers(2**31)))
        clean.append(torch.from_numpy(crop).float()[None] / 255.0)
        seen.append(torch.from_numpy(np.ascontiguousarray(view)).float()[None] / 255.0)
    return torch.stack(clean), torch.stack(seen)


def _learning_rate(config: DarkDistillConfig, step: int, total: int) -> float:
    return warmup_cosine(config.lr, step, total, min(50, total // 10), config.lr_final_fraction)


def distill_dark(student: FeatureNet, teacher: nn.Module, images: list[np.ndarray], config: DarkDistillConfig,
                 save=None, log=print) -> list[dict]:
    """Train ``student`` on darkened crops of ``images`` (grey uint8, `_load_gray`) towards ``teacher``'s heads on
    the clean crops; returns the loss log (one row per 20 steps, the mean loss over all crops, dark and clean).
    ``save(student, step)`` every ``checkpoint_every`` steps and at the end."""
    strategies = train_with_grid_sample([student, teacher])
    teacher = teacher.eval().requires_grad_(False)
    student = student.eval().requires_grad_(True)  # eval: BatchNorm keeps its running statistics
    optimizer = torch.optim.Adam(student.parameters(), lr=config.lr)
    total, began, rows, running = config.steps, time.perf_counter(), [], []
    for step in range(config.steps):
        if step == 5:
            warm = time.perf_counter()
        if step == 25 and config.minutes > 0:  # fit the schedule to the time budget
            total, pace = steps_within(config.minutes, config.steps, step, began, warm, 20)
            log(f"{pace:.2f} s a step: {total} steps in {config.minutes:g} min")
        if step >= total:
            break
        for group in optimizer.param_groups:
            group["lr"] = _learning_rate(config, step, total)
        clean, seen = make_pair_batch(images, step, config)
        with torch.no_grad():
            target = teacher(clean)
        loss = distillation_loss(student(seen), target, config.temperature)
        running.append(optimiser_step(optimizer, loss, step, "dark distillation"))
        log_losses(rows, running, step, 20, _learning_rate(config, step, total), began, log)
        if save is not None and (step + 1) % config.checkpoint_every == 0:
            save(student, step + 1)
    student.eval().requires_grad_(False)
    restore_sampling(strategies)
    if save is not None:
        save(student, min(total, config.steps))
    return rows


def held_out_loss(student: nn.Module, teacher: nn.Module, images: list[np.ndarray], config: DarkDistillConfig,
                  batches: int = 4) -> tuple[float, float]:
    """(dark, clean) distillation loss on ``batches`` fixed batches (seed + 10**6): the same crops before and
    after a run, so the two numbers compare."""
    fixed = DarkDistillConfig(**{**config.__dict__, "seed": config.seed + 10**6, "dark_share": 1.0})
    dark, clean = [], []
    with torch.no_grad():
        for step in range(batches):
            crops, seen = make_pair_batch(images, step, fixed)
            target = teacher(crops)
            dark.append(float(distillation_loss(student(seen), target, config.temperature)))
            clean.append(float(distillation_loss(student(crops), target, config.temperature)))
    return float(np.mean(dark)), float(np.mean(clean))


def main(argv: list[str] | None = None) -> int:
    """python -m toolkit.compression.dark_distill --checkpoint C --images DIR -o OUT.safetensors"""
    import argparse

    from models.checkpoint import checkpoint_metadata, load_checkpoint, save_checkpoint
    from models.weights import resolve_checkpoint
    from toolkit.errors import ToolkitError

    parser = argparse.ArgumentParser(prog="python -m toolkit.compression.dark_distill",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="slim-relu", help="the student's start")
    parser.add_argument("--teacher", help="default: the --checkpoint weights, frozen")
    parser.add_argument("--images", type=Path, required=True)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--minutes", type=float, default=0.0)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--dark-share", type=float, default=0.75)
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    args = parser.parse_args(argv)
    if args.output.suffix != ".safetensors":
        raise ToolkitError(f"-o must name a .safetensors checkpoint, got {args.output}")
    if args.output.exists() and "dark_distillation" not in (checkpoint_metadata(args.output) or {}):
        raise ToolkitError(f"{args.output} exists and was not written by this command: it is never replaced")
    if not 0.0 <= args.dark_share <= 1.0 or args.steps < 1 or args.batch < 1 or not math.isfinite(args.lr):
        raise ToolkitError("--dark-share must be in [0, 1], --steps and --batch positive, --lr finite")
    torch.set_num_threads(args.threads)
    student, info = load_checkpoint(resolve_checkpoint(args.checkpoint))
    teacher, teacher_info = load_checkpoint(resolve_checkpoint(args.teacher or args.checkpoint))
    config = DarkDistillConfig(steps=args.steps, minutes=args.minutes, batch=args.batch, lr=args.lr,
                               dark_share=args.dark_share)
    images = _load_gray(find_images(args.images))
    before = held_out_loss(student, teacher, images, config)
    print(f"held-out loss before: dark {before[0]:.4f}, clean {before[1]:.4f}", flush=True)

    def save(model: FeatureNet, step: int) -> None:  # atomic: a run cut short leaves its last whole checkpoint
        save_checkpoint(model, args.output, {"dark_distillation": {
            "start": Path(info.path).name, "start_sha256": info.sha256, "teacher": Path(teacher_info.path).name,
            "teacher_sha256": teacher_info.sha256, "step": step, "batch": config.batch, "lr": config.lr,
            "dark_share": config.dark_share, "sizes": config.sizes}})

    distill_dark(student, teacher, images, config, save=save, log=lambda text: print(text, flush=True))
    after = held_out_loss(student, teacher, images, config)
    print(f"held-out loss after: dark {after[0]:.4f}, clean {after[1]:.4f}", flush=True)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    from toolkit.errors import run_module_main

    run_module_main(main)
