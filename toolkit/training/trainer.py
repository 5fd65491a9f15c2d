"""Training loop: warped pairs -> the recipe's losses -> Adam with a warm-up + cosine schedule; atomic
checkpoints, exact resume, validation, DistributedDataParallel under torchrun (NCCL on GPUs, gloo on CPUs),
float16 autocast on CUDA, bfloat16 autocast on a CPU that computes bfloat16 natively (`cpu_precision`).

Recipes (``TrainConfig.recipe``): ``distill`` (teacher keypoints + descriptor distillation + InfoNCE,
multi-scale views; `toolkit.training.distill_losses`) and ``paper`` (SuperPoint's CE + hinge).

Run folder::

    RUN/config.json          the full TrainConfig plus the image/label folders (and, on a CPU, its precision)
    RUN/train_state.pt       model + projection + optimizer + scaler + RNG + step (the resume point)
    RUN/last.safetensors     latest weights; RUN/best.safetensors highest validation matching score
    RUN/log.csv, RUN/val.csv per-step losses and validation metrics; RUN/loss.png, RUN/val.png their curves
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import time
from dataclasses import asdict
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from models.checkpoint import build_model, save_checkpoint
from models.featurenet import widen_pixel_window
from models.deform import set_deform_strategy
from models.keypoints import model_refinement
from toolkit.errors import ToolkitError
from vo_runtime.errors import first_line
from vo_runtime.machine import check_thread_count, physical_memory_bytes
from toolkit.training.config import TrainConfig, config_from_dict, read_config_file  # noqa: F401 (re-exported)
from toolkit.training.cpu_precision import cpu_computes_bf16
from toolkit.training.distill_losses import DescriptorProjection, distill_loss
from toolkit.training.distill_pairs import DistillPairs
from toolkit.training.freezing import freeze_outside, hold_frozen_in_eval
from toolkit.training.label_store import LabelStore, write_atomic
from toolkit.training.losses import superpoint_loss
from toolkit.training.pairs import StepBatchSampler, WarpedPairs, load_labelled_images, split_train_val
from toolkit.training.run_log import append_csv, plot_loss_curve, plot_validation_curve, truncate_csv
from toolkit.training.validation import validate
from vo_runtime.progress import progress_bar

STATE_NAME = "train_state.pt"
LOG_FIELDS = ["step", "loss", "detector_loss", "descriptor_loss", "lr", "seconds_per_step", "position_loss"]
VAL_FIELDS = ["step", "val_loss", "repeatability", "localisation_error", "nn_map", "matching_score"]


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


def _save_state(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getvalue())


def _load_state(path: Path, why: str = "cannot resume") -> dict:
    if not path.is_file():
        raise ToolkitError(f"{why}: no checkpoint {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # any unpickling/zip error means the same thing to the user
        raise ToolkitError(f"{why}: {path} is corrupt or unreadable ({type(exc).__name__})") from None


def dense_to_depthwise_deform(state: dict, model: torch.nn.Module) -> dict:
    """``state`` with a dense deformable kernel replaced by its `separable_from_dense` stand-in when ``model``
    has a depthwise deformable conv (so a depthwise model starts from trained dense weights); else ``state``."""
    from models.deform import separable_from_dense

    prefix = "deform."
    target = getattr(getattr(model, "deform", None), "pointwise", None)
    if target is None or f"{prefix}conv.weight" not in state or f"{prefix}pointwise.weight" in state:
        return state
    converted = separable_from_dense(state[f"{prefix}conv.weight"], state.get(f"{prefix}conv.bias"))
    return {**state, **{prefix + key: value for key, value in converted.items()}}


def grow_context_blocks(state: dict, model: torch.nn.Module) -> dict:
    """``state`` completed with ``model``'s freshly initialised context blocks when ``state`` has none (a
    checkpoint from before they were added). New blocks start as the identity (`InvertedResidualBlock`),
    so the grown network computes what the source did; blocks present in ``state`` are used as they are."""
    own = {key: value for key, value in model.state_dict().items() if key.startswith("context.")}
    if not own or any(key.startswith("context.") for key in state):
        return state
    return {**state, **own}


def adapt_state(state: dict, model: torch.nn.Module) -> dict:
    """A state dict from an older layout made to fit ``model``: dense deformable kernels to depthwise ones,
    missing context blocks grown as the identity, an 8x8 cell-pixel head widened to a window."""
    return widen_pixel_window(grow_context_blocks(dense_to_depthwise_deform(state, model), model), model)


def initialise_from(source: str, model: torch.nn.Module, projection: torch.nn.Module | None) -> None:
    """Load starting weights for a new run (fresh optimizer and schedule: a fine-tune, not a resume).

    ``source`` is another run's folder (its ``train_state.pt``: the model and, for distill, the trained
    projection, so the descriptor loss does not restart from a random projection) or an EdgeFeat
    ``.safetensors`` checkpoint (the model only).
    """
    from models.checkpoint import CheckpointError, load_checkpoint

    path = Path(source)
    try:
        if path.is_dir():
            state = _load_state(path / "train_state.pt", "cannot initialise")
            model.load_state_dict(adapt_state(state["model"], model))
            if projection is not None and state.get("projection"):
                projection.load_state_dict(state["projection"])
        else:
            loaded, _ = load_checkpoint(path)
            model.load_state_dict(adapt_state(loaded.state_dict(), model))
    except CheckpointError as exc:
        raise ToolkitError(f"cannot initialise: {exc}") from None
    except (KeyError, RuntimeError) as exc:
        raise ToolkitError(f"cannot initialise from {path}: its weights do not match this model "
                           f"({str(exc).splitlines()[0][:120]})") from None


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
            config = config_from_dict(json.loads(config_path.read_text(encoding="utf-8"))["train"])
        except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
            raise ToolkitError(f"cannot resume: {config_path} is unreadable ({first_line(exc)})") from None
        if batch is not None and batch != config.batch:
            raise ToolkitError(f"cannot change --batch on --resume (the run in {run} uses {config.batch})")
    else:
        check_new_run_folder(run)
    if steps is not None:
        config.steps = steps
    if batch is not None:
        config.batch = batch
    if config.steps < 1 or config.batch < 1:
        raise ToolkitError("--steps and --batch must be at least 1")
    if config.threads:  # 0: torch's own choice
        check_thread_count(config.threads, "threads", ToolkitError)
    try:  # fail before any process group or file exists
        build_model(config.arch, config.model)
    except (TypeError, ValueError) as exc:
        raise ToolkitError(f"config model settings do not fit arch {config.arch}: {exc}") from None
    return config


def check_new_run_folder(run: Path) -> None:
    """A new run starts only in an absent or empty folder: a run folder is continued with --resume (also one
    stopped before its first checkpoint, which then starts again from step 0), and any other folder is the
    user's, never written into."""
    if run.is_symlink() or (run.exists() and not run.is_dir()):
        raise ToolkitError(f"--out {run} exists and is not a folder")
    if not run.exists() or not any(run.iterdir()):
        return
    if (run / "config.json").exists() or (run / STATE_NAME).exists():
        stopped = "" if (run / STATE_NAME).exists() else " (stopped before its first checkpoint: --resume starts it again)"
        raise ToolkitError(f"{run} already holds a training run{stopped}: pass --resume to continue it, or choose "
                           "another --out")
    raise ToolkitError(f"--out {run} is not empty and holds no training run: refusing to write into it; choose a "
                       "new or empty folder")


