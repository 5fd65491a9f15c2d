"""`FeatureExtractor`: run an exported keypoint artefact in onnxruntime (no torch)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from vo_runtime.artefact import artefact_path, aspect_distortion, verify_artefact
from vo_runtime.errors import ArtefactError, FrameError, VORuntimeError, first_line
from vo_runtime.machine import check_thread_count
from vo_runtime.graph_contract import KEYPOINT_OUTPUTS, check_graph, checked_detections, read_contract

MIN_FRAME_SIDE = 16  # smaller frames carry no trackable structure (and break the 8-px network cell)


@dataclass
class Features:
    """Detections of one image, in that image's pixel coordinates.

    keypoints: [N, 2] float32 (x, y); scores: [N] float32, descending; descriptors: [N, D] float32, unit norm.
    ``scores_predict_error``: a weaker score means a less precisely placed keypoint (a network's detection
    probability: `keypoint_sigma`); not so for ORB's corner response (docs/vo_euroc.md, "Keypoints weighted by
    their score").
    """

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray
    scores_predict_error: bool = True

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def keypoint_sigma(scores: np.ndarray, power: float, limit: float) -> np.ndarray | None:
    """Each keypoint's expected position error relative to the frame's typical one, from its detection score:
    (score / median score) ** -power, clipped to [1 / limit, limit]; None when ``power`` is 0 or the scores say
    nothing (all alike, or not positive)."""
    scores = np.asarray(scores, np.float64)
    median = float(np.median(scores)) if len(scores) else 0.0
    if power <= 0 or median <= 0 or np.ptp(scores) == 0:
        return None
    ratio = np.maximum(scores, 1e-6 * median) / median
    return np.clip(ratio ** -power, 1.0 / limit, limit)


def check_frame(image: object) -> np.ndarray:
    """Return ``image`` if it is a usable frame, else raise `FrameError` saying why.

    Usable: an HxW or HxWxC (C = 1, 3 or 4) array, each side at least `MIN_FRAME_SIDE`, of uint8, uint16, another
    integer type holding 0..255, or float (0..1 or 0..255) without NaN or inf.
    """
    if image is None:
        raise FrameError("no image (None): the frame could not be read")
    if not isinstance(image, np.ndarray):
        raise FrameError(f"expected an HxW or HxWx3 image array, got {type(image).__name__}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise FrameError(f"expected an HxW or HxWx3 image array, got shape {image.shape}")
    if min(image.shape[:2]) < MIN_FRAME_SIDE:
        raise FrameError(f"a {image.shape[1]}x{image.shape[0]} frame is too small (each side >= {MIN_FRAME_SIDE} px)")
    if image.dtype == np.bool_ or not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise FrameError(f"unsupported image dtype {image.dtype} (uint8, uint16 or float)")
    if np.issubdtype(image.dtype, np.floating) and not np.all(np.isfinite(image)):
        raise FrameError("the frame holds NaN or infinite values")
    if image.dtype not in (np.uint8, np.uint16) and np.issubdtype(image.dtype, np.integer) and (
            image.min() < 0 or image.max() > 255):
        raise FrameError(f"{image.dtype} frame values span {image.min()}..{image.max()}; expected 0..255 (or uint16)")
    return image


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Accept HxW gray or HxWx3 BGR (HxWx4 BGRA) frames as `check_frame` describes; return HxW uint8.

    16-bit frames keep their high byte (x >> 8), as OpenCV's ``IMREAD_GRAYSCALE`` reads a 16-bit PNG
    (so `toolkit label` and the VO see the same pixels); float frames in [0, 1] are scaled by 255.
    """
    image = check_frame(image)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        scale = 255.0 if np.issubdtype(image.dtype, np.floating) and image.max() <= 1.0 else 1.0
        image = np.clip(image.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    if image.ndim == 3:
        if image.shape[2] == 1:
            return image[:, :, 0]
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image


class FeatureExtractor:
    """Loads an artefact directory, verifies its checksum, and extracts keypoints in onnxruntime.

    Args:
        artefact: directory written by ``toolkit export`` (keypoint mode).
        threads: onnxruntime intra-op threads (0 = onnxruntime's default).
        resize_policy: ``"resize"`` scales any image to the artefact's input size and maps keypoints back;
            ``"reject"`` raises on another size. ``None`` takes the manifest's ``input.resize_policy``.
        providers: ``"auto"`` (default: the best available of TensorRT FP16, CUDA, CPU), or the ones to use,
            e.g. ``"cuda,cpu"`` or ``["cpu"]``; a requested provider that is missing raises `VORuntimeError`.
            ``self.providers`` lists those the session really runs on, best first.

    ``self.graph`` names the graph file loaded: ``model.onnx``, or the copy padded for this CPU's onnxruntime
    channel blocks where the artefact has one (`vo_runtime.cpu_blocks`; the same outputs).
    """

    def __init__(self, artefact: str | Path, threads: int = 1, resize_policy: str | None = None,
                 providers: str | Sequence[str] | None = "auto") -> None:
        from vo_runtime.cpu_blocks import graph_for_this_cpu
        from vo_runtime.providers import open_session, short_name

        check_thread_count(int(threads) if isinstance(threads, np.integer) else threads, "threads", allow_zero=True)
        self.directory = artefact_path(artefact)
        self.manifest = verify_artefact(self.directory)
        self.contract = read_contract(self.manifest, self.directory)  # what every run is held to
        self.height, self.width, self.scale = self.contract.height, self.contract.width, self.contract.scale
        self.resize_policy = resize_policy or self.manifest["input"].get("resize_policy", "resize")
        if self.resize_policy not in ("resize", "reject"):
            raise ArtefactError(f"unknown resize policy {self.resize_policy!r}")
        # the graph padded for this CPU's channel blocks where the artefact has one: the same outputs, sooner
        self.graph = graph_for_this_cpu(self.manifest)
        self.session = open_session(self.directory / self.graph, threads, providers)
        self.providers = [short_name(p) for p in self.session.get_providers()]
        check_graph(self.session, self.contract)
        self.input_name = self.session.get_inputs()[0].name
        self._detect(np.zeros((1, 1, self.height, self.width), np.float32))  # a bad graph fails here, not at frame 1

    def aspect_distortion(self, height: int, width: int) -> float:
        """How much resizing an ``height`` x ``width`` frame to the input stretches one axis against the other
        (0: same aspect; 1.48 for KITTI's 1226x370 into 320x240). Detections are only as precise as the
        coarser axis: without patch alignment the squeezed 240x320 artefact's VO drifted 4.6 m (ATE, KITTI 07)
        against 0.64 m for the same weights exported at 184x608; with it, 0.36 m (docs/vo.md)."""
        return aspect_distortion((self.height, self.width), height, width)

    def __call__(self, image: np.ndarray) -> Features:
        """Extract features from an HxW gray or HxWx3 BGR image."""
        gray = to_gray_u8(image)
        height, width = gray.shape
        if (height, width) != (self.height, self.width):
            if self.resize_policy == "reject":
                raise FrameError(
                    f"frame is {height}x{width} but the artefact takes {self.height}x{self.width} (resize policy: reject)"
                )
            gray = cv2.resize(gray, (self.width, self.height), interpolation=cv2.INTER_AREA)
        tensor = (gray.astype(np.float32) * self.scale)[None, None]
        keypoints, scores, descriptors = self._detect(tensor)
        if (height, width) != (self.height, self.width):
            # Pixel-centre convention: centres sit at integers, so scale about the -0.5 corner.
            keypoints[:, 0] = (keypoints[:, 0] + 0.5) * (width / self.width) - 0.5
            keypoints[:, 1] = (keypoints[:, 1] + 0.5) * (height / self.height) - 0.5
        return Features(keypoints, scores, descriptors)

    def _detect(self, tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run the graph on one input tensor; its real rows, held to the manifest (`checked_detections`)."""
        try:
            outputs = self.session.run(list(KEYPOINT_OUTPUTS), {self.input_name: tensor})
        except Exception as exc:  # onnxruntime raises several unrelated types for a graph that cannot run
            raise ArtefactError(f"onnxruntime cannot run {self.directory}: {first_line(exc)}") from None
        return checked_detections(outputs, self.contract)


class OrbExtractor:
    """OpenCV ORB as a `FeatureExtractor` stand-in: a baseline to compare artefacts against, and a test double.

    Binary descriptors are unpacked to +-1 and scaled to unit norm, so the L2 distance between two of them is
    ``sqrt(4 * hamming / bits)`` and the float matcher works unchanged (Hamming 64 of 256 bits -> 1.0).
    """

    def __init__(self, max_keypoints: int = 1000, fast_threshold: int = 20, levels: int = 1) -> None:
        self.orb = cv2.ORB_create(nfeatures=int(max_keypoints), fastThreshold=int(fast_threshold), nlevels=int(levels))
        self.providers = ["cpu"]  # OpenCV on the CPU, reported like an artefact's onnxruntime providers

    def __call__(self, image: np.ndarray) -> Features:
        gray = to_gray_u8(image)
        keypoints, descriptors = self.orb.detectAndCompute(gray, None)
        if descriptors is None or not keypoints:
            return Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 256), np.float32),
                            scores_predict_error=False)
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        order = np.argsort(-scores, kind="stable")
        bits = np.unpackbits(descriptors, axis=1).astype(np.float32)
        unit = (2.0 * bits - 1.0) / np.sqrt(bits.shape[1])
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        return Features(points[order], scores[order], unit[order], scores_predict_error=False)


def spread_selection(keypoints: np.ndarray, scores: np.ndarray, budget: int, grid: tuple[int, int] | None,
                     width: int, height: int) -> np.ndarray:
    """Rows of the ``budget`` keypoints to keep, in descending score. With ``grid`` (columns, rows) the image is
    cut into cells and the keypoints are taken round-robin by their rank within their cell (every cell's best,
    then every cell's second, ...), as ORB's grid spreads its features; without, the ``budget`` best scores.

    keypoints: [N, 2] (x, y) frame pixels; scores: [N], descending.
    """
    if len(keypoints) <= budget:
        return np.arange(len(keypoints))
    if grid is None:
        return np.arange(budget)
    columns, rows = grid
    cx = np.clip((keypoints[:, 0] * columns / width).astype(np.int64), 0, columns - 1)
    cy = np.clip((keypoints[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    cell = cy * columns + cx
    order = np.argsort(cell, kind="stable")  # within a cell the rows stay in descending score
    first = np.searchsorted(cell[order], np.arange(columns * rows))
    rank = np.empty(len(cell), np.int64)
    rank[order] = np.arange(len(cell)) - first[cell[order]]
    keep = np.lexsort((np.arange(len(cell)), rank))[:budget]  # by rank in the cell, then by score
    return np.sort(keep)


class KeypointBudget:
    """Any extractor, keeping at most ``budget`` keypoints a frame, spread over a ``grid`` of cells
    (`spread_selection`). Everything else (input size, providers) is the wrapped extractor's."""

    def __init__(self, extractor: object, budget: int, grid: tuple[int, int] | None = None) -> None:
        if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 1:
            raise VORuntimeError(f"the keypoint budget must be a positive integer, got {budget!r}")
        if grid is not None and (len(grid) != 2 or min(grid) < 1):
            raise VORuntimeError(f"the spread grid is (columns, rows) of positive integers, got {grid!r}")
        self.extractor, self.budget, self.grid = extractor, int(budget), grid

    def __getattr__(self, name: str) -> object:
        return getattr(self.__dict__["extractor"], name)

    def __call__(self, image: np.ndarray) -> Features:
        features = self.extractor(image)
        height, width = image.shape[:2]
        keep = spread_selection(features.keypoints, features.scores, self.budget, self.grid, width, height)
        return Features(features.keypoints[keep], features.scores[keep], features.descriptors[keep],
                        features.scores_predict_error)


def detector_pixel(extractor: object, height: int, width: int) -> float:
    """Frame pixels per detector pixel: an artefact that resizes frames to its input (``width`` x ``height``
    attributes) localises keypoints to its own pixels, so pixel thresholds are meant in those; 1 otherwise."""
    input_width, input_height = getattr(extractor, "width", None), getattr(extractor, "height", None)
    if not isinstance(input_width, int) or not isinstance(input_height, int) or input_width <= 0 or input_height <= 0:
        return 1.0
    return max(1.0, width / input_width, height / input_height)
