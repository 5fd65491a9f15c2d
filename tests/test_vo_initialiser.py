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
