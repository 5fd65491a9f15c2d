"""A young map adjusted once as a whole (`mapping.consolidate_map`): the local adjustment never moves a map's first
two keyframes, so an error in the first baseline stays; the consolidation moves every keyframe but the first and
the newest, on a synthetic map whose second keyframe is placed wrong."""
from __future__ import annotations

import numpy as np
import pytest

from tests.test_vo_localmap import FOCAL, map_with_keyframes, pose_at, scene
from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import camera_centre
from vo_runtime.mapping import MappingConfig, consolidate_map, local_bundle_adjustment
from vo_runtime.probation import rotation_angle_deg


def young_map():
    world, desc = scene(300)
    truth = [pose_at(0.01 * k, (0.25 * k, 0.0, 0.1 * k)) for k in range(6)]
    local_map = map_with_keyframes(world, desc, truth)
    wrong = pose_at(0.01 + 0.01, (0.25, 0.03, 0.1))  # 0.57 deg of yaw and 3 cm off: a poor first baseline
    local_map.keyframes[1].pose_cw = wrong
    return local_map, truth


def test_the_local_adjustment_leaves_the_first_baseline_as_it_is():
    local_map, truth = young_map()
    wrong = local_map.keyframes[1].pose_cw.copy()
    moved = local_bundle_adjustment(local_map, 5, MappingConfig(), FOCAL)
    assert 1 not in moved and 0 not in moved
    np.testing.assert_array_equal(local_map.keyframes[1].pose_cw, wrong)


def test_the_consolidation_moves_the_first_baseline_back_and_holds_the_first_and_newest_keyframe():
    local_map, truth = young_map()
    before = rotation_angle_deg(local_map.keyframes[1].pose_cw[:3, :3] @ truth[1][:3, :3].T)
    moved = consolidate_map(local_map, MappingConfig(), FOCAL)
    assert moved == [1, 2, 3, 4]
    after = rotation_angle_deg(local_map.keyframes[1].pose_cw[:3, :3] @ truth[1][:3, :3].T)
    assert before > 0.5 and after < 0.02
    assert np.linalg.norm(camera_centre(local_map.keyframes[1].pose_cw) - camera_centre(truth[1])) < 2e-3
    for number in (0, 5):  # the gauge and the scale
        np.testing.assert_array_equal(local_map.keyframes[number].pose_cw, truth[number])


def test_a_map_of_two_keyframes_has_nothing_to_consolidate_and_the_setting_is_checked():
    world, desc = scene(100)
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.3, 0, 0))])
    assert consolidate_map(local_map, MappingConfig(), FOCAL) == []
    for bad in (-1, 1, 2):
        with pytest.raises(VORuntimeError, match="consolidate_keyframes"):
            MappingConfig(consolidate_keyframes=bad)
