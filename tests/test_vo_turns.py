"""Tracking through a turn, on synthetic scenes with known answers: the rotation measured on two frames' matches
(`tracking.image_rotation`) turns a failed prediction and vetoes a fallback's pose that disagrees with it, and a
new keyframe triangulates against its widest covisible keyframe (`mapping.widest_partner`)."""
from __future__ import annotations

import numpy as np

from tests.test_vo_localmap import FOCAL, frame_from, map_with_keyframes, pose_at, scene, settings
from vo_runtime.geometry import camera_centre
from vo_runtime.mapping import widest_partner
from vo_runtime.probation import rotation_angle_deg
from vo_runtime.tracking import IMAGE_ROTATION, WIDE_SEARCH, TrackOutcome, _agrees, image_rotation, track_frame, turned


def test_the_rotation_between_two_frames_is_measured_on_their_matches():
    world, desc = scene()
    before, after = pose_at(0.0, (0.5, 0, 0)), pose_at(0.04, (0.52, 0.0, 0.05))  # 2.3 deg of yaw, 5 cm ahead
    last, _ = frame_from(world, desc, before, seed=1)
    frame, _ = frame_from(world, desc, after, seed=2)
    turn = image_rotation(last, frame, settings())
    truth = after[:3, :3] @ before[:3, :3].T
    assert turn is not None and rotation_angle_deg(turn.T @ truth) < 0.1
    # Unrelated descriptors: nothing matches, nothing is measured.
    other, _ = frame_from(world, np.random.default_rng(5).normal(size=desc.shape), after, seed=2)
    other.descriptors /= np.linalg.norm(other.descriptors, axis=1, keepdims=True)
    assert image_rotation(last, other, settings()) is None


def test_a_turned_prediction_keeps_the_predicted_camera_centre():
    predicted, previous = pose_at(0.0, (0.8, 0.05, 1.0)), pose_at(0.01, (0.7, 0.0, 0.9))
    turn = pose_at(0.05, (0, 0, 0))[:3, :3]
    pose = turned(predicted, previous, turn)
    np.testing.assert_allclose(camera_centre(pose), camera_centre(predicted), atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], turn @ previous[:3, :3], atol=1e-12)


def test_a_failed_prediction_is_turned_by_the_measured_rotation_and_found_in_the_local_map():
    world, desc = scene()
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    before, truth = pose_at(0.0, (0.78, 0.05, 0.95)), pose_at(0.03, (0.8, 0.05, 1.0))
    last, order = frame_from(world, desc, before, seed=3)
    frame, _ = frame_from(world, desc, truth, seed=9)
    off = pose_at(-0.02, (0.8, 0.05, 1.0))  # the constant-velocity guess turned the wrong way: ~25 px off
    ids = np.arange(len(world))
    without = track_frame(local_map, ids, off, frame, (last, order.astype(np.int64)), settings(), before)
    assert without is not None and without.source == WIDE_SEARCH  # off by default: the wide search finds it
    outcome = track_frame(local_map, ids, off, frame, (last, order.astype(np.int64)),
                          settings(image_rotation_deg=1.0), before)
    assert outcome is not None and outcome.source == IMAGE_ROTATION
    np.testing.assert_allclose(outcome.pose_cw, truth, atol=1e-6)


def test_a_fallback_pose_that_turned_otherwise_than_the_frames_is_refused():
    previous = pose_at(0.0, (0.5, 0, 0))
    turn = pose_at(0.01, (0, 0, 0))[:3, :3]  # the frames turned 0.57 deg
    found = TrackOutcome(pose_at(0.04, (0.55, 0, 0.1)), np.zeros(0, np.int64), 40, 30, WIDE_SEARCH)  # 2.3 deg
    assert _agrees(found, previous, turn, settings(image_rotation_deg=1.0)) is None  # 1.7 deg apart
    assert _agrees(found, previous, turn, settings(image_rotation_deg=2.0)) is found
    assert _agrees(found, previous, None, settings(image_rotation_deg=1.0)) is found  # nothing measured: kept


def test_the_widest_partner_is_the_furthest_keyframe_that_still_shares_the_view():
    world, desc = scene(100)
    poses = [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.1, 0, 0)), pose_at(0.0, (0.9, 0, 0)), pose_at(0.0, (0.3, 0, 0))]
    local_map = map_with_keyframes(world, desc, poses)
    assert widest_partner(local_map, 0, 5, 20) == 2
    assert widest_partner(local_map, 2, 5, 20) == 0
    assert widest_partner(local_map, 0, 0, 20) is None  # off
    assert widest_partner(local_map, 0, 5, 101) is None  # none shares enough landmarks
    local_map.remove_observations(np.arange(90), np.full(90, 2))  # keyframe 2 keeps 10 landmarks of 100
    assert widest_partner(local_map, 0, 5, 20) == 3
