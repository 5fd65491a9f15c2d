"""What compression cost: output drift against the uncompressed model, and latency measured side by side.

No trained weights exist yet, so accuracy is measured as drift from the uncompressed model's own outputs
(a stated proxy for the evaluation metrics): heatmap error, share of keypoints unchanged, descriptor cosine.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import onnx
import torch
from torch import nn

from models.keypoints import extract_keypoints, heatmap_from_logits
from toolkit.errors import ToolkitError
from vo_runtime.errors import first_line

KEYPOINT_BUDGET = 500


@dataclass
class Drift:
    """Candidate vs reference on the same images. ``None`` where the graph does not expose the quantity."""

    images: int
    keypoints_unchanged: float  # fraction of the reference's valid keypoints found at the same pixel
    descriptor_cosine: float  # mean cosine between descriptors (at shared keypoints, or per cell for dense maps)
    heatmap_mean_abs: float | None = None
    heatmap_max_abs: float | None = None
    scores_max_abs: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def _same_pixels(reference: np.ndarray, candidate: np.ndarray) -> tuple[list[int], list[int]]:
    """Indices (ref, cand) of keypoints ([N, 2] x, y) that land on the same integer pixel."""
    lookup = {(int(round(x)), int(round(y))): i for i, (x, y) in enumerate(candidate)}
    pairs = [(i, lookup[key]) for i, key in enumerate((int(round(x)), int(round(y))) for x, y in reference) if key in lookup]
    return [p[0] for p in pairs], [p[1] for p in pairs]


def torch_drift(reference: nn.Module, candidate: nn.Module, images: np.ndarray, budget: int = KEYPOINT_BUDGET) -> Drift:
    """Drift of ``candidate`` from ``reference`` (PyTorch FeatureNets) on ``images`` [N, 1, H, W] in [0, 1]."""
    found = total = 0
    heat_abs, heat_max, cosines = [], 0.0, []
    with torch.no_grad():
        for image in images:
            tensor = torch.from_numpy(image[None])
            ref, cand = reference.eval()(tensor), candidate.eval()(tensor)
            ref_heat, cand_heat = heatmap_from_logits(ref["logits"]), heatmap_from_logits(cand["logits"])
            heat_abs.append(float((ref_heat - cand_heat).abs().mean()))
            heat_max = max(heat_max, float((ref_heat - cand_heat).abs().max()))
            cosines.append(float((ref["descriptors"] * cand["descriptors"]).sum(1).mean()))
            ref_kp = extract_keypoints(ref["logits"], ref["descriptors"], budget, 4, 0.005, 4)
            cand_kp = extract_keypoints(cand["logits"], cand["descriptors"], budget, 4, 0.005, 4)
            n_ref, n_cand = int(ref_kp["num_valid"][0]), int(cand_kp["num_valid"][0])
            shared, _ = _same_pixels(ref_kp["keypoints"][:n_ref].numpy(), cand_kp["keypoints"][:n_cand].numpy())
            found += len(shared)
            total += n_ref
    return Drift(len(images), found / total if total else 1.0, float(np.mean(cosines)),
                 float(np.mean(heat_abs)), heat_max)


def ort_session(model: onnx.ModelProto | str, threads: int = 1):
    """A CPU onnxruntime session with a fixed thread count (timings on a shared machine need it)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    source = model if isinstance(model, str) else model.SerializeToString()
    try:
        return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several unrelated types
        raise ToolkitError(f"onnxruntime cannot load the model: {first_line(exc)}") from None


def ort_drift(reference, candidate, images: np.ndarray) -> Drift:
    """Drift of one onnxruntime session from another, keypoint graphs (keypoints, scores, descriptors,
    num_valid) or dense graphs (heatmap, descriptors_coarse), on ``images`` [N, 1, H, W]."""
    names = [o.name for o in reference.get_outputs()]
    found = total = 0
    cosines, heat_abs, heat_max, score_max = [], [], 0.0, 0.0
    for image in images:
        feed = {reference.get_inputs()[0].name: image[None]}
        ref = dict(zip(names, reference.run(names, feed)))
        cand = dict(zip(names, candidate.run(names, feed)))
        if "heatmap" in ref:
            diff = np.abs(ref["heatmap"] - cand["heatmap"])
            heat_abs.append(float(diff.mean()))
            heat_max = max(heat_max, float(diff.max()))
            cosines.append(float((ref["descriptors_coarse"] * cand["descriptors_coarse"]).sum(1).mean()))
            continue
        n_ref, n_cand = int(ref["num_valid"][0]), int(cand["num_valid"][0])
        ri, ci = _same_pixels(ref["keypoints"][:n_ref], cand["keypoints"][:n_cand])
        found += len(ri)
        total += n_ref
        if ri:
            cosines.append(float((ref["descriptors"][ri] * cand["descriptors"][ci]).sum(1).mean()))
            score_max = max(score_max, float(np.abs(ref["scores"][ri] - cand["scores"][ci]).max()))
    if "heatmap" in names:
        return Drift(len(images), float("nan"), float(np.mean(cosines)), float(np.mean(heat_abs)), heat_max)
    # No reference keypoints means nothing was compared: that is no evidence of parity (fp16's gate fails on it).
    return Drift(len(images), found / total if total else 0.0, float(np.mean(cosines)) if cosines else 0.0,
                 scores_max_abs=score_max)


def median_ms(run: Callable[[], object], repeats: int = 20, warmup: int = 3) -> float:
    """Median wall time of ``run()`` in milliseconds."""
    for _ in range(warmup):
        run()
    times = []
    for _ in range(repeats):
        tick = time.perf_counter()
        run()
        times.append((time.perf_counter() - tick) * 1e3)
    return statistics.median(times)


def interleaved_median_ms(runs: dict[str, Callable[[], object]], repeats: int = 20, warmup: int = 3) -> dict[str, float]:
    """Median ms of each callable, timed round-robin so machine-load swings hit all of them alike."""
    from toolkit.profiling.latency import time_interleaved

    return {name: statistics.median(values) for name, values in time_interleaved(runs, repeats, warmup).items()}
