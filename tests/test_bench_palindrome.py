"""bench/palindrome_sequence.py on a tiny EuRoC folder the test writes: the frames forward then backward, each
with the ground truth of the frame it shows, read back by the VO's own reader; bad input is one error line."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from tests.test_vo_euroc import write_mav0
from vo_runtime.datasets import open_sequence
from vo_runtime.euroc import camera_groundtruth

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "palindrome_sequence.py"


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=ROOT)


def test_frames_run_there_and_back_with_their_own_ground_truth(tmp_path):
    source = open_sequence(write_mav0(tmp_path / "seq", frames=5))
    done = _run(tmp_path / "seq", tmp_path / "out" / "back")
    assert done.returncode == 0, done.stderr
    played = open_sequence(tmp_path / "out" / "back")
    order = [0, 1, 2, 3, 4, 3, 2, 1, 0]
    assert len(played) == len(order)
    assert np.all(np.diff(played.timestamps) > 0)
    assert [Path(f).resolve() for f in played.frames] == [Path(source.frames[i]).resolve() for i in order]
    _, truth = camera_groundtruth(source.groundtruth, source.body_from_camera, source.timestamps)
    _, replayed = camera_groundtruth(played.groundtruth, played.body_from_camera, played.timestamps)
    for pose, i in zip(replayed, order):
        np.testing.assert_allclose(pose, truth[i], atol=1e-9)
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["back"]  # nothing else left beside it


def test_laps_fly_there_and_back_again_without_repeating_the_turning_frames(tmp_path):
    source = open_sequence(write_mav0(tmp_path / "seq", frames=3))
    done = _run(tmp_path / "seq", tmp_path / "laps", "--laps", 3)
    assert done.returncode == 0, done.stderr
    played = open_sequence(tmp_path / "laps")
    order = [0, 1, 2, 1] * 3 + [0]
    assert [Path(f).resolve() for f in played.frames] == [Path(source.frames[i]).resolve() for i in order]
    assert np.all(np.diff(played.timestamps) > 0)
    refused = _run(tmp_path / "seq", tmp_path / "none", "--laps", 0)
    assert refused.returncode == 2 and refused.stderr.startswith("error:") and len(refused.stderr.splitlines()) == 1
    assert not (tmp_path / "none").exists()


def test_an_existing_target_or_a_folder_without_mav0_is_one_error_line(tmp_path):
    write_mav0(tmp_path / "seq", frames=3)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "keep.txt").write_text("the user's")
    for source, target in ((tmp_path / "seq", tmp_path / "mine"), (tmp_path, tmp_path / "new")):
        done = _run(source, target)
        assert done.returncode == 2 and done.stderr.startswith("error:") and len(done.stderr.splitlines()) == 1
    assert (tmp_path / "mine" / "keep.txt").read_text() == "the user's"
    assert not (tmp_path / "new").exists()
