"""What every `toolkit eval` detector is: an HxW uint8 gray image -> `Detection`, with the settings applied to
all models alike. Shared by the adapters (`detectors` for OpenCV and artefacts, `torch_models` for networks)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np


@dataclass
class Detection:
    """keypoints ``[N, 2]`` float32 (x, y); scores ``[N]`` float32; descriptors ``[N, D]`` float32 or uint8 bits."""

    keypoints: np.ndarray
    scores: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


@dataclass
class DetectorConfig:
    """Settings applied to every model alike (NMS only where the post-processing runs in Python)."""

    max_keypoints: int = 1000
    nms_radius: int = 4
    score_window: int = 1  # 65-way networks: `models.keypoints.keypoint_scores`; 1 = the peak pixel
    refinement: str = ""  # 65-way networks: `models.keypoints.parse_refinement` text; "" = the model's own
    detection_threshold: float = 0.005
    border: int = 4


@dataclass
class Detector:
    """A named image -> `Detection` function with the settings it ran under (reported in the JSON)."""

    label: str
    kind: str
    detect: Callable[[np.ndarray], Detection]
    settings: dict[str, Any] = field(default_factory=dict)

    def __call__(self, gray: np.ndarray) -> Detection:
        return self.detect(gray)


def top_k(detection: Detection, max_keypoints: int) -> Detection:
    """Keep the ``max_keypoints`` highest-scoring detections, sorted by descending score."""
    order = np.argsort(-detection.scores, kind="stable")[:max_keypoints]
    return Detection(detection.keypoints[order], detection.scores[order], detection.descriptors[order])
