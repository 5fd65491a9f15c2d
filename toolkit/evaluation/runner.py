"""Run detectors over image pairs and aggregate the per-pair metrics into the report's numbers."""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np

from toolkit.evaluation.datasets import ImagePair, load_gray, resize_with_matrix, scale_homography
from toolkit.evaluation.detection import Detection, Detector
from toolkit.evaluation.metrics import PairMetrics, evaluate_detections
from vo_runtime.progress import progress_bar

CORNER_THRESHOLDS: tuple[int, ...] = (1, 3, 5)


@dataclass
class EvalConfig:
    """Protocol settings shared by all models of one run."""

    size: tuple[int, int] | None = (240, 320)   # (height, width); None keeps native size
    correct_threshold: float = 3.0               # px, repeatability / mAP / matching score
    ransac_threshold: float = 3.0                # px, reprojection threshold of RANSAC
    normalise: str = "none"                      # "minmax": stretch each image to 0..255 before detection


@dataclass
class PairExample:
    """One pair's images, detections and mutual-NN matches, kept for the PNG of matches."""

    name: str
    image_a: np.ndarray
    image_b: np.ndarray
    detection_a: Detection
    detection_b: Detection
    matches: np.ndarray
    homography: np.ndarray


@dataclass
class ModelResult:
    """Per-pair metrics of one detector plus its settings and the example pair."""

    label: str
    kind: str
    settings: dict[str, Any]
    pairs: dict[str, tuple[str, PairMetrics]] = field(default_factory=dict)   # name -> (group, metrics)
    examples: list[PairExample] = field(default_factory=list)  # a few pairs spread over the set, for the plot


EXAMPLE_PAIRS = 6  # pairs drawn per model in the report's match plot


def example_indices(count: int, wanted: int = EXAMPLE_PAIRS) -> set[int]:
    """``wanted`` pair indices spread evenly over ``count`` pairs (all of them when there are fewer)."""
    return set(np.linspace(0, count - 1, min(count, wanted)).round().astype(int).tolist()) if count else set()


class RecentCache:
    """The ``capacity`` most recently used values by key. Pairs come sequence by sequence, so a small cache
    serves the HPatches reference image to its five pairs without holding a whole dataset in memory."""

    def __init__(self, capacity: int = 8) -> None:
        self.capacity = capacity
        self._values: OrderedDict[str, Any] = OrderedDict()

    def get(self, key: str, make: Callable[[], Any]) -> Any:
        if key in self._values:
            self._values.move_to_end(key)
        else:
            self._values[key] = make()
            if len(self._values) > self.capacity:
                self._values.popitem(last=False)
        return self._values[key]


class ImageCache:
    """Resized (and optionally contrast-stretched) gray images by path, read through a `RecentCache`.

    ``read`` turns a path into the HxW uint8 gray image: the file by default, or images held in memory
    (`toolkit eval synth`), which then go through the same resizing as files do."""

    def __init__(self, size: tuple[int, int] | None, normalise: str = "none",
                 read: Callable[[Any], np.ndarray] = load_gray) -> None:
        self.size = size
        self.normalise = normalise
        self.read = read
        self._images = RecentCache()

    def _load(self, path) -> tuple[np.ndarray, np.ndarray]:
        image, scale = resize_with_matrix(self.read(path), self.size)
        if self.normalise == "minmax":
            image = stretch_contrast(image)
        return image, scale

    def get(self, path) -> tuple[np.ndarray, np.ndarray]:
        """(image HxW uint8, S 3x3 mapping original to resized pixels)."""
        return self._images.get(str(path), lambda: self._load(path))


def stretch_contrast(image: np.ndarray) -> np.ndarray:
    """Min-max stretch of an HxW uint8 image to 0..255 (a flat image stays as it is)."""
    low, high = int(image.min()), int(image.max())
    if high <= low:
        return image
    return np.round((image.astype(np.float32) - low) * (255.0 / (high - low))).astype(np.uint8)


