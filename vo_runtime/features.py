"""`FeatureExtractor`: run an exported keypoint artefact in onnxruntime (no torch)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vo_runtime.artefact import verify_artefact
from vo_runtime.errors import ArtefactError, VORuntimeError


@dataclass
class Features:
    """Detections of one image, in that image's pixel coordinates.

    keypoints: [N, 2] float32 (x, y); scores: [N] float32, descending; descriptors: [N, D] float32, unit norm.
    """

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Accept HxW gray or HxWx3 BGR (uint8, or float in [0, 1]); return HxW uint8."""
    if image is None or not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise VORuntimeError("expected an HxW or HxWx3 image array")
    if image.dtype != np.uint8:
        image = np.clip(image.astype(np.float32) * (255.0 if image.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    if image.ndim == 3:
        if image.shape[2] == 1:
            return image[:, :, 0]
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


class FeatureExtractor:
    """Loads an artefact directory, verifies its checksum, and extracts keypoints in onnxruntime.

    Args:
        artefact: directory written by ``toolkit export`` (keypoint mode).
        threads: onnxruntime intra-op threads (0 = onnxruntime's default).
        resize_policy: ``"resize"`` scales any image to the artefact's input size and maps keypoints back;
            ``"reject"`` raises on another size. ``None`` takes the manifest's ``input.resize_policy``.
    """

    def __init__(self, artefact: str | Path, threads: int = 1, resize_policy: str | None = None) -> None:
        import onnxruntime as ort

        self.directory = Path(artefact)
        self.manifest = verify_artefact(self.directory)
        if self.manifest.get("mode") != "keypoints":
            raise ArtefactError(f"{self.directory} is a dense artefact; FeatureExtractor needs keypoint mode")
        shape = self.manifest["input"]["shape"]
        self.height, self.width = int(shape[2]), int(shape[3])
        self.scale = float(self.manifest["input"]["normalisation"]["scale"])
        self.resize_policy = resize_policy or self.manifest["input"].get("resize_policy", "resize")
        if self.resize_policy not in ("resize", "reject"):
            raise ArtefactError(f"unknown resize policy {self.resize_policy!r}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(threads)
        options.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(
                str(self.directory / self.manifest["onnx"]["file"]), options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises several unrelated types for a bad model
            raise ArtefactError(f"onnxruntime cannot load {self.directory}: {str(exc).splitlines()[0]}") from None
        self.input_name = self.session.get_inputs()[0].name

    def __call__(self, image: np.ndarray) -> Features:
        """Extract features from an HxW gray or HxWx3 BGR image."""
        gray = to_gray_u8(image)
        height, width = gray.shape
        if (height, width) != (self.height, self.width):
            if self.resize_policy == "reject":
                raise VORuntimeError(
                    f"frame is {height}x{width} but the artefact takes {self.height}x{self.width} (resize policy: reject)"
                )
            gray = cv2.resize(gray, (self.width, self.height), interpolation=cv2.INTER_AREA)
        tensor = (gray.astype(np.float32) * self.scale)[None, None]
        keypoints, scores, descriptors, num_valid = self.session.run(
            ["keypoints", "scores", "descriptors", "num_valid"], {self.input_name: tensor}
        )
        n = int(np.asarray(num_valid).reshape(-1)[0])
        keypoints = keypoints[:n].astype(np.float32)
        if (height, width) != (self.height, self.width):
            # Pixel-centre convention: centres sit at integers, so scale about the -0.5 corner.
            keypoints[:, 0] = (keypoints[:, 0] + 0.5) * (width / self.width) - 0.5
            keypoints[:, 1] = (keypoints[:, 1] + 0.5) * (height / self.height) - 0.5
        return Features(keypoints, scores[:n].astype(np.float32), descriptors[:n].astype(np.float32))


class OrbExtractor:
    """OpenCV ORB as a `FeatureExtractor` stand-in: a baseline to compare artefacts against, and a test double.

    Binary descriptors are unpacked to +-1 and scaled to unit norm, so the L2 distance between two of them is
    ``sqrt(4 * hamming / bits)`` and the float matcher works unchanged (Hamming 64 of 256 bits -> 1.0).
    """

    def __init__(self, max_keypoints: int = 1000, fast_threshold: int = 20, levels: int = 1) -> None:
        self.orb = cv2.ORB_create(nfeatures=int(max_keypoints), fastThreshold=int(fast_threshold), nlevels=int(levels))

    def __call__(self, image: np.ndarray) -> Features:
        gray = to_gray_u8(image)
        keypoints, descriptors = self.orb.detectAndCompute(gray, None)
        if descriptors is None or not keypoints:
            return Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 256), np.float32))
        scores = np.array([kp.response for kp in keypoints], dtype=np.float32)
        order = np.argsort(-scores, kind="stable")
        bits = np.unpackbits(descriptors, axis=1).astype(np.float32)
        unit = (2.0 * bits - 1.0) / np.sqrt(bits.shape[1])
        points = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        return Features(points[order], scores[order], unit[order])
