"""bench/long_flight.py on a tiny EuRoC folder the test writes: a row every N frames, the map's bytes counted
exactly, and bad input as one error line."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.test_vo_euroc import write_mav0
from tests.test_vo_localmap import map_with_keyframes, pose_at, scene
from vo_runtime.localmap import LANDMARK_ARRAYS

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "long_flight.py"
sys.path.insert(0, str(ROOT / "bench"))

from long_flight import map_bytes  # noqa: E402


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=ROOT)


def test_map_bytes_count_every_array_and_drop_with_released_descriptors():
    world, desc = scene(50)
    local_map = map_with_keyframes(world, desc, [pose_at(0.0, (0, 0, 0)), pose_at(0.0, (0.5, 0, 0))])
    landmarks = sum(getattr(local_map, name).nbytes for name in LANDMARK_ARRAYS)
    keyframe = local_map.keyframes[0]
    each = keyframe.points.nbytes + keyframe.pixels.nbytes + keyframe.descriptors.nbytes + keyframe.landmark.nbytes
    assert map_bytes(local_map) == landmarks + 2 * each
    released = keyframe.descriptors.nbytes
    local_map.release_descriptors(0)
    assert released > 0 and map_bytes(local_map) == landmarks + 2 * each - released
    assert map_bytes(None) == 0  # before the first map


def test_a_row_every_n_frames_and_the_last(tmp_path):
    write_mav0(tmp_path / "seq", frames=5)
    done = _run("--sequence", tmp_path / "seq", "--features", "orb", "--every", 2)
    assert done.returncode == 0, done.stderr
    rows = [line.split("|")[1].strip() for line in done.stdout.splitlines() if line.startswith("| ")
            and line.split("|")[1].strip().isdigit()]
    assert rows == ["2", "4", "5"]


def test_bad_input_is_one_error_line(tmp_path):
    for args in (("--sequence", tmp_path / "missing"), ("--sequence", tmp_path, "--every", 0)):
        done = _run(*args)
        assert done.returncode == 2 and done.stderr.startswith("error:") and len(done.stderr.splitlines()) == 1
