"""Local-map tracking parts on synthetic scenes with known answers: guided matching by projection, epipolar
matching between keyframes, pose tracking with its fallbacks, and relocalisation against keyframes."""
from __future__ import annotations

import cv2
import numpy as np

from vo_runtime.geometry import invert_pose, make_pose
from vo_runtime.localmap import Keyframe, LocalMap
from vo_runtime.mapping import essential_between
from vo_runtime.matching import match_by_projection, match_epipolar
from vo_runtime.relocalise import relocalise
from vo_runtime.tracking import LOCAL_MAP, PREVIOUS_FRAME, WIDE_SEARCH, FrameData, TrackingSettings, track_frame

FOCAL = 500.0
RNG_SEED = 7


def unit(rows: np.ndarray) -> np.ndarray:
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def scene(points: int = 400, seed: int = RNG_SEED) -> tuple[np.ndarray, np.ndarray]:
    """World points in front of the origin camera and one random unit descriptor each."""
    rng = np.random.default_rng(seed)
    world = np.c_[rng.uniform(-8, 8, points), rng.uniform(-3, 3, points), rng.uniform(6, 30, points)]
    return world, unit(rng.normal(size=(points, 32)))


def project(world: np.ndarray, pose_cw: np.ndarray) -> np.ndarray:
    cam = world @ pose_cw[:3, :3].T + pose_cw[:3, 3]
    return cam[:, :2] / cam[:, 2:3]


def pose_at(yaw: float, position: tuple[float, float, float]) -> np.ndarray:
    """World-to-camera pose of a camera at ``position`` turned by ``yaw`` about y."""
    rotation = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]
    return invert_pose(make_pose(rotation, position))


def frame_from(world: np.ndarray, descriptors: np.ndarray, pose_cw: np.ndarray, seed: int = 0) -> tuple[FrameData, np.ndarray]:
    """The frame a camera at ``pose_cw`` sees, keypoints shuffled; returns it and the point index per keypoint."""
    order = np.random.default_rng(seed).permutation(len(world))
    points = project(world, pose_cw)[order]
    return FrameData.build(points, points * FOCAL, descriptors[order]), order


def settings(**changes) -> TrackingSettings:
    values = dict(focal=FOCAL, bounds=(-2.0, 2.0, -2.0, 2.0), radius_px=10.0, wide_radius_px=40.0, threshold_px=2.0,
                  min_inliers=20, max_distance=0.9, ratio=0.9, max_points=1000)
    values.update(changes)
    return TrackingSettings(**values)


def map_with_keyframes(world: np.ndarray, descriptors: np.ndarray, poses: list[np.ndarray]) -> LocalMap:
    """A map whose keyframes at ``poses`` observe every point (landmark i is point i)."""
    local_map = LocalMap(descriptors.shape[1])
    for number, pose in enumerate(poses):
        frame, order = frame_from(world, descriptors, pose, seed=number)
        local_map.add_keyframe(Keyframe(number, pose, frame.points, frame.pixels, frame.descriptors,
                                        np.full(len(order), -1, np.int64)))
    rows = [np.argsort(frame_from(world, descriptors, pose, seed=n)[1]) for n, pose in enumerate(poses)]
    local_map.add_landmarks(world, [(n, rows[n]) for n in range(len(poses))], np.full(len(world), 5.0))
    return local_map


# ---------------------------------------------------------------------------------------------- matching
def test_projection_matching_takes_the_right_keypoint_within_the_radius():
    rng = np.random.default_rng(0)
    landmarks = rng.uniform(0, 600, size=(50, 2))
    desc = unit(rng.normal(size=(50, 32)))
    # Each landmark's true keypoint lies 3 px from its projection; a look-alike (the same descriptor as the
    # true keypoint) lies 25 px away.
    angle = rng.uniform(0, 2 * np.pi, 50)
    true_kp = landmarks + 3.0 * np.c_[np.cos(angle), np.sin(angle)]
    decoy_kp = landmarks + np.array([25.0, 0.0])
    keypoints = np.concatenate([true_kp, decoy_kp])
    seen = unit(desc + 0.05 * rng.normal(size=desc.shape))
    kp_desc = np.concatenate([seen, seen])
    pairs = match_by_projection(landmarks, desc, keypoints, kp_desc, radius_px=10.0)
    np.testing.assert_array_equal(pairs, np.c_[np.arange(50), np.arange(50)])
    # A radius that also reaches the look-alikes makes every landmark ambiguous: the ratio test drops them all.
    assert match_by_projection(landmarks, desc, keypoints, kp_desc, radius_px=30.0, ratio=0.9).shape == (0, 2)
    assert len(match_by_projection(landmarks, desc, keypoints, kp_desc, radius_px=30.0, ratio=None)) == 50
    assert match_by_projection(landmarks, desc, keypoints, kp_desc, radius_px=2.5).shape == (0, 2)  # nothing that close