def check_batch_fits(config: TrainConfig, size: tuple[int, int], world: int) -> None:
    """A step's pairs must fit in this machine's memory: their input views alone take 2 x H x W float32 each
    (activations many times more), and a batch of 10^8 pairs would allocate without end before the first step."""
    memory = physical_memory_bytes()
    pixels = max(h * w for h, w in config.scales.sizes) if config.recipe == "distill" else size[0] * size[1]
    needed = config.batch * world * 2 * pixels * 4
    if memory is not None and needed > memory:
        raise ToolkitError(f"--batch {config.batch}: the pairs' input views alone need {needed / 1e9:,.0f} GB, more than "
                           f"this machine's {memory / 1e9:,.0f} GB of memory; use a smaller --batch")


def train(config: TrainConfig, images: str, labels: str, run: str | Path, resume: bool = False) -> dict:
    """Train per ``config`` (already resolved by `resolve_config`).

    Returns:
        final step, counts of images, the last logged losses, the last validation metrics and the model.
    """
    run = Path(run)
    store = LabelStore.open(labels)
    detail = config.scales.detail if config.recipe == "distill" else 1.0
    records, unreadable = load_labelled_images(images, store, detail)
    rank, world, device = init_distributed(config.device)
    try:
        return _train(config, store, records, unreadable, images, labels, run, resume, rank, world, device)
    finally:
        if world > 1 and dist.is_initialized():
            dist.destroy_process_group()


