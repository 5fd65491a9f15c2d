"""A new keyframe's pose refined on its landmarks and on its epipolar geometry to the previous keyframe.

Tracking fits a frame's pose to the landmarks it found. In a slow, dim turn (the drone's take-off, EuRoC MH_05)
those are few and bunched (30-70 points of the board under the drone), and a rotation about one axis trades for a
translation along another: keyframe poses came out 0.5-1.1 deg off in rotation while a rotation fitted to all of
the frame's matches with the previous keyframe, most of them far hall points with no landmark, was 0.1-0.3 deg
off. A wrong keyframe rotation reads as parallax: it triangulates the far hall 5-7x too close, and the map loses
its scale (docs/vo_takeoff.md). The epipolar constraint holds for every match whatever its depth, so adding it
(Sampson distances, robust) to the landmarks' reprojection errors pins the rotation where the landmarks alone
cannot, while the landmarks keep the translation and the scale.
"""
from __future__ import annotations

import numpy as np

from vo_runtime.geometry import left_increment, projection_jacobian
from vo_runtime.mapping import essential_between
from vo_runtime.matching import match_mutual_nn

ITERATIONS = 8             # Gauss-Newton steps at most: a 6-parameter fit from a pose close to the answer
CONVERGED = 1e-7           # ... or until no parameter moves by more (radians; normalised-plane units)
DIFFERENCE_STEP = 1e-7     # of the Sampson distances' numerical derivative


def _homogeneous(points: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(points, np.float64), np.ones((len(points), 1))], axis=1)


def _sampson(essential: np.ndarray, homogeneous_a: np.ndarray, homogeneous_b: np.ndarray) -> np.ndarray:
    lines_b = homogeneous_a @ essential.T   # epipolar lines in view b
    lines_a = homogeneous_b @ essential     # ... and in view a
    algebraic = np.einsum("ij,ij->i", homogeneous_b, lines_b)
    norm = np.sqrt(lines_b[:, 0] ** 2 + lines_b[:, 1] ** 2 + lines_a[:, 0] ** 2 + lines_a[:, 1] ** 2)
    return algebraic / np.maximum(norm, 1e-15)


def sampson_distances(essential: np.ndarray, points_a: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Signed first-order distances [N] of matches ``points_a`` -> ``points_b`` (normalised [N, 2]) from ``essential``."""
    return _sampson(essential, _homogeneous(points_a), _homogeneous(points_b))


def epipolar_matches(points_a: np.ndarray, desc_a: np.ndarray, points_b: np.ndarray, desc_b: np.ndarray,
                     pose_a: np.ndarray, pose_b: np.ndarray, gate: float, max_distance: float,
                     ratio: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Mutual-nearest descriptor matches between two keyframes within ``gate`` (normalised units) of the epipolar
    geometry of their current poses: a loose gate, since the poses it checks are the ones to be corrected."""
    pairs = match_mutual_nn(desc_a, desc_b, max_distance, ratio)
    if len(pairs) == 0:
        return np.empty((0, 2)), np.empty((0, 2))
    near = np.abs(sampson_distances(essential_between(pose_a, pose_b), points_a[pairs[:, 0]],
                                    points_b[pairs[:, 1]])) < gate
    return points_a[pairs[near, 0]], points_b[pairs[near, 1]]


def _projection_rows(pose: np.ndarray, world: np.ndarray, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection residuals [2N] of ``world`` under ``pose`` and their Jacobian [2N, 6] in a left increment."""
    camera = world @ pose[:3, :3].T + pose[:3, 3]
    residual = camera[:, :2] / camera[:, 2:3] - observed
    return residual.ravel(), projection_jacobian(camera)


def _epipolar_rows(pose_a: np.ndarray, pose: np.ndarray, homogeneous_a: np.ndarray,
                   homogeneous_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sampson distances [M] and their Jacobian [M, 6] in a left increment of ``pose`` (forward differences)."""
    residual = _sampson(essential_between(pose_a, pose), homogeneous_a, homogeneous_b)
    jacobian = np.empty((len(residual), 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = DIFFERENCE_STEP
        moved = _sampson(essential_between(pose_a, left_increment(pose, delta)), homogeneous_a, homogeneous_b)
        jacobian[:, k] = (moved - residual) / DIFFERENCE_STEP
    return residual, jacobian


def refine_with_epipolar(pose_b: np.ndarray, world: np.ndarray, observed: np.ndarray, pose_a: np.ndarray,
                         points_a: np.ndarray, points_b: np.ndarray, robust_scale: float,
                         weight: float = 1.0) -> np.ndarray:
    """Pose b [4, 4] (world-to-camera) minimising its landmarks' reprojection errors and its matches' Sampson
    distances to view a (whose pose stays), both under a Cauchy loss of ``robust_scale`` (normalised units):
    Gauss-Newton on iteratively reweighted residuals, from pose b.

    Args:
        world [N, 3], observed [N, 2]: pose b's landmarks and where b sees them (normalised).
        points_a, points_b [M, 2]: matches between views a and b (normalised), any depth.
        weight: of a match's distance against a landmark's error.
    """
    pose = pose_b
    homogeneous_a, homogeneous_b = _homogeneous(points_a), _homogeneous(points_b)
    for _ in range(ITERATIONS):
        projection, d_projection = _projection_rows(pose, world, observed)
        epipolar, d_epipolar = _epipolar_rows(pose_a, pose, homogeneous_a, homogeneous_b)
        residual = np.concatenate([projection, weight * epipolar]) / robust_scale
        jacobian = np.vstack([d_projection, weight * d_epipolar]) / robust_scale
        cauchy = 1.0 / (1.0 + residual ** 2)
        hessian = jacobian.T @ (cauchy[:, None] * jacobian)
        step = np.linalg.solve(hessian + 1e-12 * np.eye(6), -jacobian.T @ (cauchy * residual))
        pose = left_increment(pose, step)
        if np.abs(step).max() < CONVERGED:
            break
    return pose
