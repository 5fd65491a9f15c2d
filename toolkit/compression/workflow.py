"""`toolkit prune` end to end: load, prune (ratio or MAC budget), distil, save, measure before/after."""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from models.checkpoint import checkpoint_metadata, load_checkpoint, save_checkpoint
from models.featurenet import FeatureNet
from toolkit.compression.distill import DistillConfig, DistillResult, distill
from toolkit.compression.images import default_image_dir, load_images
from toolkit.compression.prune import (count_macs, count_parameters, prune_channels, ratio_for_target_macs,
                                       rebuild)
from toolkit.compression.report import Drift, interleaved_median_ms, torch_drift
from toolkit.atomic import FilesClaim, check_output_path, claim_output_files
from toolkit.errors import ToolkitError
from vo_runtime.atomic_file import nan_as_null, write_json_atomic

MEASURE_IMAGES = 8  # drift images; spread over the image folder
MAX_BATCH = 64  # images per distillation step; far more runs out of memory at 240x320 on a CPU


@dataclass
class PruneOptions:
    checkpoint: Path | None
    output: Path
    ratio: float | None = None
    target_macs: int | None = None
    images: Path | None = None
    labels: Path | None = None
    steps: int = 100
    size: tuple[int, int] = (240, 320)
    batch: int = 4
    lr: float = 1e-4
    timing_repeats: int = 20
    force: bool = False
    evaluate: bool = True


@dataclass
class ModelFigures:
    parameters: int
    macs: int
    latency_ms: float  # PyTorch eager, 1 thread, median, timed interleaved with the other model


@dataclass
class PruneReport:
    checkpoint: str
    output: str
    ratio: float
    size: list[int]
    widths_before: dict
    widths_after: dict
    before: ModelFigures
    after: ModelFigures
    drift_pruned: Drift  # right after pruning, before fine-tuning
    drift_distilled: Drift  # after fine-tuning
    distillation: DistillResult
    evaluation: dict[str, dict] = field(default_factory=dict)  # "before"/"after" -> toolkit eval summary
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def evaluation_metrics(models: dict[str, FeatureNet], size: tuple[int, int]) -> tuple[dict[str, dict], str]:
    """`toolkit eval` metrics (repeatability, matching score, homography accuracy) of each model on HPatches
    v_dogman and the LOL low->high pairs, and a note saying what was run; ({}, reason) when the evaluation
    package or the data is missing."""
    from export.parity import shared_data_dir

    try:
        from toolkit.evaluation.datasets import read_hpatches, read_registered_pairs
        from toolkit.evaluation.detection import Detector, DetectorConfig
        from toolkit.evaluation.runner import EvalConfig, ImageCache, evaluate_model, summarise
        from toolkit.evaluation.torch_models import detect_with_network
    except ImportError as exc:
        return {}, f"evaluation metrics skipped: the evaluation package does not import ({exc})"
    data = shared_data_dir()
    if data is None or not (data / "hpatches_v_dogman").is_dir() or not (data / "lowlight_pairs").is_dir():
        return {}, "evaluation metrics skipped: ../shared/data/hpatches_v_dogman or lowlight_pairs not found"
    pairs = read_hpatches(data / "hpatches_v_dogman") + read_registered_pairs(data / "lowlight_pairs")
    config, detector_config = EvalConfig(size=size), DetectorConfig()
    images = ImageCache(config.size, config.normalise)
    results = {}
    for label, model in models.items():
        detector = Detector(label, "checkpoint", lambda gray, m=model: detect_with_network(m, gray, detector_config))
        result = evaluate_model(detector, pairs, config, images)
        results[label] = summarise([metrics for _group, metrics in result.pairs.values()])
    return results, f"evaluation metrics: {len(pairs)} pairs (HPatches v_dogman, LOL low->high) at {size[0]}x{size[1]}"


def _is_prune_report(path: Path) -> bool:
    try:
        report = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(report, dict) and {"widths_before", "widths_after", "ratio"} <= set(report)


def _is_pruned_checkpoint(path: Path) -> bool:
    metadata = checkpoint_metadata(path)
    return metadata is not None and "pruning" in metadata


