"""bench/compare_runs.py: two eval_vo runs paired by start and draw, ratio with an interval over starts."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "compare_runs.py"


def _row(start: int, seed: int, ate: float | None, features: str = "default_artefact", lost: int = 0,
         initialised_at: int = 5) -> dict:
    return {"name": "kitti_odom07_f000000-000159", "features": features, "light": "low", "start": start,
            "seed": seed, "ate": ate, "after_init": 100, "tracked": 100 - lost, "initialised_at": initialised_at}


def _write(path: Path, rows: list[dict]) -> Path:
    path.write_text(json.dumps({"overrides": {}, "rows": rows}))
    return path


def _compare(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=60)


def _assert_one_error_line(run: subprocess.CompletedProcess, says: str) -> None:
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0]
    assert run.stdout == ""


def _table_row(stdout: str) -> list[str]:
    line = next(line for line in stdout.splitlines() if line.startswith("| kitti_odom07"))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_a_uniform_change_is_its_ratio_with_no_spread_and_failures_are_counted_apart(tmp_path):
    base_ates = {0: 0.1, 25: 0.2, 50: 0.4}
    base = [_row(s, d, a * (1 + 0.1 * d)) for s, a in base_ates.items() for d in range(2)]
    new = [_row(s, d, 2 * a * (1 + 0.1 * d), lost=3) for s, a in base_ates.items() for d in range(2)]
    new.append(_row(75, 0, None, lost=40))  # a run without a trajectory ...
    base.append(_row(75, 0, 0.3))            # ... leaves the ratio, and is counted
    run = _compare(_write(tmp_path / "a.json", base), _write(tmp_path / "b.json", new))
    assert run.returncode == 0, run.stderr
    cells = _table_row(run.stdout)
    assert cells[2] == "7"  # runs paired
    expected_base = np.exp(np.mean(np.log([a * (1 + 0.1 * d) for a in base_ates.values() for d in range(2)])))
    assert float(cells[3]) == pytest.approx(expected_base, abs=1e-4)
    assert float(cells[4]) == pytest.approx(2 * expected_base, abs=1e-4)
    assert cells[5] == "2.00x [2.00, 2.00]"
    assert cells[6] == "0 / 1" and cells[7] == "0 / 58"


def test_the_interval_resamples_starts_and_spans_their_spread(tmp_path):
    ratios = {0: 0.5, 10: 0.8, 20: 1.0, 30: 1.25, 40: 2.0}
    base = [_row(s, 0, 0.2) for s in ratios]
    new = [_row(s, 0, 0.2 * r, features="other") for s, r in ratios.items()]
    run = _compare(_write(tmp_path / "a.json", base), _write(tmp_path / "b.json", new),
                   "--base-features", "default_artefact", "--new-features", "other")
    assert run.returncode == 0, run.stderr
    assert "other against default_artefact" in run.stdout
    ratio, interval = _table_row(run.stdout)[5].split("x ")
    low, high = (float(v) for v in interval.strip("[]").split(","))
    assert float(ratio) == pytest.approx(1.0, abs=0.005)  # symmetric in log
    assert 0.5 <= low < 0.9 and 1.1 < high <= 2.0


def test_split_delay_separates_runs_whose_base_started_later(tmp_path):
    # ORB-like base: a frame after the new run at start 0 and before it at 10 (ratio 0.5), 30 frames after it at 20
    # and 30 (ratio 2).
    late = {0: False, 10: False, 20: True, 30: True}
    base = [_row(s, 0, 0.1, features="orb", initialised_at=38 if is_late else 9 - 7 * (s == 10))
            for s, is_late in late.items()]
    new = [_row(s, 0, 0.2 if is_late else 0.05, initialised_at=8) for s, is_late in late.items()]
    args = (_write(tmp_path / "a.json", base), _write(tmp_path / "b.json", new), "--base-features", "orb",
            "--new-features", "default_artefact")
    whole = _compare(*args)
    assert whole.returncode == 0, whole.stderr
    assert _table_row(whole.stdout)[5].startswith("1.00x")  # 0.5 and 2 cancel in the geometric mean
    split = _compare(*args, "--split-delay", "5")
    assert split.returncode == 0, split.stderr
    rows = {cells[1]: cells for cells in ([c.strip() for c in line.strip("|").split("|")]
                                          for line in split.stdout.splitlines() if line.startswith("| kitti"))}
    together, later = "low, base at most 5 frames later", "low, base more than 5 frames later"
    assert set(rows) == {together, later}
    assert rows[together][2] == "2" and rows[together][5] == "0.50x [0.50, 0.50]"
    assert rows[later][2] == "2" and rows[later][5] == "2.00x [2.00, 2.00]"
    # 29 frames later is "at most 30": nothing is split off.
    assert {line.split("|")[2].strip() for line in _compare(*args, "--split-delay", "30").stdout.splitlines()
            if line.startswith("| kitti")} == {"low, base at most 30 frames later"}


@pytest.mark.parametrize("content, says", [
    (None, "cannot read"),
    ("{not json", "is not JSON"),
    (json.dumps({"rows": [{"name": "x"}]}), "is not a bench/eval_vo.py results.json"),
    (json.dumps({"rows": [_row(0, 0, 0.1, features="orb")]}), "no runs pair up"),
], ids=["missing", "not json", "not results", "nothing pairs"])
def test_bad_input_is_one_error_line_exit_2(tmp_path, content, says):
    base = _write(tmp_path / "a.json", [_row(0, 0, 0.1)])
    new = tmp_path / "b.json"
    if content is not None:
        new.write_text(content)
    _assert_one_error_line(_compare(base, new), says)


@pytest.mark.parametrize("delay, rows, says", [
    ("-1", [_row(0, 0, 0.1)], "--split-delay takes a number of frames >= 0"),
    ("5", [{k: v for k, v in _row(0, 0, 0.1).items() if k != "initialised_at"}], "needs each run's initialised_at"),
], ids=["negative", "no initialised_at"])
def test_bad_split_delay_is_one_error_line_exit_2(tmp_path, delay, rows, says):
    run = _compare(_write(tmp_path / "a.json", rows), _write(tmp_path / "b.json", [_row(0, 0, 0.2)]),
                   "--split-delay", delay)
    _assert_one_error_line(run, says)
