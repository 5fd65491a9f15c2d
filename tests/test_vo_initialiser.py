"""The two-view initialiser's tracks: chains from the reference that break in one bad frame are found again
by a direct match against the reference, only while the chains are dying."""
from __future__ import annotations

import numpy as np

from vo_runtime import VOConfig
from vo_runtime.initialiser import ROW_MASK, Initialiser
from vo_runtime.tracking import FrameData

RNG = np.random.default_rng(7)
N = 200
DESCRIPTORS = RNG.normal(size=(N, 64))
DESCRIPTORS /= np.linalg.norm(DESCRIPTORS, axis=1, keepdims=True)
POINTS = RNG.uniform(-0.5, 0.5, size=(N, 2))


def frame(keep: np.ndarray, shift: float, order: np.ndarray) -> FrameData:
    """The reference's keypoints moved by ``shift``, listed in ``order``; rows outside ``keep`` carry fresh
    random descriptors (their chain breaks here)."""
    desc = DESCRIPTORS.copy()
    fresh = RNG.normal(size=(N, 64))
    desc[~keep] = (fresh / np.linalg.norm(fresh, axis=1, keepdims=True))[~keep]
    points = POINTS + shift
    return FrameData.build(points[order], 500.0 * points[order], desc[order])


def run(survivors: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference, then a frame where only ``survivors`` chains hold, then a clean frame; its tracks."""
    initialiser = Initialiser(VOConfig(), focal=500.0)
    initialiser.restart(0, frame(np.ones(N, bool), 0.0, np.arange(N)))
    keep = np.zeros(N, bool)
    keep[:survivors] = True
    initialiser.add(1, frame(keep, 0.01, RNG.permutation(N)))
    order = RNG.permutation(N)
    initialiser.add(2, frame(np.ones(N, bool), 0.02, order))
    tracks = initialiser._previous[1]
    from_reference = tracks.first_frame == 0
    return order, tracks, from_reference


def test_broken_chains_resume_from_the_reference_while_they_die():
    order, tracks, from_reference = run(survivors=60)  # 60 < 3 x min_matches: dying
    assert np.count_nonzero(from_reference) >= 190
    assert np.count_nonzero(tracks.resumed) >= 130 and not tracks.resumed[from_reference & ~tracks.resumed].any()
    # Each resumed track points at its own keypoint in the reference, and starts where that keypoint was.
    rows = np.flatnonzero(from_reference)
    np.testing.assert_array_equal(tracks.ids[rows] & ROW_MASK, order[rows])
    np.testing.assert_allclose(tracks.first_points[rows], POINTS[order[rows]])


def test_healthy_chains_are_left_alone():
    _, tracks, from_reference = run(survivors=150)  # 150 >= 90: not dying
    assert np.count_nonzero(from_reference) == 150 and not tracks.resumed.any()


def _two_views(consistent: float) -> tuple[Initialiser, list[np.ndarray]]:
    """Tracks between two views of a rigid scene 0.5 units apart, of which only the share ``consistent`` follow
    the scene (the rest land anywhere: broken matches, as in a blurred take-off); the initialiser holds them."""
    rng = np.random.default_rng(11)
    world = np.column_stack([rng.uniform(-3, 3, N), rng.uniform(-2, 2, N), rng.uniform(4, 8, N)])
    angle = np.radians(3.0)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = world @ rotation.T + (0.5, 0.05, 0.1)
    reference, current = world[:, :2] / world[:, 2:], moved[:, :2] / moved[:, 2:]
    bad = rng.permutation(N)[: int(round((1 - consistent) * N))]
    current[bad] = rng.uniform(current.min(axis=0), current.max(axis=0), size=(len(bad), 2))
    config = VOConfig(init_min_inlier_share=0.5, init_min_median_deg=0.0)
    initialiser = Initialiser(config, focal=500.0)
    initialiser.restart(0, FrameData.build(reference, 500.0 * reference, DESCRIPTORS))
    initialiser.add(1, FrameData.build(current, 500.0 * current, DESCRIPTORS))
    return initialiser, [np.eye(4), np.eye(4)]


def test_a_two_view_model_explaining_too_few_tracks_is_refused():
    initialiser, poses = _two_views(consistent=0.8)
    result = initialiser.try_initialise(1, poses, None)
    assert result is not None and result.inliers >= 0.5 * N
    initialiser, poses = _two_views(consistent=0.35)  # a fit to this explains at most ~40 % of the tracks
    assert initialiser.try_initialise(1, poses, None) is None
    initialiser.config.init_min_inlier_share = 0.0  # the gate off: the same tracks make a map
    assert initialiser.try_initialise(1, poses, None) is not None


def _views_with_dying_chains(translation: tuple[float, float, float], turn_deg: float, survivors: int = 60):
    """Reference, a frame halfway where only ``survivors`` chains hold (the rest resume from the reference),
    and the current view of a rigid scene after ``translation`` and a turn; the initialiser holding them and
    the tracks' median motion in pixels."""
    rng = np.random.default_rng(5)
    world = np.column_stack([rng.uniform(-3, 3, N), rng.uniform(-2, 2, N), rng.uniform(4, 8, N)])
    angle = np.radians(turn_deg)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    views = [world, (world + world @ rotation.T + translation) / 2, world @ rotation.T + translation]
    points = [view[:, :2] / view[:, 2:] for view in views]
    broken = DESCRIPTORS.copy()
    fresh = rng.normal(size=(N - survivors, 64))
    broken[survivors:] = fresh / np.linalg.norm(fresh, axis=1, keepdims=True)
    initialiser = Initialiser(VOConfig(), focal=500.0)
    initialiser.restart(0, FrameData.build(points[0], 500.0 * points[0], DESCRIPTORS))
    initialiser.add(1, FrameData.build(points[1], 500.0 * points[1], broken))
    initialiser.add(2, FrameData.build(points[2], 500.0 * points[2], DESCRIPTORS))
    motion = float(np.median(np.linalg.norm(points[2] - points[0], axis=1)) * 500.0)
    return initialiser, motion


def test_dying_chains_do_not_waive_the_ray_angle_gate():
    initialiser, motion = _views_with_dying_chains((0.15, 0.0, 0.0), 0.0)
    tracks = initialiser._previous[1]
    assert np.count_nonzero((tracks.first_frame == 0) & ~tracks.resumed) == 60  # dying: under 3 x min_matches
    assert np.count_nonzero(tracks.first_frame == 0) == N  # the broken chains resumed from the reference
    # Between a third of the parallax gate and the gate (dying chains try from a third), ray angles of 1-2 deg:
    # the angle gate, once waived for dying chains, refuses the map.
    assert VOConfig().init_min_parallax_px / 3 < motion < VOConfig().init_min_parallax_px
    assert initialiser.try_initialise(2, [np.eye(4)] * 3, None) is None
    # A real baseline passes both gates with the same dying chains.
    initialiser, motion = _views_with_dying_chains((0.6, 0.05, 0.1), 1.0)
    assert motion > VOConfig().init_min_parallax_px
    result = initialiser.try_initialise(2, [np.eye(4)] * 3, None)
    assert result is not None and np.median(result.angles) >= VOConfig().init_min_median_deg



def test_a_map_built_again_after_a_loss_takes_a_smaller_ray_angle_than_the_first():
    """The dark take-off lost its map in a turn: 50-96 essential inliers at 1.1-1.9 deg median ray angle for 20
    frames. A re-initialisation (its scale from the speed before, not from the baseline) accepts such views; the
    first map still needs init_min_median_deg, as its depths set the run's scale."""
    initialiser, _ = _views_with_dying_chains((0.15, 0.0, 0.0), 0.0)
    assert initialiser.try_initialise(2, [np.eye(4)] * 3, None) is None  # a first map: refused
    initialiser, _ = _views_with_dying_chains((0.15, 0.0, 0.0), 0.0)
    result = initialiser.try_initialise(2, [np.eye(4)] * 3, 0.05)  # after a loss, at 0.05 units a frame
    assert result is not None
    median = float(np.median(result.angles))
    assert VOConfig().reinit_min_median_deg <= median < VOConfig().init_min_median_deg
    assert abs(result.speed - 0.05) < 1e-12  # the scale is the speed's
    initialiser, _ = _views_with_dying_chains((0.15, 0.0, 0.0), 0.0)
    initialiser.config = VOConfig(reinit_min_median_deg=2.0)
    assert initialiser.try_initialise(2, [np.eye(4)] * 3, 0.05) is None  # the old gate refused it


def _near_and_far(near: int, far: int, survivors: int | None = None, turn_deg: float = 3.0) -> Initialiser:
    """Reference, a frame halfway and the current view (a 0.5-unit step and a ``turn_deg`` turn) of ``near`` points
    4-8 units away and ``far`` points 500-1000 away (too little ray angle for a landmark); with ``survivors``
    only that many chains hold through the middle frame (dying tracks, the rest resumed from the reference)."""
    rng = np.random.default_rng(3)
    count = near + far
    depth = np.r_[rng.uniform(4, 8, near), rng.uniform(500, 1000, far)]
    world = np.column_stack([rng.uniform(-0.6, 0.6, count) * depth, rng.uniform(-0.4, 0.4, count) * depth, depth])
    angle = np.radians(turn_deg)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    views = [world, (world + world @ rotation.T + (0.5, 0.05, 0.1)) / 2, world @ rotation.T + (0.5, 0.05, 0.1)]
    points = [view[:, :2] / view[:, 2:] for view in views]
    middle = DESCRIPTORS[:count].copy()
    if survivors is not None:
        fresh = rng.normal(size=(count - survivors, 64))
        middle[survivors:] = fresh / np.linalg.norm(fresh, axis=1, keepdims=True)
    initialiser = Initialiser(VOConfig(init_wanted_landmarks=100), focal=500.0)
    initialiser.restart(0, FrameData.build(points[0], 500.0 * points[0], DESCRIPTORS[:count]))
    initialiser.add(1, FrameData.build(points[1], 500.0 * points[1], middle))
    initialiser.add(2, FrameData.build(points[2], 500.0 * points[2], DESCRIPTORS[:count]))
    return initialiser


def test_healthy_tracks_wait_for_the_wanted_landmarks_and_dying_ones_do_not():
    poses = [np.eye(4)] * 3
    # 120 unbroken tracks (not dying: >= 3 x min_matches) but only 80 landmarks: wait for the wanted 100 ...
    assert _near_and_far(80, 40).try_initialise(2, poses, None) is None
    # ... which the same views give without the gate (init_wanted_landmarks no higher than the minimum) ...
    initialiser = _near_and_far(80, 40)
    initialiser.config.init_wanted_landmarks = initialiser.config.init_min_landmarks
    result = initialiser.try_initialise(2, poses, None)
    assert result is not None and 40 <= len(result.world) < 100
    # ... and with dying tracks (60 unbroken chains) the minimum is enough.
    result = _near_and_far(80, 40, survivors=60).try_initialise(2, poses, None)
    assert result is not None and 40 <= len(result.world) < 100
    # Healthy tracks with 120 landmarks: a map at once.
    result = _near_and_far(120, 20).try_initialise(2, poses, None)
    assert result is not None and len(result.world) >= 100


def test_a_re_initialisation_measures_again_from_a_frame_turned_far_from_its_reference():
    """KITTI 07 in the dark lost its first map while turning: 10-37 deg from the frame of the loss, the tracks
    kept matching but too few points triangulated, for 20 frames, where a fresh reference gave a map at once.
    Views 30 deg apart with 20 of 80 points well triangulated (40 wanted): a re-initialisation restarts from this
    frame; a first map, a 3 deg turn, or the rule off keep the reference."""
    poses = [np.eye(4)] * 3
    initialiser = _near_and_far(20, 60, turn_deg=30.0)
    assert initialiser.try_initialise(2, poses, 0.05) is None and initialiser.reference == 2
    initialiser = _near_and_far(20, 60, turn_deg=30.0)
    assert initialiser.try_initialise(2, poses, None) is None and initialiser.reference == 0
    initialiser = _near_and_far(20, 60, turn_deg=3.0)
    assert initialiser.try_initialise(2, poses, 0.05) is None and initialiser.reference == 0
    initialiser = _near_and_far(20, 60, turn_deg=30.0)
    initialiser.config = VOConfig(reinit_max_turn_deg=0.0)
    assert initialiser.try_initialise(2, poses, 0.05) is None and initialiser.reference == 0