def check_prune_output(output: Path, checkpoint: Path, force: bool) -> None:
    """The pruned checkpoint and its ``.json`` report may replace only an earlier prune's (with ``force``),
    never the source checkpoint or any other file."""
    check_output_path(output)
    if output.suffix != ".safetensors":
        raise ToolkitError(f"output must be a .safetensors checkpoint, got {output}")
    if output.resolve() == checkpoint.resolve():
        raise ToolkitError(f"-o {output} is the checkpoint being pruned: pruning never replaces its source")
    for path, is_own, what in ((output, _is_pruned_checkpoint, "a checkpoint written by toolkit prune"),
                               (report_path(output), _is_prune_report, "a report written by toolkit prune")):
        if not (path.exists() or path.is_symlink()):
            continue
        if not path.is_file() or not is_own(path):
            raise ToolkitError(f"refusing to overwrite {path}: it is not {what}")
        if not force:
            raise ToolkitError(f"{path} exists; pass --force to replace it")


def _check_numbers(options: PruneOptions) -> None:
    """Refuse out-of-range settings before any file is read."""
    if (options.ratio is None) == (options.target_macs is None):
        raise ToolkitError("give exactly one of --ratio and --target-macs")
    if options.ratio is not None and not 0.0 < options.ratio < 1.0:  # NaN fails too
        raise ToolkitError(f"--ratio must be in (0, 1), got {options.ratio}")
    if options.target_macs is not None and options.target_macs <= 0:
        raise ToolkitError(f"--target-macs must be positive, got {options.target_macs}")
    if options.steps < 0:
        raise ToolkitError(f"--steps must be >= 0, got {options.steps}")
    if not 1 <= options.batch <= MAX_BATCH:
        raise ToolkitError(f"--batch must be between 1 and {MAX_BATCH}, got {options.batch}")
    if not (math.isfinite(options.lr) and options.lr > 0):
        raise ToolkitError(f"--lr must be a positive number, got {options.lr}")
    if options.labels is not None and options.images is None:
        raise ToolkitError("--labels needs --images (the folder the labels were made for)")


def default_output(checkpoint: Path, ratio: float) -> Path:
    return checkpoint.with_name(f"{checkpoint.stem}-pruned{round(ratio * 100)}.safetensors")


def _widths(model: FeatureNet) -> dict:
    return {"widths": list(model.config.widths), "head_channels": model.config.head_channels}


def prune_checkpoint(options: PruneOptions, log=print, progress: bool = True) -> PruneReport:
    """Prune, distil and save; returns the before/after report (also stored in the checkpoint metadata)."""
    _check_numbers(options)
    from models.weights import WEIGHTS_DIR, resolve_checkpoint

    checkpoint = resolve_checkpoint(options.checkpoint)
    teacher, info = load_checkpoint(checkpoint)
    if not isinstance(teacher, FeatureNet):
        raise ToolkitError(f"pruning supports featurenet checkpoints; {checkpoint} is {info.arch}")
    images = Path(options.images) if options.images else default_image_dir()
    measure, _ = load_images(images, MEASURE_IMAGES, options.size)  # fails early on an image-less folder

    if options.target_macs is not None:
        search = ratio_for_target_macs(teacher, options.target_macs, options.size)
        ratio = search.ratio
        log(f"ratio {ratio:.3f} meets {options.target_macs:,} MACs ({search.macs:,} at {options.size[0]}x{options.size[1]})")
    else:
        ratio = options.ratio
    output = Path(options.output) if options.output else default_output(checkpoint, ratio)
    if not options.output and checkpoint.resolve().parent == WEIGHTS_DIR:
        output = Path.cwd() / output.name  # never write beside the shipped weights, inside the package
    with claim_output_files([output, report_path(output)]) as claim:
        check_prune_output(output, checkpoint, options.force)
        return _prune_into(claim, options, checkpoint, teacher, info, images, measure, ratio, output, log, progress)


def report_path(output: Path) -> Path:
    """The JSON report written beside a pruned checkpoint."""
    return output.with_suffix(".json")


