"""`export_artefact`: checkpoint -> verified artefact directory (model.onnx, manifest.json, README.md).

One entry point, per-target choices from the `TargetProfile`, and nothing on disk until every check has
passed: the artefact is assembled in a temporary sibling directory and renamed into place.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import onnx
import torch

from export.block_graphs import block_graphs
from export.half import to_fp16
from export.checks import check_against_profile, require_non_negative_gathers
from export.graphs import DENSE_OUTPUTS, KEYPOINT_OUTPUTS, DenseGraph, KeypointGraph
from export.onnx_export import check_before_writing, export_onnx, op_histogram
from export.parity import MIN_PARITY_KEYPOINTS, default_parity_paths, images_in, measure_parity, prepare_parity_image
from export.readme import artefact_readme
from export.reference import reference_images, write_cpu_references
from models.checkpoint import load_checkpoint
from models.deform import set_deform_strategy
from models.keypoints import is_score_window, model_refinement, parse_refinement
from models.featurenet import set_elu_form
from profiles import TargetProfile, load_profile
from export.errors import ExportError
from profiles.fields import MAX_SIDE, MIN_SIDE
from vo_runtime.artefact import ARTEFACT_FORMAT, MANIFEST_NAME, MODEL_NAME, sha256_file
from vo_runtime.outputs import OutputClaim, OutputKind, claim_output
from vo_runtime.version import __version__

# FP16 weights move scores by ~1e-3, enough to reorder near-tied keypoints at the top-K cut.
MIN_IDENTICAL = {"fp32": 0.99, "fp16": 0.90}


@dataclass
class ExportOptions:
    target: str
    output: Path
    checkpoint: Path | None = None
    input_size: tuple[int, int] | None = None
    precision: str | None = None
    max_keypoints: int | None = None
    nms_radius: int = 4
    score_window: int = 1  # `models.keypoints.keypoint_scores`; 1 = the peak pixel
    refinement: str = ""  # `models.keypoints.parse_refinement` text; "" = the one the checkpoint names
    threshold: float = 0.005
    border: int = 4
    dense: bool = False
    force: bool = False
    parity_images: Path | None = None


# What --force may replace: an artefact this command wrote before, as its listing records (vo_runtime.outputs).
EXPORTED_ARTEFACT = OutputKind("exported-artefact", "an artefact written by toolkit export")


def _resolve(options: ExportOptions, profile: TargetProfile) -> tuple[tuple[int, int], str, int]:
    size = options.input_size or profile.default_input_size
    if size[0] % 8 or size[1] % 8 or min(size) < MIN_SIDE or max(size) > MAX_SIDE:
        raise ExportError(f"input size {size[0]}x{size[1]}: each side must be between {MIN_SIDE} and {MAX_SIDE} "
                           "and divisible by 8")
    precision = options.precision or profile.default_precision
    if precision not in profile.precisions:
        raise ExportError(f"precision {precision} is not available for {profile.name} (choose from {', '.join(profile.precisions)})")
    keypoints = profile.default_max_keypoints if options.max_keypoints is None else options.max_keypoints
    if not 1 <= keypoints <= size[0] * size[1] // 4:
        raise ExportError(f"--max-keypoints must be between 1 and {size[0] * size[1] // 4} at {size[0]}x{size[1]}, got {keypoints}")
    _check_postprocess(options, size)
    return size, precision, keypoints


def _check_postprocess(options: ExportOptions, size: tuple[int, int]) -> None:
    """Refuse settings that leave no keypoints or no valid graph (a NaN threshold also made invalid JSON)."""
    if not (math.isfinite(options.threshold) and 0.0 <= options.threshold < 1.0):
        raise ExportError(f"--threshold is a keypoint probability: it must be in [0, 1), got {options.threshold}")
    if not 0 <= options.border < min(size) // 4:
        raise ExportError(f"--border must be between 0 and {min(size) // 4 - 1} px at {size[0]}x{size[1]}, got {options.border}")
    if not 0 <= options.nms_radius < min(size) // 4:
        raise ExportError(f"--nms-radius must be between 0 and {min(size) // 4 - 1} px at {size[0]}x{size[1]}, "
                           f"got {options.nms_radius}")
    if options.refinement:
        try:
            parse_refinement(options.refinement)
        except ValueError as exc:
            raise ExportError(f"--refine: {exc}") from None
    if not (is_score_window(options.score_window) and options.score_window < min(size) // 4):
        raise ExportError(f"--score-window must be an odd number of pixels between 1 and {min(size) // 4 - 1}, "
                           f"got {options.score_window}")


def export_artefact(options: ExportOptions, log=print) -> Path:
    """Export, verify and write an artefact; returns its directory. Raises `ExportError` on any failure."""
    profile = load_profile(options.target)
    (height, width), precision, max_keypoints = _resolve(options, profile)
    output = Path(options.output)
    inputs = [options.checkpoint, options.parity_images]
    with claim_output(output, EXPORTED_ARTEFACT, options.force, inputs, ExportError) as claim:
        _export_into(claim, options, profile, (height, width), precision, max_keypoints, log)
    return output


def _export_into(claim: OutputClaim, options: ExportOptions, profile: TargetProfile, size: tuple[int, int],
                 precision: str, max_keypoints: int, log) -> None:
    """Build, check and measure the graphs, then write the artefact through ``claim`` (held by the caller)."""
    height, width = size
    # Every input is read before the first export step, so a bad one fails in a second.
    paths = images_in(options.parity_images) if options.parity_images else default_parity_paths()
    images = [prepare_parity_image(path, height, width) for path in paths]
    from models.weights import resolve_checkpoint

    net, info = load_checkpoint(resolve_checkpoint(options.checkpoint))
    set_deform_strategy(net, "native" if profile.deform_strategy == "native" else "torch")
    set_elu_form(net, profile.elu_form)
    torch.manual_seed(0)

    try:
        refinement = model_refinement(net, options.refinement)
    except ValueError as exc:
        raise ExportError(f"--refine: {exc}") from None
    keypoint_module = KeypointGraph(net, height, width, max_keypoints, options.nms_radius, options.threshold, options.border,
                                    options.score_window, refinement).eval()
    dense_module = DenseGraph(net).eval()
    dummy = torch.zeros(1, 1, height, width)
    log(f"exporting {info.arch} for {profile.name} at {height}x{width}, opset {profile.max_opset}, deform {profile.deform_strategy}")
    keypoint_export = export_onnx(keypoint_module, dummy, profile.max_opset, KEYPOINT_OUTPUTS)
    dense_export = export_onnx(dense_module, dummy, profile.max_opset, DENSE_OUTPUTS)
    deployed = dense_export if options.dense else keypoint_export
    check_against_profile(deployed.model, profile)
    # On the TX2, FP16 is a TensorRT build flag on the FP32 graph; on the CPU the file itself becomes FP16.
    onnx_fp16 = precision == "fp16" and profile.runtime.startswith("onnxruntime")
    finish = to_fp16 if onnx_fp16 else _unchanged
    keypoint_model, dense_model = finish(keypoint_export.model), finish(dense_export.model)
    final_model = dense_model if options.dense else keypoint_model
    graph_label = f"the {'fp16' if onnx_fp16 else 'fp32'} {'dense' if options.dense else 'keypoint'} graph"
    checker = check_before_writing(final_model, graph_label)  # before the parity run: it takes milliseconds

    parity = measure_parity(keypoint_module, keypoint_model, dense_module, dense_model, images, [p.name for p in paths])
    lowest_gather = require_non_negative_gathers(keypoint_model, images, profile)
    required = MIN_IDENTICAL["fp16" if onnx_fp16 else "fp32"]
    compared = sum(parity.num_valid_torch)
    if compared < MIN_PARITY_KEYPOINTS:
        raise ExportError(f"parity failed: PyTorch found only {compared} keypoints on {len(paths)} parity images "
                           f"(need {MIN_PARITY_KEYPOINTS} to compare); use images with more texture or a lower --threshold")
    if parity.keypoints_identical < required:
        raise ExportError(
            f"parity failed: only {parity.keypoints_identical:.1%} of keypoints identical to PyTorch (need {required:.0%})"
        )

    # The CPU's channel blocks: the same values, fewer layout conversions, checked against the graph above.
    blocks = block_graphs(deployed.model, profile.channel_blocks, images, finish)
    for graph in blocks:
        check_before_writing(graph.model, f"{graph_label} padded for {graph.block}-channel blocks")
        log(f"padded for onnxruntime's {graph.block}-channel blocks ({graph.file_name}): " + ", ".join(
            f"{chain.producer} {chain.channels} -> {chain.padded}" for chain in graph.chains))

    with claim.writing() as staging:
        onnx.save(final_model, str(staging / MODEL_NAME))
        for graph in blocks:
            onnx.save(graph.model, str(staging / graph.file_name))
        manifest = {
            "format": ARTEFACT_FORMAT,
            "target": profile.name,
            "runtime": profile.runtime,
            "mode": "dense" if options.dense else "keypoints",
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "toolkit_version": __version__,
            "precision": precision,
            "precision_applied": "onnx-fp16-weights" if onnx_fp16 else ("tensorrt-build-flag" if precision == "fp16" else "fp32"),
            "deform_strategy": profile.deform_strategy,
            "model": {"arch": info.arch, "config": info.config, "checkpoint": Path(info.path).name,
                      "checkpoint_sha256": info.sha256, "parameters": sum(p.numel() for p in net.parameters())},
            "onnx": {"file": MODEL_NAME, "sha256": sha256_file(staging / MODEL_NAME), "opset": profile.max_opset,
                     "nodes_before_simplify": deployed.nodes_before_simplify,
                     "nodes_after_simplify": deployed.nodes_after_simplify, "simplifier": deployed.simplifier,
                     "op_types": op_histogram(final_model), "checker": checker,
                     "block_graphs": [{"block": graph.block, "file": graph.file_name,
                                       "sha256": sha256_file(staging / graph.file_name),
                                       "chains": [chain.to_dict() for chain in graph.chains],
                                       "max_abs_diff": graph.max_abs_diff} for graph in blocks]},
            "input": {"name": "image", "shape": [1, 1, height, width], "dtype": "float32", "layout": "NCHW",
                      "color": "gray", "normalisation": {"scale": 1.0 / 255.0, "offset": 0.0},
                      "resize": "cv2.INTER_AREA to the input shape", "resize_policy": "resize"},
            "outputs": _describe_outputs(options.dense, max_keypoints, height, width, net),
            "postprocess": {"max_keypoints": max_keypoints, "nms_radius": options.nms_radius,
                            "score_window": options.score_window, "refinement": refinement.describe(),
                            "detection_threshold": options.threshold, "border": options.border},
            "parity": {**parity.to_dict(), "required_identical": required, "min_gather_index": lowest_gather},
            # the parity run's inputs and this graph's outputs for them, for `python -m vo_runtime verify`
            "reference": write_cpu_references(staging, MODEL_NAME, reference_images(paths, height, width), 1.0 / 255.0,
                                              "dense" if options.dense else "keypoints"),
        }
        (staging / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2) + "\n")
        (staging / "README.md").write_text(artefact_readme(manifest, profile))


def _unchanged(model: onnx.ModelProto) -> onnx.ModelProto:
    return model


def _describe_outputs(dense: bool, k: int, height: int, width: int, net: torch.nn.Module) -> dict:
    dim = net.config.descriptor_dim
    if dense:
        return {
            "heatmap": {"shape": [1, 1, height, width], "dtype": "float32", "meaning": "keypoint probability per pixel"},
            "descriptors_coarse": {"shape": [1, dim, height // 8, width // 8], "dtype": "float32",
                                   "meaning": "unit-norm descriptor per 8x8 cell"},
        }
    return {
        "keypoints": {"shape": [k, 2], "dtype": "float32", "meaning": "(x, y) input pixels, centres at integers"},
        "scores": {"shape": [k], "dtype": "float32", "meaning": "keypoint probability after NMS, descending"},
        "descriptors": {"shape": [k, dim], "dtype": "float32", "meaning": "unit-norm descriptor per keypoint"},
        "num_valid": {"shape": [1], "dtype": "int32", "meaning": "rows [0, num_valid) score above the threshold"},
    }
