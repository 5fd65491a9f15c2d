"""Parity of an exported graph against PyTorch on real images.

Images are prepared exactly as `vo_runtime.FeatureExtractor` prepares frames (gray, INTER_AREA resize,
scale to [0, 1]), so the figures describe what the runtime will see.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import onnx
import torch
from torch import nn

from export.errors import ExportError
from vo_runtime.image_decode import decode_image, decode_problem
from vo_runtime.errors import first_line

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp")
# Real images with texture, dark frames and a viewpoint change: two HPatches frames and a LOL low/high pair.


@dataclass
class ParityReport:
    images: list[str]
    keypoints_identical: float  # fraction of PyTorch's valid keypoints found at the same pixel by the artefact
    num_valid_torch: list[int]
    num_valid_onnx: list[int]
    scores_max_abs_diff: float
    descriptors_max_abs_diff: float
    heatmap_max_abs_diff: float
    descriptors_coarse_max_abs_diff: float

    def to_dict(self) -> dict:
        return asdict(self)


def shared_data_dir() -> Path | None:
    """``$EDGEFEAT_DATA``, else ``../shared/data`` from the working directory or from the source tree."""
    candidates = [os.environ.get("EDGEFEAT_DATA", ""), "../shared/data", Path(__file__).resolve().parents[2] / "shared" / "data"]
    for candidate in candidates:
        if candidate and Path(candidate).is_dir():
            return Path(candidate).resolve()
    return None


# Shipped with the package (public domain and our own renders: parity_images/PROVENANCE.md), so export and
# quantise need no ../shared: two normal-light and two dark 240x320 images.
SHIPPED_PARITY_DIR = Path(__file__).resolve().parent / "parity_images"


def default_parity_paths() -> list[Path]:
    """The shipped parity and calibration images (used when no image folder is given)."""
    paths = sorted(SHIPPED_PARITY_DIR.glob("*.png"))
    if not paths:
        raise ExportError(f"the shipped parity images are missing from {SHIPPED_PARITY_DIR}: reinstall the package")
    return paths


# A parity run proves something only on real content: a single flat 4x4 image once read 99.8 % identical.
MIN_PARITY_IMAGES = 2
MIN_PARITY_SIDE = 64        # px, each side of each source image
MIN_PARITY_CONTRAST = 4.0   # grey levels of standard deviation: less is a flat image
MIN_PARITY_KEYPOINTS = 50   # PyTorch keypoints compared over all images


def images_in(directory: str | Path, limit: int = 4) -> list[Path]:
    """Up to ``limit`` parity images of ``directory``, at least `MIN_PARITY_IMAGES` of them."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ExportError(f"parity image folder not found: {directory}")
    paths = sorted(p for p in directory.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)[:limit]
    if len(paths) < MIN_PARITY_IMAGES:
        raise ExportError(f"{directory} holds {len(paths)} image(s); a parity run needs at least {MIN_PARITY_IMAGES}")
    return paths


def read_gray(path: Path) -> np.ndarray:
    """An image file as HxW uint8 gray; `ExportError` when it cannot be read."""
    data = np.fromfile(str(path), dtype=np.uint8) if path.is_file() else np.zeros(0, np.uint8)
    gray, native = decode_image(data, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise ExportError(f"cannot read image {path}{decode_problem(native)}")
    return gray


def resize_and_scale(gray: np.ndarray, height: int, width: int) -> np.ndarray:
    """INTER_AREA resize to (height, width), scale to [0, 1]: [1, 1, H, W] float32, as the runtime prepares frames."""
    if gray.shape != (height, width):
        gray = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
    return (gray.astype(np.float32) / 255.0)[None, None]


def prepare_image(path: Path, height: int, width: int) -> np.ndarray:
    """Read as gray, resize with INTER_AREA, scale to [0, 1]: [1, 1, H, W] float32."""
    return resize_and_scale(read_gray(path), height, width)


def prepare_parity_image(path: Path, height: int, width: int) -> np.ndarray:
    """`prepare_image` for a parity image, refusing one too small or too flat to show a difference."""
    gray = read_gray(path)
    if min(gray.shape) < MIN_PARITY_SIDE:
        raise ExportError(f"parity image {path} is {gray.shape[1]}x{gray.shape[0]}; each side must be at least "
                           f"{MIN_PARITY_SIDE} px")
    if float(gray.std()) < MIN_PARITY_CONTRAST:
        raise ExportError(f"parity image {path} is flat (grey-level spread {gray.std():.1f} < {MIN_PARITY_CONTRAST}): "
                           "parity needs images with texture")
    return resize_and_scale(gray, height, width)


def cpu_session(model: onnx.ModelProto):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several unrelated types
        raise ExportError(f"onnxruntime cannot load the exported graph: {first_line(exc)}") from None


def _pixel_keys(keypoints: np.ndarray) -> dict[tuple[int, int], int]:
    return {(int(round(x)), int(round(y))): i for i, (x, y) in enumerate(keypoints)}


def measure_parity(
    keypoint_module: nn.Module,
    keypoint_model: onnx.ModelProto,
    dense_module: nn.Module,
    dense_model: onnx.ModelProto,
    images: list[np.ndarray],
    names: list[str],
) -> ParityReport:
    """Run PyTorch and onnxruntime side by side on ``images`` and compare heads and keypoints."""
    keypoint_session, dense_session = cpu_session(keypoint_model), cpu_session(dense_model)
    found = total = 0
    valid_torch: list[int] = []
    valid_onnx: list[int] = []
    score_diff = desc_diff = heat_diff = coarse_diff = 0.0
    with torch.no_grad():
        for image in images:
            reference = [t.numpy() for t in keypoint_module(torch.from_numpy(image))]
            exported = keypoint_session.run(None, {"image": image})
            n_ref, n_exp = int(reference[3][0]), int(exported[3][0])
            valid_torch.append(n_ref)
            valid_onnx.append(n_exp)
            ref_keys, exp_keys = _pixel_keys(reference[0][:n_ref]), _pixel_keys(exported[0][:n_exp])
            common = [(ref_keys[k], exp_keys[k]) for k in ref_keys if k in exp_keys]
            found += len(common)
            total += len(ref_keys)
            if common:
                ri, ei = map(list, zip(*common))
                score_diff = max(score_diff, float(np.abs(reference[1][ri] - exported[1][ei]).max()))
                desc_diff = max(desc_diff, float(np.abs(reference[2][ri] - exported[2][ei]).max()))
            dense_ref = [t.numpy() for t in dense_module(torch.from_numpy(image))]
            dense_exp = dense_session.run(None, {"image": image})
            heat_diff = max(heat_diff, float(np.abs(dense_ref[0] - dense_exp[0]).max()))
            coarse_diff = max(coarse_diff, float(np.abs(dense_ref[1] - dense_exp[1]).max()))
    return ParityReport(
        images=names,
        keypoints_identical=found / total if total else 0.0,  # nothing compared proves nothing
        num_valid_torch=valid_torch,
        num_valid_onnx=valid_onnx,
        scores_max_abs_diff=score_diff,
        descriptors_max_abs_diff=desc_diff,
        heatmap_max_abs_diff=heat_diff,
        descriptors_coarse_max_abs_diff=coarse_diff,
    )
