"""A map re-initialised after a loss finds the lost map and takes its frame and scale (`map_merge.py`): the
similarity on a synthetic scene with a known answer, its refusals, and the VO's scale after a loss."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

import vo_runtime.odometry as odometry
from tests.test_vo_localmap import FOCAL, frame_from, map_with_keyframes, pose_at, scene
from tests.test_vo_odometry import SyntheticExtractor, creeping_before, run, straight_then_turn
from vo_runtime.config import VOConfig
from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import invert_pose, make_pose
from vo_runtime.map_merge import Similarity, find_in_lost_map
from vo_runtime.states import REINITIALISED

# The new map's world: the lost one turned, moved and shrunk to 0.3 of its scale (a re-initialisation's guess).
TRUE_SCALE = 3.0 / 0.9  # lost units per new unit
TURN = cv2.Rodrigues(np.array([0.1, -0.4, 0.2]))[0]
SHIFT = np.array([2.0, -1.0, 0.5])


def to_new_world(points: np.ndarray) -> np.ndarray:
    """Lost-world points in the new world: x_lost = TRUE_SCALE * TURN @ x_new + SHIFT, inverted."""
    return (points - SHIFT) @ TURN / TRUE_SCALE


def new_pose(pose_cw: np.ndarray) -> np.ndarray:
    """A lost-world camera pose in the new world (its centre and orientation, new units)."""
    pose_wc = invert_pose(pose_cw)
    return invert_pose(make_pose(TURN.T @ pose_wc[:3, :3], to_new_world(pose_wc[:3, 3][None])[0]))


def lost_map_and_frame(known: float = 0.5):
    """The lost map (two keyframes over a scene) and a later frame, with the new map's positions of ``known``
    of its keypoints' points (NaN for the rest)."""
    world, descriptors = scene()
    lost = map_with_keyframes(world, descriptors, [pose_at(0.0, (0, 0, 0)), pose_at(0.05, (0.5, 0, 0))])
    pose_lost = pose_at(0.1, (1.0, 0.2, 0.3))
    frame, order = frame_from(world, descriptors, pose_lost, seed=11)
    positions = to_new_world(world[order])
    positions[np.random.default_rng(3).random(len(order)) > known] = np.nan
    return lost, frame, positions, pose_lost


def find(lost, frame, positions, pose_new, **changes):
    values = dict(threshold=2.0 / FOCAL, min_pairs=20, max_spread=0.1, max_distance=0.9, ratio=0.9)
    values.update(changes)
    return find_in_lost_map(lost, [1, 0], frame.points, frame.descriptors, positions, pose_new, **values)


def test_the_similarity_maps_the_new_map_onto_the_lost_one():
    lost, frame, positions, pose_lost = lost_map_and_frame()
    found = find(lost, frame, positions, new_pose(pose_lost))
    assert isinstance(found, Similarity)
    assert found.scale == pytest.approx(TRUE_SCALE, rel=1e-6)
    assert found.pairs > 100 and found.spread < 1e-6
    np.testing.assert_allclose(found.pose(new_pose(pose_lost)), pose_lost, atol=1e-6)
    known = np.isfinite(positions[:, 0])
    world_lost = (positions[known] * TRUE_SCALE) @ TURN.T + SHIFT
    np.testing.assert_allclose(found.point(positions[known]), world_lost, atol=1e-6)
    # A motion between two cameras keeps its rotation, and its translation takes the lost map's scale.
    step = make_pose(TURN, np.array([0.1, 0.0, 0.2]))
    np.testing.assert_allclose(found.relative(step)[:3, 3], TRUE_SCALE * step[:3, 3])
    np.testing.assert_allclose(found.relative(step)[:3, :3], TURN)


def test_no_similarity_from_another_place_too_few_shared_landmarks_or_no_single_scale():
    lost, frame, positions, pose_lost = lost_map_and_frame()
    rng = np.random.default_rng(5)
    other = rng.normal(size=frame.descriptors.shape)
    frame_elsewhere = type(frame).build(frame.points, frame.pixels, other / np.linalg.norm(other, axis=1, keepdims=True))
    assert find(lost, frame_elsewhere, positions, new_pose(pose_lost)) is None
    # The lost map found, but only 4 % of the frame's keypoints are landmarks of the new map: 20 pairs needed.
    lost, frame, few, pose_lost = lost_map_and_frame(known=0.04)
    assert 0 < np.count_nonzero(np.isfinite(few[:, 0])) < 20
    assert find(lost, frame, few, new_pose(pose_lost)) is None
    # Landmarks of the new map at depths that disagree by a random factor of up to 2: no one scale.
    lost, frame, positions, pose_lost = lost_map_and_frame()
    centre = invert_pose(new_pose(pose_lost))[:3, 3]
    scattered = centre + (positions - centre) * rng.uniform(0.5, 2.0, (len(positions), 1))
    assert find(lost, frame, scattered, new_pose(pose_lost)) is None


@pytest.mark.parametrize("merge_keyframes", [0, 20])
def test_a_map_re_initialised_at_a_wrong_scale_takes_the_lost_maps(monkeypatch, merge_keyframes):
    # Frames 26-29 creep at a tenth of the speed, the camera is lost at 30 and relocalisation fails (as in the
    # dark); with speed_frames 1 the new map takes the creep's scale, ten times too short. Merged, its steps are
    # the lost map's again; without a merge they stay short.
    monkeypatch.setattr(odometry, "relocalise", lambda *args, **kwargs: None)
    poses = creeping_before(30, straight_then_turn(60))
    vo = run(SyntheticExtractor(poses, scramble=frozenset({30})), 60,
             VOConfig(lost_predict_frames=0, speed_frames=1, young_map_frames=0, merge_keyframes=merge_keyframes))
    statuses = [r.status for r in vo.results]
    assert REINITIALISED in statuses[31:]
    merged = [r for r in vo.results if r.merged_scale is not None]
    est = np.array([r.pose[:3, 3] for r in vo.results])
    before = np.linalg.norm(est[20] - est[19])
    after = np.linalg.norm(est[59] - est[58])
    if merge_keyframes == 0:
        assert not merged and after == pytest.approx(0.1 * before, rel=0.1)
        return
    assert len(merged) == 1 and merged[0].merged_scale == pytest.approx(10.0, rel=0.1)
    assert after == pytest.approx(before, rel=0.02)
    # Every frame tracked on the new map, before the merge too, sits on the true path in the lost map's frame.
    first = statuses.index(REINITIALISED, 31)
    truth = np.array([pose[:3, 3] for pose in poses])
    true_step = np.linalg.norm(truth[20] - truth[19])
    scale = true_step / before
    origin = truth[19] - scale * est[19]  # the first map's frame is the first camera's, as the truth's
    errors = [np.linalg.norm(origin + scale * est[index] - truth[index]) for index in range(first, 60)]
    assert max(errors) < 0.5 * true_step


@pytest.mark.parametrize("field, value", [("merge_keyframes", -1), ("merge_min_pairs", 5), ("merge_max_spread", 0.0)])
def test_merge_settings_are_validated(field, value):
    with pytest.raises(VORuntimeError, match=field):
        VOConfig(**{field: value})