def evaluate_model(detector: Detector, pairs: list[ImagePair], config: EvalConfig, images: ImageCache) -> ModelResult:
    """Detect on both images of every pair (a progress bar on stderr) and compute each pair's metrics."""
    result = ModelResult(detector.label, detector.kind, dict(detector.settings))
    detections = RecentCache()
    shown = example_indices(len(pairs))
    for index, pair in enumerate(progress_bar(pairs, desc=f"eval {detector.label}", unit="pair", leave=False)):
        image_a, scale_a = images.get(pair.path_a)
        image_b, scale_b = images.get(pair.path_b)
        detection_a: Detection = detections.get(str(pair.path_a), lambda: detector(image_a))
        detection_b: Detection = detections.get(str(pair.path_b), lambda: detector(image_b))
        homography = scale_homography(pair.homography, scale_a, scale_b)
        metrics, matches = evaluate_detections(
            detection_a.keypoints, detection_a.descriptors, detection_b.keypoints, detection_b.descriptors,
            homography, image_a.shape, image_b.shape, config.correct_threshold, config.ransac_threshold)
        result.pairs[pair.name] = (pair.group, metrics)
        if index in shown:
            result.examples.append(PairExample(pair.name, image_a, image_b, detection_a, detection_b, matches,
                                               homography))
    return result


def _finite_mean(values: list[float]) -> float | None:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


# The per-pair value behind each dataset number (NaN: undefined in that pair, left out of the mean). The
# summary and its bootstrap intervals (`toolkit.evaluation.intervals`) both read them from here.
PAIR_VALUES: dict[str, Callable[[PairMetrics], float]] = {
    "num_keypoints": lambda m: m.num_keypoints,
    "repeatability": lambda m: m.repeatability,
    "localisation_error": lambda m: m.localisation_error,
    "nn_map": lambda m: m.nn_map,
    "matching_score": lambda m: m.matching_score,
    **{f"homography_{e}px": (lambda m, e=e: float(m.corner_error <= e)) for e in CORNER_THRESHOLDS},
}


def summarise(metrics: list[PairMetrics]) -> dict[str, Any]:
    """Means over pairs; homography accuracy is the fraction of pairs with corner error <= epsilon.

    MLE averages only pairs where it is defined (some keypoint repeated); ``None`` if none is.
    """
    if not metrics:
        return {"num_pairs": 0}
    summary: dict[str, Any] = {"num_pairs": len(metrics)}
    for key, value_of in PAIR_VALUES.items():
        summary[key] = _finite_mean([value_of(m) for m in metrics])
    return summary


def grouped_pairs(result: ModelResult) -> dict[str, dict[str, PairMetrics]]:
    """Pair name -> metrics for ``all`` and each HPatches group present (``i``, ``v``, ``dark``, ``other``),
    ``all`` first, pairs in the order they were evaluated."""
    groups: dict[str, dict[str, PairMetrics]] = {"all": {}}
    for name, (group, metrics) in result.pairs.items():
        groups["all"][name] = metrics
        if group != "pairs":   # registered pairs have one group only, which is "all"
            groups.setdefault(group, {})[name] = metrics
    return groups


def group_summaries(result: ModelResult) -> dict[str, dict[str, Any]]:
    """Summaries for ``all`` and each HPatches group present, ``all`` first (`grouped_pairs`)."""
    return {name: summarise(list(pairs.values())) for name, pairs in grouped_pairs(result).items()}


def pair_records(result: ModelResult) -> list[dict[str, Any]]:
    """Per-pair metrics as JSON-safe dicts (inf/NaN become None)."""
    records = []
    for name, (group, metrics) in result.pairs.items():
        record = {"pair": name, "group": group}
        for key, value in asdict(metrics).items():
            record[key] = value if isinstance(value, int) or math.isfinite(value) else None
        records.append(record)
    return records
