"""ORB-SLAM's baseline rule for new landmarks (`mapping.min_baseline_depth`): two keyframes closer than a share of
the partner's median landmark depth triangulate nothing, on a synthetic scene with known depths (6-30 m); `MonoVO`
keeps the rule to a young first map."""
from __future__ import annotations

import numpy as np
import pytest

import vo_runtime.keyframing
from tests.test_vo_localmap import FOCAL, frame_from, pose_at, scene
from tests.test_vo_odometry import SyntheticExtractor, run, straight_then_turn
from vo_runtime import VOConfig
from vo_runtime.errors import VORuntimeError
from vo_runtime.localmap import Keyframe, LocalMap
from vo_runtime.mapping import MappingConfig, short_baseline, triangulate_new_landmarks

MAPPED = 150  # the first 150 points are landmarks both keyframes see; the other 150 are keypoints without one


def two_keyframes(baseline: float) -> LocalMap:
    """Keyframe 0 at the origin, keyframe 1 ``baseline`` metres to its right, both seeing every point."""
    world, descriptors = scene(300)
    local_map = LocalMap(descriptors.shape[1])
    rows = []
    for number, pose in enumerate([pose_at(0.0, (0.0, 0.0, 0.0)), pose_at(0.0, (baseline, 0.0, 0.0))]):
        frame, order = frame_from(world, descriptors, pose, seed=number)
        local_map.add_keyframe(Keyframe(number, pose, frame.points, frame.pixels, frame.descriptors,
                                        np.full(len(order), -1, np.int64)))
        rows.append(np.argsort(order))  # keypoint row of each point
    local_map.add_landmarks(world[:MAPPED], [(0, rows[0][:MAPPED]), (1, rows[1][:MAPPED])], np.full(MAPPED, 5.0))
    return local_map


def new_landmarks(baseline: float, share: float, rule: bool = True) -> int:
    local_map = two_keyframes(baseline)
    config = MappingConfig(min_baseline_depth=share, min_parallax_px=0.5)
    return triangulate_new_landmarks(local_map, 1, config, FOCAL, max_distance=0.9, ratio=0.9, baseline_rule=rule)


def test_the_rule_compares_the_baseline_with_the_partners_median_depth():
    world, _ = scene(300)
    median = float(np.median(world[:MAPPED, 2]))  # keyframe 0 sits at the origin looking down z
    for baseline in (0.5 * 0.01 * median, 0.9 * 0.01 * median):
        assert short_baseline(two_keyframes(baseline), 0, 1, 0.01)
    assert not short_baseline(two_keyframes(1.1 * 0.01 * median), 0, 1, 0.01)
    assert not short_baseline(two_keyframes(0.5 * 0.01 * median), 0, 1, 0.0)  # off


def test_a_short_baseline_triangulates_nothing_and_a_long_one_or_the_rule_off_does():
    # 0.1 m against a median depth near 18 m: 0.6 % of it
    assert new_landmarks(0.1, 0.01) == 0
    assert new_landmarks(0.1, 0.0) > 100
    assert new_landmarks(0.5, 0.01) > 100  # 2.8 %
    assert new_landmarks(0.1, 0.01, rule=False) > 100  # a keyframe the rule is not applied to


def test_the_vo_applies_the_rule_while_its_first_map_is_young(monkeypatch):
    # A map lost while young is discarded and built again, so running out of landmarks costs little then; later a
    # loss costs the track (a drone slowing near structure the far map's depth rules out: docs/vo_euroc.md).
    seen = []

    def recording(local_map, number, *args, **kwargs):
        seen.append((local_map.keyframes[number].frame - local_map.keyframes[0].frame, kwargs["baseline_rule"]))
        return triangulate_new_landmarks(local_map, number, *args, **kwargs)

    monkeypatch.setattr(vo_runtime.keyframing, "triangulate_new_landmarks", recording)
    poses = straight_then_turn(60)
    run(SyntheticExtractor(poses), 60, VOConfig(young_map_frames=20, keyframe_max_gap=3))
    assert len(seen) > 10
    assert all(rule == (age <= 20) for age, rule in seen)
    assert {rule for _, rule in seen} == {True, False}


def test_the_share_is_checked():
    for bad in (-0.01, 1.0):
        with pytest.raises(VORuntimeError, match="min_baseline_depth"):
            MappingConfig(min_baseline_depth=bad)
