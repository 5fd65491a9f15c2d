"""Training loop: warped pairs -> SuperPoint losses -> Adam; atomic checkpoints, exact resume, validation,
DistributedDataParallel under torchrun (NCCL on GPUs, gloo on CPUs), mixed precision on CUDA.

Run folder::

    RUN/config.json          the full TrainConfig plus the image/label folders
    RUN/train_state.pt       model + optimizer + scaler + RNG + step (the resume point, replaced atomically)
    RUN/last.safetensors     latest weights, RUN/best.safetensors lowest validation loss (models.checkpoint)
    RUN/log.csv, RUN/val.csv per-step losses and validation metrics; RUN/loss.png the loss curve
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import time
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from models.checkpoint import build_model, save_checkpoint
from toolkit.errors import ToolkitError
from toolkit.training.augment import AugmentConfig
from toolkit.training.homographies import HomographyConfig
from toolkit.training.label_store import LabelStore, write_atomic
from toolkit.training.losses import LossConfig, superpoint_loss
from toolkit.training.pairs import StepBatchSampler, WarpedPairs, load_labelled_images, split_train_val
from toolkit.training.validation import ValidationConfig, validate

LOG_FIELDS = ["step", "loss", "detector_loss", "descriptor_loss", "lr", "seconds_per_step"]
VAL_FIELDS = ["step", "val_loss", "repeatability", "nn_accuracy"]


@dataclass
class TrainConfig:
    """Everything a run depends on; ``--config FILE`` (JSON or TOML) sets any field, nested by section."""

    arch: str = "featurenet"  # or "superpoint"
    model: dict = field(default_factory=dict)  # FeatureNetConfig / SuperPointConfig fields
    steps: int = 20000
    batch: int = 8  # pairs per step and per process
    lr: float = 1e-4
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
    loss: LossConfig = field(default_factory=LossConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)


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
        elif isinstance(default, tuple):
            value = tuple(value)
        built[name] = value
    return kind(**built)


def config_from_dict(values: dict[str, Any]) -> TrainConfig:
    """Nested dict (e.g. parsed JSON/TOML) -> TrainConfig; unknown keys are an error, missing ones default."""
    return _build_dataclass(TrainConfig, values, "")


def read_config_file(path: str | Path) -> TrainConfig:
    """``.toml`` or ``.json`` file -> TrainConfig."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ToolkitError(f"cannot read config {path}: {exc.strerror}") from None
    try:
        if path.suffix == ".toml":
            import tomllib

            values = tomllib.loads(text)
        else:
            values = json.loads(text)
    except ValueError as exc:
        raise ToolkitError(f"cannot parse config {path}: {exc}") from None
    return config_from_dict(values)


