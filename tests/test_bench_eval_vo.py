"""bench/eval_vo.py: bad input is one `error:` line, exit 2, nothing written; noise draws are runs of their own."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args, says", [
    (["--sequences", "kitti_odom06_f000000-000050,no_such_sequence"], "error: no_such_sequence"),
    (["--sequences", "kitti_odom06_f000000-000050", "--set", "init_wanted_landmarks=1.5"],
     "error: --set init_wanted_landmarks=1.5"),
    (["--sequences", "tum_fr2_desk_snippet", "--seeds", "0"], "error: --seeds"),
    (["--sequences", "tum_fr2_desk_snippet", "--seeds", "two"], "error: --seeds"),
    (["--sequences", "tum_fr2_desk_snippet", "--light", "normal,dusk"], "error: --light 'dusk'"),
    (["--sequences", "tum_fr2_desk_snippet", "--stride", "0"], "error: --stride"),
    (["--sequences", "tum_fr2_desk_snippet", "--features", "artefact,sift"], "error: --features 'sift'"),
], ids=["unknown sequence", "mistyped --set", "no noise draws", "not a number of draws", "unknown light", "no stride",
        "unknown features"])
def test_bad_input_is_one_error_line_before_any_run_and_writes_nothing(tmp_path, shared_data, args, says):
    output = tmp_path / "table"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_vo.py"), "--data", str(shared_data), *args,
                          "-o", str(output)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and says.removeprefix("error: ") in lines[0]
    assert not output.exists()  # no run started, no folder made


def test_each_noise_draw_is_a_run_of_its_own_against_orb_of_the_same_draw(tmp_path, shared_data):
    # TUM in the dark, two draws of the sensor noise each for the learned feature and ORB: four runs, the two
    # draws of one feature darken differently (different results), and the shared-frames table pairs by draw.
    output = tmp_path / "table"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_vo.py"), "--data", str(shared_data),
                          "--sequences", "tum_fr2_desk_snippet", "--light", "low", "--seeds", "2",
                          "--workers", "2", "-o", str(output)], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    rows = json.loads((output / "results.json").read_text())["rows"]
    assert sorted((r["features"], r["seed"]) for r in rows) == [
        ("default_artefact", 0), ("default_artefact", 1), ("orb", 0), ("orb", 1)]
    learned = [r for r in rows if r["features"] == "default_artefact"]
    assert learned[0]["ate"] != learned[1]["ate"] or learned[0]["tracked"] != learned[1]["tracked"]
    assert "| TUM fr2 desk | default_artefact | low | 2 of 2 |" in run.stdout
    assert len(list((output / "trajectories").glob("*_noise1.txt"))) == 2


def test_a_stride_runs_every_nth_frame_with_each_frames_own_stamp(tmp_path, shared_data):
    # KITTI 06 (51 frames) at stride 2 from frame 10: frames 10, 12, ..., 50, each scored at its own timestamp
    sys.path.insert(0, str(ROOT))
    from vo_runtime.datasets import open_sequence

    output = tmp_path / "table"
    name = "kitti_odom06_f000000-000050"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_vo.py"), "--data", str(shared_data),
                          "--sequences", name, "--features", "orb", "--light", "normal", "--starts", "10",
                          "--stride", "2", "-o", str(output)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    [row] = json.loads((output / "results.json").read_text())["rows"]
    assert row["stride"] == 2 and row["frames"] == 21 and row["sequence"].endswith("from 10 every 2")
    [trajectory] = (output / "trajectories").glob("*_every2.txt")
    stamps = np.loadtxt(trajectory, ndmin=2)[:, 0]
    every_second = np.asarray(open_sequence(shared_data / name).timestamps[10::2])
    assert len(stamps) >= 10 and np.all(np.isin(np.round(stamps, 6), np.round(every_second, 6)))


def test_grain_is_one_grey_level_of_seeded_noise_at_normal_lights_starts():
    sys.path.insert(0, str(ROOT))  # bench/ is a folder of scripts
    from bench.eval_vo import GRAIN_SIGMA, LIGHTS, STARTS, study_starts

    frame = np.full((240, 320), 128, np.uint8)
    frame[:, :4], frame[:, -4:] = 0, 255  # clipped at both ends, never wrapped round
    grainy = LIGHTS["grain"](frame, seed=7)
    assert grainy.dtype == np.uint8 and grainy.shape == frame.shape
    assert np.array_equal(grainy, LIGHTS["grain"](frame, seed=7))  # a draw is its seed's
    assert not np.array_equal(grainy, LIGHTS["grain"](frame, seed=8))
    middle = grainy[:, 4:-4].astype(np.float64) - 128
    # rounding to grey levels adds a uniform error of variance 1/12
    assert abs(middle.mean()) < 0.02 and abs(middle.std() - np.sqrt(GRAIN_SIGMA ** 2 + 1 / 12)) < 0.015
    assert grainy[:, :4].max() <= 4 and grainy[:, -4:].min() >= 251
    name = "kitti_odom07_f000000-000159"
    assert study_starts(name, "grain", 160) == study_starts(name, "normal", 160) == list(STARTS["normal"][name])


def test_a_learned_peer_runs_in_the_vo_with_unit_descriptors_in_score_order(shared_data):
    # XFeat (bench/vo_peers.py) on a drone frame: its own detector, unit-norm descriptors for the VO's matcher,
    # strongest first, and scores that weigh nothing in the pose fit (as ORB's).
    sys.path.insert(0, str(ROOT))
    from bench.vo_peers import PeerExtractor, is_peer
    from vo_runtime.datasets import open_sequence
    from vo_runtime.sequence import read_frames

    assert is_peer("xfeat") and is_peer("teacher:alike-n") and not is_peer("orb") and not is_peer("artefact")
    frame = next(read_frames(open_sequence(shared_data / "euroc_mh05_f000000-000199").frames[100:101]))
    features = PeerExtractor("xfeat", keypoints=300)(frame)
    assert 100 < len(features) <= 300 and features.descriptors.shape[1] == 64
    assert np.allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(features.scores) <= 0) and not features.scores_predict_error
    height, width = frame.shape[:2]
    assert features.keypoints[:, 0].max() < width and features.keypoints[:, 1].max() < height
