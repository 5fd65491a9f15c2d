"""A keyframe's pose refined on its landmarks and its epipolar geometry (`vo_runtime.keyframe_pose`), on scenes
the tests build: a few near landmarks bunched in one corner of the view (the board under a drone) and many far
points without landmarks (the hall)."""
import numpy as np
import pytest

from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import camera_centre, left_increment, make_pose
from vo_runtime.keyframe_pose import epipolar_matches, refine_with_epipolar, sampson_distances
from vo_runtime.mapping import MappingConfig, essential_between
from vo_runtime.pose import refine_pose
from vo_runtime.probation import rotation_angle_deg

FOCAL = 460.0  # pixels, as the drone camera's


def rotation_about(axis, degrees):
    import cv2
    vector = np.radians(degrees) * np.asarray(axis, np.float64) / np.linalg.norm(axis)
    return cv2.Rodrigues(vector.reshape(3, 1))[0]


def project(pose_cw, world):
    camera = world @ pose_cw[:3, :3].T + pose_cw[:3, 3]
    return camera[:, :2] / camera[:, 2:3]


def scene(rng):
    """Poses a, b (b moved 15 mm and turned 1 deg), 40 near landmarks in one corner, 300 far points."""
    pose_a = np.eye(4)
    pose_b = make_pose(rotation_about([0.2, 1.0, 0.1], 1.0), [0.015, 0.004, 0.002])
    near = np.column_stack([rng.uniform(0.1, 0.35, 40), rng.uniform(0.1, 0.3, 40), rng.uniform(1.8, 2.2, 40)])
    far = np.column_stack([rng.uniform(-0.45, 0.45, 300) * 30, rng.uniform(-0.3, 0.3, 300) * 30,
                           rng.uniform(25, 35, 300)])
    return pose_a, pose_b, near, far


def noisy(points, rng, pixels=0.5):
    return points + rng.normal(0.0, pixels / FOCAL, points.shape)


def test_sampson_distance_is_zero_on_the_epipolar_geometry_and_grows_off_it():
    rng = np.random.default_rng(0)
    pose_a, pose_b, near, far = scene(rng)
    world = np.vstack([near, far])
    points_a, points_b = project(pose_a, world), project(pose_b, world)
    essential = essential_between(pose_a, pose_b)
    assert np.abs(sampson_distances(essential, points_a, points_b)).max() < 1e-9
    # b moved along x, so epipolar lines run roughly along x: a shift along y leaves them, and twice the shift
    # gives twice the distance (first order), with the sign following the side
    shift = np.array([0.0, 2.0 / FOCAL])
    one = sampson_distances(essential, points_a, points_b + shift)
    two = sampson_distances(essential, points_a, points_b + 2 * shift)
    minus = sampson_distances(essential, points_a, points_b - shift)
    assert np.all(np.abs(one) > 0.5 / FOCAL)
    np.testing.assert_allclose(two, 2 * one, rtol=1e-3)
    np.testing.assert_allclose(minus, -one, rtol=1e-3)


def test_epipolar_matches_drop_matches_off_the_geometry():
    rng = np.random.default_rng(1)
    pose_a, pose_b, near, far = scene(rng)
    world = np.vstack([near, far])
    points_a, points_b = project(pose_a, world), project(pose_b, world)
    descriptors = rng.normal(size=(len(world), 32)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    points_b[:20] += np.array([0.0, 30.0 / FOCAL])   # 20 matches 30 px off their epipolar lines
    kept_a, kept_b = epipolar_matches(points_a, descriptors, points_b, descriptors, pose_a, pose_b,
                                      20.0 / FOCAL, 0.9, 0.9)
    assert len(kept_a) == len(world) - 20
    np.testing.assert_allclose(kept_a, points_a[20:])


def test_the_epipolar_terms_fix_the_rotation_that_bunched_landmarks_trade_for_translation():
    errors_landmarks, errors_joint, centres_landmarks, centres_joint, residuals = [], [], [], [], []
    for seed in range(5):
        rng = np.random.default_rng(10 + seed)
        pose_a, pose_b, near, far = scene(rng)
        observed = noisy(project(pose_b, near), rng)
        # tracking's pose: the landmarks' own refinement from a start 0.7 deg off in rotation
        start = left_increment(pose_b, np.r_[np.radians(0.7) * np.array([1.0, 0.0, 0.0]), np.zeros(3)])
        tracked, _ = refine_pose(near, observed, start, 3.0 / FOCAL, 20)
        points_a, points_b = noisy(project(pose_a, far), rng), noisy(project(pose_b, far), rng)
        refined = refine_with_epipolar(tracked, near, observed, pose_a, points_a, points_b, 1.5 / FOCAL)
        errors_landmarks.append(rotation_angle_deg(tracked[:3, :3] @ pose_b[:3, :3].T))
        errors_joint.append(rotation_angle_deg(refined[:3, :3] @ pose_b[:3, :3].T))
        centres_landmarks.append(np.linalg.norm(camera_centre(tracked) - camera_centre(pose_b)))
        centres_joint.append(np.linalg.norm(camera_centre(refined) - camera_centre(pose_b)))
        residuals.append(np.sqrt(np.mean((project(refined, near) - observed) ** 2)) * FOCAL)
    assert np.median(errors_landmarks) > 0.2           # the ambiguity this module exists for
    assert np.median(errors_joint) < 0.5 * np.median(errors_landmarks)
    assert max(errors_joint) < 0.15
    # the landmarks still explain the pose (0.5 px noise) and hold its position no worse than alone (a 40-point
    # corner 2 m away places the camera to 3-18 mm either way)
    assert max(residuals) < 1.0
    assert np.median(centres_joint) <= np.median(centres_landmarks)


def test_wrong_matches_through_the_gate_do_not_move_a_right_pose():
    rng = np.random.default_rng(3)
    pose_a, pose_b, near, far = scene(rng)
    observed = project(pose_b, near)
    points_a, points_b = project(pose_a, far), project(pose_b, far)
    points_b[:60] = rng.uniform([-0.8, -0.5], [0.8, 0.5], (60, 2))   # a fifth of the matches anywhere in view
    descriptors = rng.normal(size=(len(far), 32)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    kept_a, kept_b = epipolar_matches(points_a, descriptors, points_b, descriptors, pose_a, pose_b,
                                      20.0 / FOCAL, 0.9, 0.9)
    assert len(far) - 60 < len(kept_a) < len(far) - 40   # most wrong ones caught by the gate, a few not
    refined = refine_with_epipolar(pose_b, near, observed, pose_a, kept_a, kept_b, 1.5 / FOCAL)
    # the few through the gate move it along the bunched landmarks' weak direction, but by ~0.3 px, not the
    # 0.2-0.7 deg (2-5 px) of the ambiguity the refinement removes (without them: exact)
    assert rotation_angle_deg(refined[:3, :3] @ pose_b[:3, :3].T) < 0.06
    assert np.linalg.norm(refined[:3, 3] - pose_b[:3, 3]) < 2.5e-3   # the translation that trades for it


def test_config_rejects_a_negative_weight():
    with pytest.raises(VORuntimeError, match="keyframe_epipolar_weight"):
        MappingConfig(keyframe_epipolar_weight=-1.0)
    with pytest.raises(VORuntimeError, match="keyframe_epipolar_weight"):
        MappingConfig(keyframe_epipolar_scale_px=0.0)

