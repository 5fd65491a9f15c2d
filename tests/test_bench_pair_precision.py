"""bench/pair_precision.py: matches' distances to the true epipolar line, on a geometry the test builds and on
the drone clip."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.pair_precision import epipolar_distances  # noqa: E402
from vo_runtime.camera import Camera  # noqa: E402
from vo_runtime.features import Features  # noqa: E402


def test_a_match_off_its_epipolar_line_is_measured_in_pixels():
    camera = Camera(fx=400.0, fy=400.0, cx=320.0, cy=240.0)
    rng = np.random.default_rng(0)
    world = np.c_[rng.uniform(-2, 2, 40), rng.uniform(-1, 1, 40), rng.uniform(4, 8, 40)]
    relative = np.eye(4)
    relative[0, 3] = -0.3  # camera b 0.3 to the right of a: x_b = x_a + t
    pixels_a = world[:, :2] / world[:, 2:] * 400.0 + [320.0, 240.0]
    moved = world + relative[:3, 3]
    pixels_b = moved[:, :2] / moved[:, 2:] * 400.0 + [320.0, 240.0]
    pixels_b[5, 1] += 2.0  # a horizontal baseline: epipolar lines are rows, so 2 px down is 2 px off
    descriptors = rng.normal(size=(40, 16)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    scores = np.ones(40, np.float32)
    pairs, distances = epipolar_distances(camera, Features(pixels_a, scores, descriptors),
                                          Features(pixels_b, scores, descriptors), relative)
    np.testing.assert_array_equal(pairs, np.c_[np.arange(40), np.arange(40)])
    assert abs(distances[5] - 2.0) < 1e-6 and np.all(np.delete(distances, 5) < 1e-6)


def test_the_drone_clips_learned_matches_mostly_lie_on_their_lines_and_bad_input_is_one_line(shared_data):
    command = [sys.executable, str(ROOT / "bench/pair_precision.py"), "--sequence",
               str(shared_data / "euroc_mh05_f000000-000199"), "--first", "100", "--every", "40", "--light", "normal"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    row = next(line.split() for line in done.stdout.splitlines() if line.startswith("normal"))
    matches, good, share = float(row[2]), float(row[3]), float(row[4])
    assert matches > 200 and 0.7 < share <= 1.0 and abs(good / matches - share) < 0.01
    bad = subprocess.run(command[:-1] + ["dusk"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.startswith("error:") and "Traceback" not in bad.stderr
