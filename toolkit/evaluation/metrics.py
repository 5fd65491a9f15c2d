"""Detector and descriptor metrics of SuperPoint's HPatches evaluation (exact definitions: docs/evaluation.md).

All functions take numpy arrays for one image pair: keypoints ``[N, 2]`` (x, y) in pixels, descriptors
``[N, D]`` float (L2 distance) or uint8 packed bits (Hamming distance), homography ``[3, 3]`` mapping
image A to image B. Empty inputs give zeros (or NaN where a quantity is undefined), never an exception.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def warp_points(points: np.ndarray, homography: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to ``[N, 2]`` points; returns ``[N, 2]`` float64."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ homography.T
    return homogeneous[:, :2] / homogeneous[:, 2:3]


def inside_image(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``[N]`` bool: point lies within an image of ``shape`` (height, width), pixel centres at integers."""
    height, width = shape[:2]
    x, y = points[:, 0], points[:, 1]
    return (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)


def shared_view_masks(keypoints_a: np.ndarray, keypoints_b: np.ndarray, homography: np.ndarray,
                      shape_a: tuple[int, int], shape_b: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Masks ``[N_a]``, ``[N_b]`` of keypoints whose projection lands inside the other image."""
    visible_a = inside_image(warp_points(keypoints_a, homography), shape_b)
    visible_b = inside_image(warp_points(keypoints_b, np.linalg.inv(homography)), shape_a)
    return visible_a, visible_b


def pairwise_point_distances(points_a: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Euclidean distances ``[N_a, N_b]`` between two point sets."""
    return np.linalg.norm(points_a[:, None, :] - points_b[None, :, :], axis=2)


def descriptor_distances(descriptors_a: np.ndarray, descriptors_b: np.ndarray) -> np.ndarray:
    """``[N_a, N_b]`` distances: Hamming for uint8 packed binary descriptors, L2 for float ones."""
    if len(descriptors_a) == 0 or len(descriptors_b) == 0:
        return np.zeros((len(descriptors_a), len(descriptors_b)), dtype=np.float32)
    if descriptors_a.dtype == np.uint8:
        bits_a = np.unpackbits(descriptors_a, axis=1).astype(np.float32)
        bits_b = np.unpackbits(descriptors_b, axis=1).astype(np.float32)
        # Bits that differ: a=1,b=0 plus a=0,b=1; two float matmuls are exact for counts below 2**24.
        return bits_a @ (1.0 - bits_b).T + (1.0 - bits_a) @ bits_b.T
    a = descriptors_a.astype(np.float32)
    b = descriptors_b.astype(np.float32)
    squared = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(squared, 0.0))


def mutual_nearest_neighbours(distances: np.ndarray) -> np.ndarray:
    """``[M, 2]`` index pairs (i, j) where j is i's nearest neighbour and i is j's; from ``[N_a, N_b]``."""
    if distances.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    nearest_b = distances.argmin(axis=1)
    nearest_a = distances.argmin(axis=0)
    rows = np.arange(distances.shape[0])
    mutual = nearest_a[nearest_b] == rows
    return np.stack([rows[mutual], nearest_b[mutual]], axis=1).astype(np.int64)


def repeatability_and_localisation(keypoints_a: np.ndarray, keypoints_b: np.ndarray, homography: np.ndarray,
                                   shape_a: tuple[int, int], shape_b: tuple[int, int],
                                   threshold: float = 3.0) -> tuple[float, float]:
    """SuperPoint repeatability and mean localisation error (MLE) on the shared view.

    Keypoints of A are warped into B; only keypoints whose projection lies in the other image count.
    A keypoint is repeated if its nearest projected counterpart is within ``threshold`` px, counted in both
    directions: ``rep = (n_a_rep + n_b_rep) / (N_a + N_b)``. MLE is the mean of those nearest distances
    that are within the threshold. Returns (0, NaN) when nothing is repeated (MLE is undefined then).
    """
    visible_a, visible_b = shared_view_masks(keypoints_a, keypoints_b, homography, shape_a, shape_b)
    warped_a = warp_points(keypoints_a[visible_a], homography)
    points_b = np.asarray(keypoints_b, dtype=np.float64)[visible_b]
    total = len(warped_a) + len(points_b)
    if len(warped_a) == 0 or len(points_b) == 0:
        return 0.0, float("nan")
    distances = pairwise_point_distances(warped_a, points_b)
    nearest_from_a = distances.min(axis=1)
    nearest_from_b = distances.min(axis=0)
    close = np.concatenate([nearest_from_a[nearest_from_a <= threshold], nearest_from_b[nearest_from_b <= threshold]])
    if close.size == 0:
        return 0.0, float("nan")
    return float(close.size / total), float(close.mean())


def average_precision(scores: np.ndarray, correct: np.ndarray, num_positives: int) -> float:
    """AP of a ranked list: sum over correct items of precision-at-rank, divided by ``num_positives``.

    scores: ``[M]`` higher is more confident; correct: ``[M]`` bool. Returns 0 when ``num_positives`` is 0.
    """
    if num_positives <= 0 or len(scores) == 0:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind="stable")
    hits = np.asarray(correct, dtype=np.float64)[order]
    precision_at_rank = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision_at_rank * hits).sum() / num_positives)


