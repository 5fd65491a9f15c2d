"""The pose fit's and the probation's helpers written for speed keep their meaning: reprojection errors behind or on
the camera plane, the Jacobian against finite differences, batched rotations as one at a time, and the rotation
RANSAC on tracks of a camera that only turned."""
from __future__ import annotations

import cv2
import numpy as np

from vo_runtime.geometry import left_increment, make_pose, projection_jacobian, reprojection_errors
from vo_runtime.rotation_fit import fit_rotation, fit_rotation_ransac


def test_reprojection_errors_are_infinite_behind_the_camera_and_on_its_plane() -> None:
    world = np.array([[0.1, 0.2, 2.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [1.0, 0.0, 1e-320]])
    image = np.array([[0.05, 0.1], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    errors = reprojection_errors(world, image, np.zeros((3, 1)), np.zeros((3, 1)))
    assert errors[0] == 0.0
    assert np.isinf(errors[1]) and np.isinf(errors[2]) and np.isinf(errors[3])
    assert errors[4] == np.finfo(np.float64).max  # x/z overflows in front of the camera: the largest float, as before


def test_projection_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(4)
    world = rng.normal(size=(20, 3)) + [0.0, 0.0, 4.0]
    pose = make_pose(cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], [0.3, -0.1, 0.2])

    def project(delta):
        cam = world @ left_increment(pose, delta)[:3, :3].T + left_increment(pose, delta)[:3, 3]
        return (cam[:, :2] / cam[:, 2:]).ravel()

    cam = world @ pose[:3, :3].T + pose[:3, 3]
    numeric = np.stack([(project(step) - project(-step)) / 2e-6 for step in np.eye(6) * 1e-6], axis=1)
    np.testing.assert_allclose(projection_jacobian(cam), numeric, atol=1e-6)


def test_rotations_fitted_in_a_batch_equal_those_fitted_one_at_a_time() -> None:
    rng = np.random.default_rng(5)
    rays_a, rays_b = rng.normal(size=(16, 5, 3)), rng.normal(size=(16, 5, 3))
    batched = fit_rotation(rays_a, rays_b)
    for sample in range(16):
        np.testing.assert_array_equal(batched[sample], fit_rotation(rays_a[sample], rays_b[sample]))
        assert np.isclose(np.linalg.det(batched[sample]), 1.0)


def test_rotation_ransac_finds_a_pure_turn_among_wrong_tracks() -> None:
    rng = np.random.default_rng(6)
    truth = cv2.Rodrigues(np.array([0.02, -0.05, 0.01]))[0]
    rays = np.c_[rng.uniform(-0.5, 0.5, size=(200, 2)), np.ones(200)]
    turned = rays @ truth.T
    points_a, points_b = rays[:, :2], turned[:, :2] / turned[:, 2:]
    points_b[:60] += rng.uniform(0.02, 0.1, size=(60, 2))  # 30 % wrong matches
    rotation, residuals = fit_rotation_ransac(points_a, points_b, threshold=1e-3)
    assert np.degrees(np.arccos(np.clip((np.trace(rotation.T @ truth) - 1) / 2, -1, 1))) < 0.01
    assert np.count_nonzero(residuals < 1e-3) == 140
