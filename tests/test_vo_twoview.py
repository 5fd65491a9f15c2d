"""The two-view model's inliers: points far beyond 50 baselines still count (OpenCV's default dropped them)."""
from __future__ import annotations

import numpy as np

from vo_runtime.twoview import relative_pose_hypotheses


def test_far_points_stay_inliers_of_the_essential_matrix():
    """A slow drone in a hall: depths of 3-8 m over an 8 cm sideways baseline (40-100 baselines away)."""
    rng = np.random.default_rng(5)
    world = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(-2, 2, 300), rng.uniform(3, 8, 300)])
    angle = np.radians(4.0)
    rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = world @ rotation.T + (-0.08, 0.0, 0.01)
    a, b = world[:, :2] / world[:, 2:], moved[:, :2] / moved[:, 2:]
    b = b + rng.normal(0, 0.3 / 458, b.shape)  # 0.3 px of detection noise at a 458 px focal length
    hypotheses = relative_pose_hypotheses(a, b, 1.0 / 458)
    assert hypotheses and hypotheses[0].model == "essential"
    farther = np.linalg.norm(world, axis=1) > 50 * 0.08
    assert np.count_nonzero(farther) > 200
    assert np.count_nonzero(hypotheses[0].inliers & farther) > 0.8 * np.count_nonzero(farther)
    translation = hypotheses[0].translation / np.linalg.norm(hypotheses[0].translation)
    assert abs(translation[0]) > 0.9  # and the sideways motion is found
