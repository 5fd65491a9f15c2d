"""The local bundle adjustment's closed-form Jacobians against finite differences of its own residuals."""
from __future__ import annotations

import numpy as np

from vo_runtime.geometry import left_increment, make_pose
from vo_runtime.schur import _jacobians, _project, _residuals


def _window(rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    import cv2

    poses = [make_pose(cv2.Rodrigues(rng.normal(0, 0.2, 3))[0], rng.normal(0, 0.3, 3)) for _ in range(3)]
    points = rng.uniform([-1, -1, 3], [1, 1, 6], (8, 3))
    frame = np.repeat(np.arange(3), 8)
    point = np.tile(np.arange(8), 3)
    return poses, points, frame, point


def test_pose_and_point_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(3)
    poses, points, frame, point = _window(rng)
    xy = np.zeros((len(frame), 2))
    gain = rng.uniform(300, 500, len(frame))  # a per-observation gain, as obs_scale makes it
    cam = _project(poses, points, frame, point)
    j_pose, j_point = _jacobians(cam, np.stack(poses)[frame, :3, :3], gain)
    base, _ = _residuals(poses, points, frame, point, xy, gain)
    step = 1e-6
    for axis in range(6):
        delta = np.zeros(6)
        delta[axis] = step
        moved = [left_increment(p, delta) for p in poses]
        numeric = (_residuals(moved, points, frame, point, xy, gain)[0] - base) / step
        np.testing.assert_allclose(j_pose[:, :, axis], numeric, rtol=1e-4, atol=1e-3)
    for axis in range(3):
        moved = points.copy()
        moved[:, axis] += step
        numeric = (_residuals(poses, moved, frame, point, xy, gain)[0] - base) / step
        np.testing.assert_allclose(j_point[:, :, axis], numeric, rtol=1e-4, atol=1e-3)


def test_projection_is_every_observation_in_its_own_pose() -> None:
    rng = np.random.default_rng(4)
    poses, points, frame, point = _window(rng)
    expected = np.array([poses[f][:3, :3] @ points[p] + poses[f][:3, 3] for f, p in zip(frame, point)])
    np.testing.assert_allclose(_project(poses, points, frame, point), expected, rtol=1e-12, atol=1e-12)