def test_a_contested_keypoint_goes_to_the_closest_descriptor():
    desc = unit(np.array([[1.0, 0.0, 0.0], [1.0, 0.3, 0.0]]))
    keypoints, kp_desc = np.array([[100.0, 100.0]]), unit(np.array([[1.0, 0.05, 0.0]]))
    pairs = match_by_projection(np.array([[101.0, 100.0], [99.0, 100.0]]), desc, keypoints, kp_desc, radius_px=5.0)
    np.testing.assert_array_equal(pairs, [[0, 0]])


def test_epipolar_matching_rejects_a_look_alike_off_the_line():
    world, desc = scene(200)
    pose_a, pose_b = pose_at(0.0, (0, 0, 0)), pose_at(0.05, (1.0, 0.0, 0.5))
    pts_a, pts_b = project(world, pose_a), project(world, pose_b)
    # Point 0 of b is moved 20 px off its epipolar line (descriptor unchanged): it may not match.
    pts_b[0] += np.array([0.0, 20.0 / FOCAL])
    pairs = match_epipolar(pts_a, desc, pts_b, desc, essential_between(pose_a, pose_b), 2.0 / FOCAL)
    assert 0 not in pairs[:, 0]
    np.testing.assert_array_equal(pairs[:, 0], pairs[:, 1])
    assert len(pairs) == 199


# ---------------------------------------------------------------------------------------------- tracking
def test_guided_tracking_recovers_the_pose_from_a_close_prediction():
    world, desc = scene()
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    truth = pose_at(0.03, (0.8, 0.05, 1.0))
    frame, order = frame_from(world, desc, truth, seed=9)
    predicted = pose_at(0.025, (0.75, 0.05, 0.95))  # a few pixels off: the constant-velocity guess
    outcome = track_frame(local_map, np.arange(len(world)), predicted, frame, None, settings())
    assert outcome is not None and outcome.source == LOCAL_MAP
    np.testing.assert_allclose(outcome.pose_cw, truth, atol=1e-6)
    matched = outcome.landmark >= 0
    assert matched.mean() > 0.95
    np.testing.assert_array_equal(outcome.landmark[matched], order[matched])  # each keypoint to its own point
    assert local_map.found[:len(world)].max() == 2  # found once at creation, once here


def test_a_bad_prediction_falls_back_to_the_wide_search_then_the_previous_frame():
    world, desc = scene()
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    truth = pose_at(0.03, (0.8, 0.05, 1.0))
    frame, _ = frame_from(world, desc, truth, seed=9)
    off = pose_at(0.07, (0.8, 0.05, 1.0))  # 2.3 deg of yaw off: ~20 px, beyond the small radius
    outcome = track_frame(local_map, np.arange(len(world)), off, frame, None, settings())
    assert outcome is not None and outcome.source == WIDE_SEARCH
    np.testing.assert_allclose(outcome.pose_cw, truth, atol=1e-6)
    # Far off (17 deg): neither radius reaches; the previous frame's matches to landmarks give the pose.
    previous, order = frame_from(world, desc, local_map.keyframes[1].pose_cw, seed=3)
    lost = pose_at(0.33, (0.8, 0.05, 1.0))
    outcome = track_frame(local_map, np.arange(len(world)), lost, frame, (previous, order.astype(np.int64)),
                          settings())
    assert outcome is not None and outcome.source == PREVIOUS_FRAME
    np.testing.assert_allclose(outcome.pose_cw, truth, atol=1e-6)
    assert track_frame(local_map, np.arange(len(world)), lost, frame, None, settings()) is None


# ---------------------------------------------------------------------------------------------- relocalisation
def test_relocalisation_finds_the_pose_from_keyframes_alone():
    world, desc = scene()
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.02, (0.5, 0, 0.3))])
    truth = pose_at(-0.06, (0.3, -0.1, 0.8))
    frame, _ = frame_from(world, desc, truth, seed=11)
    found = relocalise(local_map, frame.points, frame.descriptors, keyframes=2, threshold=2.0 / FOCAL,
                       min_inliers=20, max_distance=0.9, ratio=0.9)
    assert found is not None
    pose, keyframe = found
    np.testing.assert_allclose(pose, truth, atol=1e-6)
    assert keyframe == 1  # the newest keyframe is tried first
    # A frame of unrelated descriptors (another place) does not relocalise.
    other = unit(np.random.default_rng(1).normal(size=frame.descriptors.shape))
    assert relocalise(local_map, frame.points, other, keyframes=2, threshold=2.0 / FOCAL, min_inliers=20,
                      max_distance=0.9, ratio=0.9) is None