def nearest_neighbour_map(keypoints_a: np.ndarray, descriptors_a: np.ndarray, keypoints_b: np.ndarray,
                          descriptors_b: np.ndarray, homography: np.ndarray, shape_a: tuple[int, int],
                          shape_b: tuple[int, int], threshold: float = 3.0) -> float:
    """Descriptor nearest-neighbour mAP on the shared view, A -> B.

    Each visible keypoint of A is matched to the descriptor-nearest visible keypoint of B; the match is
    correct if B's keypoint lies within ``threshold`` px of A's projection. Matches are ranked by ascending
    descriptor distance; AP divides by the number of A keypoints that have any B keypoint within the
    threshold (those a perfect descriptor could match).
    """
    visible_a, visible_b = shared_view_masks(keypoints_a, keypoints_b, homography, shape_a, shape_b)
    if not visible_a.any() or not visible_b.any():
        return 0.0
    warped_a = warp_points(keypoints_a[visible_a], homography)
    points_b = np.asarray(keypoints_b, dtype=np.float64)[visible_b]
    geometric = pairwise_point_distances(warped_a, points_b)
    descriptor = descriptor_distances(descriptors_a[visible_a], descriptors_b[visible_b])
    nearest = descriptor.argmin(axis=1)
    rows = np.arange(len(nearest))
    correct = geometric[rows, nearest] <= threshold
    num_positives = int((geometric.min(axis=1) <= threshold).sum())
    return average_precision(-descriptor[rows, nearest], correct, num_positives)


def matching_score(keypoints_a: np.ndarray, keypoints_b: np.ndarray, matches: np.ndarray, homography: np.ndarray,
                   shape_a: tuple[int, int], shape_b: tuple[int, int], threshold: float = 3.0) -> float:
    """Correct mutual-NN matches over keypoints in the shared view, averaged over both directions.

    ``matches`` ``[M, 2]`` are mutual nearest neighbours among all keypoints. A match counts in direction
    A->B if both ends are in the shared view and ``|H a - b| <= threshold``, in B->A if
    ``|H^-1 b - a| <= threshold``. ``score = (c_ab / N_a_visible + c_ba / N_b_visible) / 2``.
    """
    visible_a, visible_b = shared_view_masks(keypoints_a, keypoints_b, homography, shape_a, shape_b)
    if not visible_a.any() or not visible_b.any() or len(matches) == 0:
        return 0.0
    kept = matches[visible_a[matches[:, 0]] & visible_b[matches[:, 1]]]
    matched_a, matched_b = keypoints_a[kept[:, 0]], keypoints_b[kept[:, 1]]
    correct_ab = np.linalg.norm(warp_points(matched_a, homography) - matched_b, axis=1) <= threshold
    correct_ba = np.linalg.norm(warp_points(matched_b, np.linalg.inv(homography)) - matched_a, axis=1) <= threshold
    return float(0.5 * (correct_ab.sum() / visible_a.sum() + correct_ba.sum() / visible_b.sum()))


def image_corners(shape: tuple[int, int]) -> np.ndarray:
    """The four corners ``[4, 2]`` of an image of ``shape`` (height, width), as SuperPoint uses them."""
    height, width = shape[:2]
    return np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]])


def estimate_homography(points_a: np.ndarray, points_b: np.ndarray,
                        ransac_threshold: float = 3.0) -> np.ndarray | None:
    """RANSAC homography ``[3, 3]`` from matched ``[M, 2]`` points, or None with < 4 matches or on failure."""
    if len(points_a) < 4:
        return None
    # A fixed seed keeps OpenCV's RANSAC, and so the report, reproducible run to run.
    cv2.setRNGSeed(0)
    homography, _ = cv2.findHomography(points_a.astype(np.float64), points_b.astype(np.float64),
                                       cv2.RANSAC, ransac_threshold, maxIters=5000, confidence=0.9995)
    if homography is None or not np.all(np.isfinite(homography)):
        return None
    return homography


def corner_error(estimated: np.ndarray | None, truth: np.ndarray, shape_a: tuple[int, int]) -> float:
    """Mean distance between image A's corners mapped by the estimate and by the truth; inf if no estimate."""
    if estimated is None:
        return float("inf")
    corners = image_corners(shape_a)
    return float(np.linalg.norm(warp_points(corners, estimated) - warp_points(corners, truth), axis=1).mean())


@dataclass
class PairMetrics:
    """Metrics of one pair. ``corner_error`` is inf when no homography could be estimated; ``localisation_error``
    is NaN when no keypoint is repeated."""

    repeatability: float
    localisation_error: float
    nn_map: float
    matching_score: float
    corner_error: float
    num_keypoints: float
    num_matches: int


def evaluate_detections(keypoints_a: np.ndarray, descriptors_a: np.ndarray, keypoints_b: np.ndarray,
                        descriptors_b: np.ndarray, homography: np.ndarray, shape_a: tuple[int, int],
                        shape_b: tuple[int, int], threshold: float = 3.0,
                        ransac_threshold: float = 3.0) -> tuple[PairMetrics, np.ndarray]:
    """All metrics for one pair, plus the mutual-NN matches ``[M, 2]`` used for the homography."""
    keypoints_a = np.asarray(keypoints_a, dtype=np.float64).reshape(-1, 2)
    keypoints_b = np.asarray(keypoints_b, dtype=np.float64).reshape(-1, 2)
    repeatability, localisation = repeatability_and_localisation(
        keypoints_a, keypoints_b, homography, shape_a, shape_b, threshold)
    nn_map = nearest_neighbour_map(keypoints_a, descriptors_a, keypoints_b, descriptors_b, homography,
                                   shape_a, shape_b, threshold)
    matches = mutual_nearest_neighbours(descriptor_distances(descriptors_a, descriptors_b))
    score = matching_score(keypoints_a, keypoints_b, matches, homography, shape_a, shape_b, threshold)
    estimated = estimate_homography(keypoints_a[matches[:, 0]], keypoints_b[matches[:, 1]], ransac_threshold)
    metrics = PairMetrics(repeatability, localisation, nn_map, score, corner_error(estimated, homography, shape_a),
                          0.5 * (len(keypoints_a) + len(keypoints_b)), int(len(matches)))
    return metrics, matches