def init_distributed(device: str = "auto") -> tuple[int, int, torch.device]:
    """(rank, world size, device) from torchrun's environment; a single process when there is none."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device not in ("auto", "cuda", "cpu"):
        raise ToolkitError(f"config device must be auto, cuda or cpu, not {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ToolkitError("config asks for device cuda but no CUDA GPU is available")
    cuda = device != "cpu" and torch.cuda.is_available()
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    rank = dist.get_rank() if world > 1 else 0
    if cuda:
        torch.cuda.set_device(local_rank)
        return rank, world, torch.device("cuda", local_rank)
    return rank, world, torch.device("cpu")


def keep_deformable_in_float32(model: torch.nn.Module) -> int:
    """Run every `DeformableConv` of ``model`` in float32 even under autocast; returns how many.

    ``models.deform.deform_conv2d`` computes its gather indices in the input's dtype: in float16 they
    overflow past 2048 (index errors), and sampling positions lose precision. The rest of the network
    keeps mixed precision. The weights and the state dict are unchanged.
    """
    from models.deform import DeformableConv

    count = 0
    for module in model.modules():
        if isinstance(module, DeformableConv) and not getattr(module, "_float32_forward", False):
            original = module.forward

            def forward(x: torch.Tensor, _original=original) -> torch.Tensor:
                with torch.autocast(x.device.type, enabled=False):
                    return _original(x.float())

            module.forward = forward
            module._float32_forward = True
            count += 1
    return count


def _barrier(world: int) -> None:
    if world > 1:
        dist.barrier()


def _truncate_csv(path: Path, fields: list[str], last_step: int) -> None:
    """Keep the header and the rows up to ``last_step`` (rows after the resume point are replayed)."""
    rows = []
    if path.exists():
        with path.open(newline="") as file:
            rows = [row for row in csv.DictReader(file) if int(row["step"]) <= last_step]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(path, buffer.getvalue().encode())


def _append_csv(path: Path, fields: list[str], row: dict) -> None:
    with path.open("a", newline="") as file:
        csv.DictWriter(file, fieldnames=fields).writerow({key: row[key] for key in fields})


def _save_state(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getvalue())


def _load_state(path: Path) -> dict:
    if not path.is_file():
        raise ToolkitError(f"cannot resume: no checkpoint {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any unpickling/zip error means the same thing to the user
        raise ToolkitError(f"cannot resume: {path} is corrupt or unreadable ({type(exc).__name__})") from None


def plot_loss_curve(log_path: Path, png_path: Path) -> None:
    """Loss and its parts against the step, from ``log.csv`` (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with log_path.open(newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        return
    steps = [int(r["step"]) for r in rows]
    figure, axis = plt.subplots(figsize=(6, 3.5), dpi=100)
    for key in ("loss", "detector_loss", "descriptor_loss"):
        axis.plot(steps, [float(r[key]) for r in rows], label=key)
    axis.set_xlabel("step")
    axis.set_ylabel("loss")
    axis.legend()
    axis.grid(alpha=0.3)
    figure.tight_layout()
    tmp = png_path.with_name(f".tmp-{png_path.name}")
    figure.savefig(tmp)
    plt.close(figure)
    os.replace(tmp, png_path)


def resolve_config(
    run: Path, resume: bool, config: TrainConfig, steps: int | None = None, batch: int | None = None
) -> TrainConfig:
    """The config to train with: ``config`` for a new run, the run's own for ``--resume`` (whose total
    ``steps`` may be raised; the batch may not change, it decides which samples each step sees)."""
    config_path = run / "config.json"
    if resume:
        if not config_path.is_file():
            raise ToolkitError(f"cannot resume: {run} holds no training run (no config.json)")
        try:
            config = config_from_dict(json.loads(config_path.read_text())["train"])
        except (OSError, ValueError, KeyError) as exc:
            raise ToolkitError(f"cannot resume: {config_path} is unreadable ({exc})") from None
        if batch is not None and batch != config.batch:
            raise ToolkitError(f"cannot change --batch on --resume (the run in {run} uses {config.batch})")
    elif config_path.exists() or (run / "train_state.pt").exists():
        raise ToolkitError(f"{run} already holds a training run: pass --resume to continue it, or choose another --out")
    if steps is not None:
        config.steps = steps
    if batch is not None:
        config.batch = batch
    if config.steps < 1 or config.batch < 1:
        raise ToolkitError("--steps and --batch must be at least 1")
    try:  # fail before any process group or file exists
        build_model(config.arch, config.model)
    except (TypeError, ValueError) as exc:
        raise ToolkitError(f"config model settings do not fit arch {config.arch}: {exc}") from None
    return config


def train(config: TrainConfig, images: str, labels: str, run: str | Path, resume: bool = False) -> dict:
    """Train per ``config`` (already resolved by `resolve_config`).

    Returns:
        final step, counts of images, the last logged losses, the last validation metrics and the model.
    """
    run = Path(run)
    store = LabelStore.open(labels)
    records, unreadable = load_labelled_images(images, store)
    rank, world, device = init_distributed(config.device)
    try:
        return _train(config, store, records, unreadable, images, labels, run, resume, rank, world, device)
    finally:
        if world > 1 and dist.is_initialized():
            dist.destroy_process_group()


def _train(config, store, records, unreadable, images, labels, run, resume, rank, world, device) -> dict:
    train_images, val_images = split_train_val(records, config.val_fraction, config.val_max_images)
    size = store.size
    torch.manual_seed(config.seed)
    model = build_model(config.arch, config.model).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    use_amp = config.amp and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda") if use_amp else None
    if use_amp:
        keep_deformable_in_float32(model)
    step, best_val_loss = 0, float("inf")
    state_path = run / "train_state.pt"
    if resume:
        state = _load_state(state_path)
        try:
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            if scaler is not None and state.get("scaler"):
                scaler.load_state_dict(state["scaler"])
            step, best_val_loss = int(state["step"]), float(state["best_val_loss"])
            torch.set_rng_state(state["torch_rng"])
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:
            raise ToolkitError(f"cannot resume: {state_path} does not match this run ({str(exc).splitlines()[0][:120]})") from None
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
        if not resume:
            header = {"train": asdict(config), "images": str(images), "labels": str(labels), "teacher": store.teacher}
            write_atomic(run / "config.json", json.dumps(header, indent=2).encode())
        _truncate_csv(run / "log.csv", LOG_FIELDS, step)
        _truncate_csv(run / "val.csv", VAL_FIELDS, step)
    _barrier(world)

    if world > 1:
        network = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    else:
        network = model
    workers = config.num_workers if config.num_workers >= 0 else (4 if device.type == "cuda" else 0)
    train_set = WarpedPairs(train_images, size, config.homography, config.augment, config.seed)
    loader = torch.utils.data.DataLoader(
        train_set,
        batch_sampler=StepBatchSampler(step, config.steps, config.batch, rank, world),
        num_workers=workers,
        pin_memory=device.type == "cuda",
    )
    val_set = WarpedPairs(val_images, size, config.homography, None, config.seed + 1)
    val_loader = torch.utils.data.DataLoader(
        val_set, batch_sampler=[list(range(i, min(i + config.batch, len(val_set)))) for i in range(0, len(val_set), config.batch)]
    )
    autocast = (lambda: torch.autocast("cuda", dtype=torch.float16)) if use_amp else contextlib.nullcontext
    last: dict[str, float] = {}
    metrics: dict[str, float] = {}
    model.train()
    tick = time.perf_counter()
    for batch in loader:
        batch = {key: value.to(device, non_blocking=True) for key, value in batch.items()}
        count = batch["image_a"].shape[0]
        with autocast():
            outputs = network(torch.cat([batch["image_a"], batch["image_b"]]))
        outputs_a = {key: value[:count] for key, value in outputs.items()}
        outputs_b = {key: value[count:] for key, value in outputs.items()}
        generator = torch.Generator().manual_seed(config.seed * 65_537 + step)
        losses = superpoint_loss(outputs_a, outputs_b, batch, config.loss, generator)
        optimizer.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(losses["loss"]).backward()
            scaler.step(optimizer)
            scaler.update()
        else:
            losses["loss"].backward()
            optimizer.step()
        step += 1
        if step % config.log_every == 0 or step == config.steps:
            values = torch.stack([losses["loss"].detach(), losses["detector_loss"], losses["descriptor_loss"]]).float()
            if world > 1:
                dist.all_reduce(values)
                values /= world
            now = time.perf_counter()
            last = {
                "step": step, "loss": float(values[0]), "detector_loss": float(values[1]),
                "descriptor_loss": float(values[2]), "lr": config.lr,
                "seconds_per_step": (now - tick) / config.log_every if step % config.log_every == 0 else 0.0,
            }
            tick = now
            if rank == 0:
                _append_csv(run / "log.csv", LOG_FIELDS, last)
        if rank == 0 and (step % config.validate_every == 0 or step == config.steps):
            metrics = {"step": step, **validate(model, val_loader, device, config.loss, config.validation)}
            _append_csv(run / "val.csv", VAL_FIELDS, metrics)
            if metrics["val_loss"] < best_val_loss:
                best_val_loss = metrics["val_loss"]
                save_checkpoint(model, run / "best.safetensors", {"step": step, **metrics})
        if rank == 0 and (step % config.checkpoint_every == 0 or step == config.steps):
            save_checkpoint(model, run / "last.safetensors", {"step": step})
            _save_state(state_path, {
                "step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "scaler": scaler.state_dict() if scaler is not None else {}, "torch_rng": torch.get_rng_state(),
                "best_val_loss": best_val_loss,
            })
        if step % config.validate_every == 0 or step % config.checkpoint_every == 0:
            _barrier(world)
            tick = time.perf_counter()  # seconds_per_step measures training, not validation or saving
    if rank == 0 and (run / "log.csv").exists():
        plot_loss_curve(run / "log.csv", run / "loss.png")
    return {"step": step, "rank": rank, "unreadable": unreadable, "train_images": len(train_images), "val_images": len(val_images),
            "last": last, "validation": metrics, "model": model}