def test_dead_landmarks_leave_their_keyframes():
    world, desc = scene(50)
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    local_map.kill(np.array([3, 4]))
    assert set(local_map.landmarks_of([0, 1]).tolist()) == set(range(50)) - {3, 4}
    local_map.remove_observations(np.array([5]), np.array([0]))  # one view left: it cannot be triangulated
    assert not local_map.alive[5] and 5 not in local_map.keyframes[1].landmark


def test_neighbour_keyframes_gain_the_observations_tracking_missed():
    from vo_runtime.mapping import MappingConfig, observe_in_neighbours

    world, desc = scene(200)
    poses = [pose_at(0.0, (0, 0, 0)), pose_at(0.02, (0.4, 0, 0)), pose_at(0.04, (0.8, 0, 0))]
    local_map = map_with_keyframes(world, desc, poses)
    middle = local_map.keyframes[1]
    rows = np.array([local_map.observations[i][1] for i in range(60)])
    local_map.remove_observations(np.arange(60), np.ones(60, np.int64))  # keyframe 1 never matched 0-59
    assert all(local_map.alive[:60]) and not np.isin(np.arange(60), middle.landmark).any()
    rng = np.random.default_rng(1)
    middle.descriptors[rows[40:50]] = unit(rng.normal(size=(10, desc.shape[1])))  # 40-49: another look
    middle.points[rows[50:60]] += 20.0 / FOCAL  # 50-59: 28 px from where the map projects them

    off = MappingConfig(neighbour_keyframes=0)
    assert observe_in_neighbours(local_map, 2, off, FOCAL, 0.9, 0.9) == 0 and middle.landmark[rows].max() < 0
    added = observe_in_neighbours(local_map, 2, MappingConfig(neighbour_keyframes=2, neighbour_radius_px=3.0),
                                  FOCAL, 0.9, 0.9)
    assert added == 40
    assert np.array_equal(middle.landmark[rows[:40]], np.arange(40))  # each at its own keypoint
    assert (middle.landmark[rows[40:]] < 0).all()
    assert all(list(local_map.observations[i]) == [0, 1, 2] for i in range(40))  # kept in keyframe order


def test_landmarks_only_old_keyframes_see_retire_and_their_ids_are_reused_only_after_the_horizon():
    world, desc = scene(50)
    poses = [pose_at(0.0, (0.5 * k, 0, 0)) for k in range(3)]
    local_map = map_with_keyframes(world, desc, poses[:2])  # landmarks 0-49 seen by keyframes 0 and 1
    frame, order = frame_from(world, desc, poses[2], seed=2)
    later = np.full(len(order), -1, np.int64)
    later[np.argsort(order)[:10]] = np.arange(10)  # keyframe 2 sees landmarks 0-9 again
    local_map.add_keyframe(Keyframe(2, poses[2], frame.points, frame.pixels, frame.descriptors, later))
    local_map.retire(1)  # keyframe 1 is behind the horizon: what only keyframes 0 and 1 see dies
    assert set(np.flatnonzero(local_map.alive[:local_map.size]).tolist()) == set(range(10))
    assert set(local_map.keyframes[0].landmark_ids().tolist()) == set(range(10))
    local_map.recycle(2)  # they died with 3 keyframes in the map: not yet free
    fresh = local_map.add_landmarks(world[:5], [(1, np.arange(5)), (2, np.arange(5))], np.full(5, 3.0))
    assert fresh.tolist() == list(range(50, 55))
    local_map.recycle(3)
    reused = local_map.add_landmarks(world[:5] + 1.0, [(1, np.arange(5)), (2, np.arange(5))], np.full(5, 3.0))
    assert set(reused.tolist()) <= set(range(10, 50)) and local_map.size == 55
    assert all(local_map.observations[i] == {1: r, 2: r} for r, i in enumerate(reused.tolist()))
    np.testing.assert_allclose(local_map.positions[reused], world[:5] + 1.0)
    assert local_map.alive[reused].all() and (local_map.created[reused] == 2).all()


def test_a_released_keyframe_keeps_its_pose_and_observations_but_not_its_descriptors():
    world, desc = scene(50)
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    before = local_map.landmarks_of([0])
    local_map.release_descriptors(0)
    assert local_map.keyframes[0].descriptors is None
    np.testing.assert_array_equal(local_map.landmarks_of([0]), before)
    local_map._update_descriptors(before)  # the medoid is then chosen among the views that kept theirs
    frame, order = frame_from(world, desc, pose_at(0.0, (0.5, 0, 0)), seed=1)
    np.testing.assert_allclose(local_map.descriptors[order], frame.descriptors)
