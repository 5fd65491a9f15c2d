"""bench/eval_vo.py: bad input is one `error:` line, exit 2, nothing written; noise draws are runs of their own."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args, says", [
    (["--sequences", "kitti_odom06_f000000-000050,no_such_sequence"], "error: no_such_sequence"),
    (["--sequences", "kitti_odom06_f000000-000050", "--set", "init_wanted_landmarks=1.5"],
     "error: --set init_wanted_landmarks=1.5"),
    (["--sequences", "tum_fr2_desk_snippet", "--seeds", "0"], "error: --seeds"),
    (["--sequences", "tum_fr2_desk_snippet", "--seeds", "two"], "error: --seeds"),
], ids=["unknown sequence", "mistyped --set", "no noise draws", "not a number of draws"])
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