def _data(config: TrainConfig, store: LabelStore, images: list, seed: int, world: int, validation: bool):
    """The recipe's dataset over ``images``: training pairs, or fixed-size un-augmented validation pairs."""
    if config.recipe == "distill":
        fixed = tuple(store.size) if validation else None
        return DistillPairs(images, store, config.scales, config.homography, None if validation else config.augment,
                            seed, config.batch * world, fixed)
    return WarpedPairs(images, store.size, config.homography, None if validation else config.augment, seed)


def _train(config, store, records, unreadable, images, labels, run, resume, rank, world, device) -> dict:
    train_images, val_images = split_train_val(records, config.val_fraction, config.val_max_images)
    check_batch_fits(config, store.size, world)
    if config.threads:
        torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    model = build_model(config.arch, config.model).to(device)
    set_deform_strategy(model, "grid_sample" if config.train_sampler == "grid_sample" else "torch")
    distilling = config.recipe == "distill"
    if distilling and not hasattr(model.config, "descriptor_dim"):
        raise ToolkitError(f"the distill recipe trains featurenet, not {config.arch}")
    # Datasets first: a recipe that cannot run on these labels fails before anything is written.
    train_set = _data(config, store, train_images, config.seed, world, validation=False)
    val_set = _data(config, store, val_images, config.seed + 1, 1, validation=True)
    projection = None
    if distilling:  # the teacher's width comes from its stored maps (128 for alike-n)
        teacher_dim = int(store.get_descriptors(train_images[0].sha256).shape[0])
        projection = DescriptorProjection(model.config.descriptor_dim, teacher_dim).to(device)
    freeze_outside(model, config.train_only)
    parameters = [p for p in model.parameters() if p.requires_grad]
    parameters += list(projection.parameters()) if projection is not None else []
    optimizer = torch.optim.Adam(parameters, lr=config.lr)
    use_amp = config.amp and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda") if use_amp else None
    if use_amp:
        keep_deformable_in_float32(model)
    step, best_score = 0, -1.0
    state_path = run / STATE_NAME
    restart = resume and not state_path.exists()  # stopped before its first checkpoint: step 0, the run's config
    if config.init and (not resume or restart):
        initialise_from(config.init, model, projection)
    if resume and not restart:
        state = _load_state(state_path)
        try:
            model.load_state_dict(state["model"])
            if projection is not None:
                projection.load_state_dict(state["projection"])
            optimizer.load_state_dict(state["optimizer"])
            if scaler is not None and state.get("scaler"):
                scaler.load_state_dict(state["scaler"])
            step, best_score = int(state["step"]), float(state["best_score"])
            torch.set_rng_state(state["torch_rng"])
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:
            raise ToolkitError(f"cannot resume: {state_path} does not match this run ({str(exc).splitlines()[0][:120]})") from None
    cpu_bfloat16 = device.type == "cpu" and config.cpu_bf16 and cpu_computes_bf16()  # emulated bfloat16 is 4.6x slower
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
        if not resume:
            header = {"train": asdict(config), "images": str(images), "labels": str(labels), "teacher": store.teacher}
            if device.type == "cpu":  # what cpu_bf16 came to on this machine
                header["cpu_precision"] = "bfloat16" if cpu_bfloat16 else "float32"
            write_atomic(run / "config.json", json.dumps(header, indent=2).encode())
        truncate_csv(run / "log.csv", LOG_FIELDS, step)
        truncate_csv(run / "val.csv", VAL_FIELDS, step)
    _barrier(world)

    if world > 1:
        network = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    else:
        network = model
    workers = config.num_workers if config.num_workers >= 0 else (4 if device.type == "cuda" else 0)
    loader = torch.utils.data.DataLoader(
        train_set,
        batch_sampler=StepBatchSampler(step, config.steps, config.batch, rank, world),
        num_workers=workers,
        pin_memory=device.type == "cuda",
    )
    val_loader = torch.utils.data.DataLoader(
        val_set, batch_sampler=[list(range(i, min(i + config.batch, len(val_set)))) for i in range(0, len(val_set), config.batch)]
    )

    refinement = model_refinement(model)  # the position loss trains the refinement the export will run

    def loss_fn(outputs_a, outputs_b, batch, generator=None):
        if distilling:
            return distill_loss(outputs_a, outputs_b, batch, projection, config.distill, generator, refinement)
        return superpoint_loss(outputs_a, outputs_b, batch, config.loss, generator)

    if use_amp:
        autocast = lambda: torch.autocast("cuda", dtype=torch.float16)  # noqa: E731
    elif cpu_bfloat16:
        autocast = lambda: torch.autocast("cpu", dtype=torch.bfloat16)  # noqa: E731
    else:
        autocast = contextlib.nullcontext
    last: dict[str, float] = {}
    metrics: dict[str, float] = {}
    model.train()
    hold_frozen_in_eval(model, config.train_only)
    tick = time.perf_counter()
    bar = progress_bar(total=config.steps, initial=step, desc="train", unit="step", enabled=rank == 0)
    for batch in loader:
        batch = {key: value.to(device, non_blocking=True) for key, value in batch.items()}
        count = batch["image_a"].shape[0]
        learning_rate = config.learning_rate(step)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate
        generator = torch.Generator().manual_seed(config.seed * 65_537 + step)
        with autocast():
            outputs = network(torch.cat([batch["image_a"], batch["image_b"]]))
            outputs_a = {key: value[:count] for key, value in outputs.items()}
            outputs_b = {key: value[count:] for key, value in outputs.items()}
            losses = loss_fn(outputs_a, outputs_b, batch, generator)
        optimizer.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(losses["loss"]).backward()
            scaler.step(optimizer)
            scaler.update()
        else:
            losses["loss"].backward()
            optimizer.step()
        step += 1
        bar.update(1)
        if step % config.log_every == 0 or step == config.steps:
            position = losses.get("position_loss", losses["detector_loss"] * 0.0)
            values = torch.stack([losses["loss"].detach(), losses["detector_loss"], losses["descriptor_loss"], position]).float()
            if world > 1:
                dist.all_reduce(values)
                values /= world
            now = time.perf_counter()
            last = {
                "step": step, "loss": float(values[0]), "detector_loss": float(values[1]),
                "descriptor_loss": float(values[2]), "lr": learning_rate,
                "seconds_per_step": (now - tick) / config.log_every if step % config.log_every == 0 else 0.0,
                "position_loss": float(values[3]),
            }
            tick = now
            bar.set_postfix(loss=f"{last['loss']:.3f}")
            if rank == 0:
                append_csv(run / "log.csv", LOG_FIELDS, last)
        if rank == 0 and (step % config.validate_every == 0 or step == config.steps):
            with autocast():
                metrics = {"step": step, **validate(model, val_loader, device, loss_fn, config.validation)}
            hold_frozen_in_eval(model, config.train_only)  # validate() switched the model back to training
            append_csv(run / "val.csv", VAL_FIELDS, metrics)
            plot_validation_curve(run / "val.csv", run / "val.png")
            # The best checkpoint is the one that matches best: detector and descriptor both count.
            if metrics["matching_score"] > best_score:
                best_score = metrics["matching_score"]
                save_checkpoint(model, run / "best.safetensors", {"step": step, **metrics})
        if rank == 0 and (step % config.checkpoint_every == 0 or step == config.steps):
            save_checkpoint(model, run / "last.safetensors", {"step": step})
            _save_state(state_path, {
                "step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "projection": projection.state_dict() if projection is not None else {},
                "scaler": scaler.state_dict() if scaler is not None else {}, "torch_rng": torch.get_rng_state(),
                "best_score": best_score,
            })
        if step % config.validate_every == 0 or step % config.checkpoint_every == 0:
            _barrier(world)
            tick = time.perf_counter()  # seconds_per_step measures training, not validation or saving
    bar.close()
    if rank == 0 and (run / "log.csv").exists():
        plot_loss_curve(run / "log.csv", run / "loss.png")
    return {"step": step, "rank": rank, "unreadable": unreadable, "train_images": len(train_images), "val_images": len(val_images),
            "last": last, "validation": metrics, "model": model}
