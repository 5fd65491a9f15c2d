"""The keypoint budget: at most N keypoints a frame, spread over a grid of cells as ORB's grid spreads them."""
from __future__ import annotations

import numpy as np
import pytest

from vo_runtime import VORuntimeError
from vo_runtime.features import Features, KeypointBudget, spread_selection


def _clustered(n_dense: int = 50, n_sparse: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A dense cluster of strong keypoints in the top-left corner and a few weak ones in the bottom right."""
    rng = np.random.default_rng(0)
    keypoints = np.vstack([rng.uniform(0, 10, (n_dense, 2)), rng.uniform(90, 100, (n_sparse, 2))]).astype(np.float32)
    scores = np.linspace(1.0, 0.1, n_dense + n_sparse).astype(np.float32)  # descending: the cluster scores higher
    return keypoints, scores


def test_without_a_grid_the_best_scores_are_kept():
    keypoints, scores = _clustered()
    np.testing.assert_array_equal(spread_selection(keypoints, scores, 10, None, 100, 100), np.arange(10))
    np.testing.assert_array_equal(spread_selection(keypoints, scores, 100, (2, 2), 100, 100), np.arange(55))


def test_a_grid_takes_every_cells_best_before_any_cells_second():
    keypoints, scores = _clustered()
    keep = spread_selection(keypoints, scores, 10, (2, 2), 100, 100)
    # two occupied cells: five from each (round-robin by rank), in descending score
    np.testing.assert_array_equal(keep, [0, 1, 2, 3, 4, 50, 51, 52, 53, 54])
    assert np.all(np.diff(scores[keep]) <= 0)


def test_budget_wraps_any_extractor():
    keypoints, scores = _clustered()
    inner = lambda image: Features(keypoints, scores, np.eye(55, 8, dtype=np.float32))  # noqa: E731
    inner.width, inner.height = 320, 240
    budget = KeypointBudget(inner, 10, (2, 2))
    features = budget(np.zeros((100, 100), np.uint8))
    assert len(features) == 10 and features.descriptors.shape == (10, 8)
    assert budget.width == 320  # the wrapped extractor's attributes (detector_pixel reads them)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(VORuntimeError, match="budget"):
            KeypointBudget(inner, bad)
    with pytest.raises(VORuntimeError, match="grid"):
        KeypointBudget(inner, 10, (0, 3))
