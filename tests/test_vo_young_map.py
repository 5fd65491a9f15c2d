"""A first map lost soon after it was built is discarded, and the next map is a first map (`young_map_frames`)."""
from __future__ import annotations

import numpy as np
import pytest

from test_vo_odometry import SyntheticExtractor, ate, run, straight_then_turn
from vo_runtime import VOConfig, VORuntimeError
from vo_runtime.odometry import INITIALISING, LOST, REINITIALISED, RELOCALISED, TRACKING

FRAMES = 80
SCRAMBLED = frozenset(range(20, 30))  # nothing matches: the first map is lost and cannot relocalise


def scrambled_run(young_map_frames: int, young_map_lost_frames: int = 40):
    poses = straight_then_turn(FRAMES)
    extractor = SyntheticExtractor(poses, scramble=SCRAMBLED)
    return poses, run(extractor, FRAMES, VOConfig(young_map_frames=young_map_frames,
                                                  young_map_lost_frames=young_map_lost_frames))


def test_a_young_first_map_that_is_lost_is_discarded_and_built_again_as_a_first_map():
    poses, vo = scrambled_run(young_map_frames=40)
    statuses = [r.status for r in vo.results]
    discarded = [r.index for r in vo.results if r.problem and r.problem.startswith("map discarded: lost")]
    assert len(discarded) == 1 and vo.results[discarded[0]].map_dropped
    # no frame is reported lost: the map's frames and the loss went back to initialising, held at the origin
    assert LOST not in statuses and REINITIALISED not in statuses
    again = next(i for i, s in enumerate(statuses) if s == TRACKING)
    assert again > discarded[0] > min(SCRAMBLED)
    assert all(s == INITIALISING for s in statuses[:again])
    assert all(not r.keyframe for r in vo.results[:again])
    np.testing.assert_allclose([r.pose for r in vo.results[:again]], [np.eye(4)] * again, atol=1e-12)
    assert all(s == TRACKING for s in statuses[again:])
    rmse, _ = ate([vo.results[i].pose for i in range(again, FRAMES)], poses[again:])
    assert rmse < 1e-6 * FRAMES


def test_off_or_an_older_map_the_map_is_kept_through_the_loss():
    # off; a map lost more than 15 frames after its first keyframe; the same map under a young_map_frames that
    # would discard it, when a loss is judged over young_map_lost_frames (15, or 0: never) instead
    for young_map_frames, lost_frames in ((0, 40), (15, 40), (40, 15), (40, 0)):
        _, vo = scrambled_run(young_map_frames, lost_frames)
        statuses = [r.status for r in vo.results]
        assert not any(r.map_dropped for r in vo.results)
        first = next(i for i, s in enumerate(statuses) if s == TRACKING)
        assert first < min(SCRAMBLED) and all(statuses[i] == LOST for i in SCRAMBLED)
        assert statuses[max(SCRAMBLED) + 1] == RELOCALISED and statuses[-1] == TRACKING  # the old map found again


def test_young_map_frames_is_checked():
    with pytest.raises(VORuntimeError):
        VOConfig(young_map_frames=-1)
    with pytest.raises(VORuntimeError):
        VOConfig(young_map_lost_frames=-1)


def test_young_map_lost_frames_judges_only_the_loss():
    """Losses judged over a shorter span (here: never) leave the travel check's verdict on a young map as it was:
    the map is discarded while within young_map_frames."""
    poses = straight_then_turn(FRAMES)
    config = VOConfig(travel_check_gap=5, travel_check_max_deg=1e-9, travel_check_frames=3, young_map_frames=80,
                      young_map_lost_frames=0, young_map_travel=True)
    vo = run(SyntheticExtractor(poses, noise_px=0.3), FRAMES, config)
    assert [r.problem.split(":")[0] for r in vo.results if r.map_dropped][:2] == ["map discarded", "map discarded"]
    assert VOConfig().young_map_lost_frames == 40 < VOConfig().young_map_frames


def test_with_young_map_travel_a_young_map_the_travel_check_breaks_is_discarded_too():
    """A travel gate every map fails: the first two maps (the discard budget) are discarded while young, their
    frames back to initialising; the third is abandoned as any map is (a new map at the speed before)."""
    poses = straight_then_turn(FRAMES)
    config = VOConfig(travel_check_gap=5, travel_check_max_deg=1e-9, travel_check_frames=3, young_map_frames=80,
                      young_map_travel=True)
    vo = run(SyntheticExtractor(poses, noise_px=0.3), FRAMES, config)
    dropped = [r for r in vo.results if r.map_dropped]
    assert [r.problem.split(":")[0] for r in dropped[:3]] == ["map discarded", "map discarded", "map abandoned"]
    second = dropped[1].index
    assert all(r.status == INITIALISING for r in vo.results[: second + 1])
    assert dropped[2].status in (LOST, REINITIALISED)  # held, or a new map at once on the check's baseline
    assert VOConfig().young_map_travel is True  # on by default