def _prune_into(claim: FilesClaim, options: PruneOptions, checkpoint: Path, teacher: FeatureNet, info, images: Path,
                measure, ratio: float, output: Path, log, progress: bool) -> PruneReport:
    """Prune, distil and measure, then write the checkpoint and its report (``claim`` held by the caller)."""
    student = prune_channels(teacher, ratio)
    log(f"pruned {ratio:.0%} of channels: widths {teacher.config.widths} -> {student.config.widths}, "
        f"heads {teacher.config.head_channels} -> {student.config.head_channels}")
    drift_pruned = torch_drift(teacher, student, measure)
    config = DistillConfig(steps=options.steps, batch=options.batch, lr=options.lr, size=options.size)
    result = distill(student, teacher, images, config, options.labels, progress=progress)
    student = rebuild(student)  # a fresh FeatureNet from the new config: what load_checkpoint will build
    drift_distilled = torch_drift(teacher, student, measure)

    example = torch.from_numpy(measure[:1])
    with torch.no_grad():
        latency = interleaved_median_ms({"before": lambda: teacher(example), "after": lambda: student(example)},
                                        repeats=options.timing_repeats, warmup=3)
    evaluation, evaluation_note = ({}, "evaluation metrics skipped (--no-eval)")
    if options.evaluate:
        evaluation, evaluation_note = evaluation_metrics({"before": teacher, "after": student}, options.size)
    report = PruneReport(
        checkpoint=str(checkpoint), output=str(output), ratio=ratio, size=list(options.size),
        widths_before=_widths(teacher), widths_after=_widths(student),
        before=ModelFigures(count_parameters(teacher), count_macs(teacher, options.size), latency["before"]),
        after=ModelFigures(count_parameters(student), count_macs(student, options.size), latency["after"]),
        drift_pruned=drift_pruned, drift_distilled=drift_distilled, distillation=result, evaluation=evaluation,
        notes=["accuracy proxy: drift from the unpruned model's own outputs on real images (no trained weights yet)",
               f"latency: PyTorch eager, {torch.get_num_threads()} thread(s), median", evaluation_note],
    )
    metadata = {**info.metadata, "pruned_from": {"checkpoint": Path(info.path).name, "sha256": info.sha256},
                "pruning": json.loads(json.dumps(report.to_dict()))}
    claim.check_unchanged()
    save_checkpoint(student, output, metadata)
    write_json_atomic(report_path(output), nan_as_null(report.to_dict()))  # NaN: not measured (--steps 0)
    return report


def format_report(report: PruneReport) -> str:
    """A before/after table for the terminal."""
    b, a = report.before, report.after
    rows = [
        ("parameters", f"{b.parameters:,}", f"{a.parameters:,}", f"{a.parameters / b.parameters:.2f}x"),
        (f"MACs @ {report.size[0]}x{report.size[1]}", f"{b.macs:,}", f"{a.macs:,}", f"{a.macs / b.macs:.2f}x"),
        ("latency ms (torch)", f"{b.latency_ms:.1f}", f"{a.latency_ms:.1f}", f"{a.latency_ms / b.latency_ms:.2f}x"),
    ]
    lines = [f"{'':24}{'before':>14}{'after':>14}{'ratio':>9}"]
    lines += [f"{name:24}{x:>14}{y:>14}{r:>9}" for name, x, y, r in rows]
    for label, drift in (("pruned", report.drift_pruned), ("distilled", report.drift_distilled)):
        lines.append(f"drift vs unpruned ({label}): {drift.keypoints_unchanged:.1%} keypoints unchanged, "
                     f"descriptor cosine {drift.descriptor_cosine:.4f}, heatmap mean abs error {drift.heatmap_mean_abs:.2e}")
    if report.evaluation:
        before, after = report.evaluation["before"], report.evaluation["after"]
        for key in ("repeatability", "matching_score", "homography_3px"):
            lines.append(f"{key + ' (eval)':24}{before[key]:>14.3f}{after[key]:>14.3f}")
    d = report.distillation
    lines.append(f"distillation: {d.steps} steps in {d.seconds:.0f} s, loss {d.first_loss:.4f} -> {d.last_loss:.4f}"
                 + (" (with the training loss on labelled pairs)" if d.used_labels else ""))
    return "\n".join(lines)
