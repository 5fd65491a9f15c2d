"""bench/vo_shared_frames.py: two runs scored on the frames both scored, on trajectories whose answer is known."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.vo_shared_frames import ratio_interval, shared_frame_ates, shared_frames_summary  # noqa: E402
from vo_runtime.config import VOResult  # noqa: E402
from vo_runtime.odometry import INITIALISING  # noqa: E402

pytest.importorskip("evo")
from evo.core.trajectory import PoseTrajectory3D  # noqa: E402

FRAMES = 60


def _truth_pose(i: int) -> np.ndarray:
    """Camera-to-world: a 2 m circle in x-y, 1 cm of climb a frame (a drone's loop)."""
    angle = 2 * np.pi * i / FRAMES
    pose = np.eye(4)
    pose[:3, 3] = [2 * np.cos(angle), 2 * np.sin(angle), 0.01 * i]
    return pose


STAMPS = [0.05 * i for i in range(FRAMES)]
TRUTH = PoseTrajectory3D(poses_se3=[_truth_pose(i) for i in range(FRAMES)], timestamps=np.array(STAMPS))


def _run(first: int, offsets: dict[int, np.ndarray] | None = None, scale: float = 0.3) -> list[VOResult]:
    """A run initialised at ``first``: the truth in its own scale (and frame), plus ``offsets`` on some frames."""
    results = []
    for i in range(FRAMES):
        pose = _truth_pose(i)
        pose[:3, 3] = scale * pose[:3, 3] + [5.0, -1.0, 0.5]  # a Sim(3) away from the truth: aligned back exactly
        if offsets and i in offsets:
            pose[:3, 3] += scale * offsets[i]
        status = INITIALISING if i < first else "tracking"
        results.append(VOResult(i, STAMPS[i], pose, status, 0, 0, 0, 0, 0.0, 0.0))
    return results


def test_each_run_is_scored_on_the_frames_both_scored_only():
    # a starts at frame 5 and is 0.5 m off on frames 10-19 (before b starts); b starts at 25 and is exact. On
    # their own frames a's ATE is large; on the shared frames 25-59 both are exactly the truth after Sim(3).
    a = _run(5, {i: np.array([0.5, 0.0, 0.0]) for i in range(10, 20)})
    b = _run(25)
    ate_a, ate_b, frames = shared_frame_ates(a, b, TRUTH, "tum", STAMPS)
    assert frames == FRAMES - 25
    assert ate_a < 1e-6 and ate_b < 1e-6
    # and an error inside the shared frames is counted: 10 cm on one of the 35 frames, against b's exact run
    c = _run(5, {40: np.array([0.1, 0.0, 0.0])})
    ate_c, ate_b, _ = shared_frame_ates(c, b, TRUTH, "tum", STAMPS)
    assert 0.01 < ate_c < 0.1 / np.sqrt(35) * 1.01 and ate_b < 1e-6


def test_too_few_shared_frames_are_not_compared():
    assert shared_frame_ates(_run(0), _run(FRAMES - 8), TRUTH, "tum", STAMPS) is None  # 8 frames shared
    assert shared_frame_ates(_run(0), _run(FRAMES - 10), TRUTH, "tum", STAMPS)[2] == 10


def test_the_summary_pairs_each_run_with_the_peer_of_the_same_start():
    def row(features, start, results, ate):
        return {"name": "loop", "features": features, "light": "low", "start": start, "_results": results,
                "ate": ate, "keypoints": None}
    noisy = {i: np.array([0.0, 0.05 * (-1) ** i, 0.0]) for i in range(FRAMES)}
    rows = [row("learned", 0, _run(2, noisy), 0.05), row("orb", 0, _run(30), 0.001),
            row("learned", 10, _run(2), 0.001), row("orb", 10, _run(FRAMES - 3), 0.002),  # 3 frames shared
            row("learned", 20, _run(2), 0.001)]  # no peer run of this start
    text = shared_frames_summary(rows, lambda name, start: (TRUTH, "tum", STAMPS), short_names={"loop": "Loop"})
    line = next(l for l in text.splitlines() if l.startswith("| Loop"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[:4] == ["Loop", "learned", "low", "1 of 2"]
    assert int(cells[4]) == FRAMES - 30
    assert float(cells[5]) == pytest.approx(0.05, abs=0.005) and float(cells[6]) < 1e-4  # the noisy run against exact
    assert cells[9] == f"{2 * (FRAMES - 2)} / {(FRAMES - 30) + 3}"  # frames scored by each side, pairs of 2 starts
    assert shared_frames_summary([rows[0], rows[4]], lambda n, s: (TRUTH, "tum", STAMPS)) == ""


def test_the_ratio_interval_resamples_starts_not_noise_draws():
    # Every run half its peer's ATE: 0.5x, no spread.
    assert ratio_interval([(0, 0.01, 0.02), (10, 0.03, 0.06)]) == pytest.approx((0.5, 0.5, 0.5))
    # Three noise draws of start 0 at 0.5x, one run of start 10 at 2x: the ratio is over the four runs
    # (2 ** -0.5), but a resample draws starts, so a quarter of them hold start 0 alone (0.5x) and a quarter
    # start 10 alone (2x): the 95 % interval spans both, as three correlated draws are not three starts.
    ratio, low, high = ratio_interval([(0, 0.01, 0.02), (0, 0.02, 0.04), (0, 0.005, 0.01), (10, 0.02, 0.01)])
    assert ratio == pytest.approx(2 ** -0.5)
    assert (low, high) == pytest.approx((0.5, 2.0))
    # One start (TUM's snippet): its draws are the units, the only spread there is.
    ratio, low, high = ratio_interval([(0, 0.01, 0.02), (0, 0.02, 0.01)])
    assert ratio == pytest.approx(1.0) and (low, high) == pytest.approx((0.5, 2.0))
