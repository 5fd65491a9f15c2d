"""The first map's probation: the map-free rotation fit, the verdict, and MonoVO discarding a map that fails it."""
from __future__ import annotations

import numpy as np
import pytest

from test_vo_odometry import CAMERA, SyntheticExtractor, ate, run, straight_then_turn
from vo_runtime import VOConfig, VORuntimeError
from vo_runtime.odometry import INITIALISING, TRACKING
from vo_runtime.probation import MapProbation, rotation_angle_deg
from vo_runtime.rotation_fit import bearings, fit_rotation_ransac


def rotation_about(axis: np.ndarray, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def test_rotation_fit_recovers_a_turn_through_noise_and_outliers():
    rng = np.random.default_rng(3)
    truth = rotation_about([0.2, 1.0, -0.1], 4.0)
    pts_a = rng.uniform(-0.6, 0.6, (400, 2))
    rays_b = bearings(pts_a) @ truth.T
    pts_b = rays_b[:, :2] / rays_b[:, 2:] + rng.normal(scale=0.5 / 500, size=(400, 2))  # 0.5 px at f = 500
    wrong = rng.choice(400, 120, replace=False)  # 30 % mismatches
    pts_b[wrong] = rng.uniform(-0.6, 0.6, (120, 2))
    fitted, residuals = fit_rotation_ransac(pts_a, pts_b, 2.0 / 500)
    assert rotation_angle_deg(fitted.T @ truth) < 0.05
    inliers = np.setdiff1d(np.arange(400), wrong)
    assert np.median(residuals[inliers]) * 500 < 1.0 and np.median(residuals[wrong]) * 500 > 20
    assert np.array_equal(fit_rotation_ransac(pts_a, pts_b, 2.0 / 500)[0], fitted)  # seeded: one answer


def test_the_verdict_needs_its_frames_and_a_median_over_the_gate():
    probation = MapProbation(frames=4, max_deg=0.8, max_discards=1, max_distance=0.9, ratio=0.9)
    assert not probation.judge(5.0)  # not begun: no verdict
    probation.begin()
    assert [probation.judge(v) for v in (0.1, None, 0.3, 2.0)] == [False] * 4  # None does not count
    assert probation.judge(0.2) is False and not probation.active  # median of 0.1, 0.3, 2.0, 0.2: 0.25
    probation.begin()
    assert [probation.judge(v) for v in (1.0, 0.9, 1.2)] == [False] * 3
    assert probation.judge(0.1) is True and probation.discards == 1
    probation.begin()
    assert not probation.active  # max_discards spent: the next map is kept whatever it shows


def test_a_healthy_first_map_passes_its_probation():
    poses = straight_then_turn(60)
    vo = run(SyntheticExtractor(poses, noise_px=0.3), 60)
    assert not any(r.problem for r in vo.results)
    assert vo._probation.discards == 0 and vo._probation.values  # it was judged, and passed
    assert max(vo._probation.values) < 0.3


def test_a_map_that_fails_its_probation_is_discarded_and_built_again():
    """A gate no map can pass: the first map is dropped after its probation frames, its frames go back to
    initialising at the reference pose, and the next map (probation spent) tracks the rest correctly."""
    poses = straight_then_turn(70)
    config = VOConfig(probation_frames=5, probation_max_deg=1e-9, probation_max_discards=1)
    vo = run(SyntheticExtractor(poses), 70, config)
    discarded = [r.index for r in vo.results if r.problem and r.problem.startswith("map discarded")]
    assert len(discarded) == 1
    at = discarded[0]
    assert vo.results[at].map_dropped and sum(r.map_dropped for r in vo.results) == 1
    statuses = [r.status for r in vo.results]
    assert all(s == INITIALISING for s in statuses[: at + 1])
    assert all(r.keyframe is False for r in vo.results[: at + 1])
    np.testing.assert_allclose([r.pose for r in vo.results[: at + 1]], [np.eye(4)] * (at + 1), atol=1e-12)
    again = next(i for i, s in enumerate(statuses) if s == TRACKING)
    assert again > at and statuses[-1] == TRACKING
    rmse, _ = ate([vo.results[i].pose for i in range(again, 70)], poses[again:])
    assert rmse < 1e-3 * 0.3 * 70


def test_probation_settings_are_checked():
    with pytest.raises(VORuntimeError):
        VOConfig(probation_frames=-1)
    with pytest.raises(VORuntimeError):
        VOConfig(probation_max_deg=0.0)
