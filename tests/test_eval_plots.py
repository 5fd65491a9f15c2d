"""The eval report's match plot: a grid of pairs spread over the set, dark images shown stretched."""
from __future__ import annotations

import cv2
import numpy as np

from toolkit.evaluation.detection import Detection
from toolkit.evaluation.report import _shown, plot_matches
from toolkit.evaluation.runner import PairExample, example_indices


def _example(name: str, level: int) -> PairExample:
    rng = np.random.default_rng(level)
    image = (rng.random((120, 160)) * level).astype(np.uint8)
    points = rng.uniform(10, 110, (20, 2)).astype(np.float32)
    detection = Detection(points, np.ones(20, np.float32), np.eye(20, 8, dtype=np.float32))
    return PairExample(name, image, image.copy(), detection, detection, np.column_stack([np.arange(20)] * 2),
                       np.eye(3))


def test_pairs_are_spread_over_the_set():
    assert example_indices(100) == {0, 20, 40, 59, 79, 99}
    assert example_indices(3) == {0, 1, 2} and example_indices(0) == set()


def test_the_plot_has_a_row_per_pair_and_stretches_dark_images(tmp_path):
    dark, bright = _example("dark", 30), _example("bright", 255)
    assert _shown(dark.image_a).max() == 255 and _shown(bright.image_a) is bright.image_a
    plot_matches([dark], tmp_path / "one.png", "m")
    plot_matches([dark, bright, dark], tmp_path / "three.png", "m")
    one, three = cv2.imread(str(tmp_path / "one.png")), cv2.imread(str(tmp_path / "three.png"))
    assert three.shape[0] > 2.5 * one.shape[0] and three.shape[1] == one.shape[1]
