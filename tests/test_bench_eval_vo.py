"""bench/eval_vo.py on bad input: one `error:` line, exit 2, nothing written."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_an_unknown_sequence_is_one_error_line_and_writes_nothing(tmp_path, shared_data):
    output = tmp_path / "table"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_vo.py"), "--data", str(shared_data),
                          "--sequences", "kitti_odom06_f000000-000050,no_such_sequence", "-o", str(output)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "no_such_sequence" in lines[0]
    assert not output.exists()  # no run started, no folder made


def test_a_mistyped_set_is_one_error_line_before_any_run(tmp_path, shared_data):
    output = tmp_path / "table"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "eval_vo.py"), "--data", str(shared_data),
                          "--sequences", "kitti_odom06_f000000-000050", "--set", "init_wanted_landmarks=1.5",
                          "-o", str(output)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --set init_wanted_landmarks=1.5")
    assert not output.exists()
