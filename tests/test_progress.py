"""Progress without a terminal: a line at intervals with an ETA, so `toolkit prune ... > log 2>&1` is not silent."""
from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

from vo_runtime.progress import LineProgress, format_duration, progress_bar


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_lines_come_at_intervals_with_rate_and_eta() -> None:
    clock, out = FakeClock(), io.StringIO()
    bar = LineProgress(total=100, desc="train", unit="step", initial=20, file=out, interval=10.0, clock=clock)
    for _ in range(10):  # 10 steps in 5 s: no line yet
        clock.now += 0.5
        bar.update(1)
    assert out.getvalue() == ""
    for _ in range(10):
        clock.now += 0.5
        bar.update(1)
    # 20 steps in 10 s after starting at step 20 of 100: 2 step/s, 60 steps left = 30 s
    assert out.getvalue().splitlines() == ["train: 40/100 step (40.0%), 2 step/s, elapsed 10s, ETA 30s"]
    bar.set_postfix(loss="0.812")  # shown with the next line
    clock.now += 10.0
    bar.update(1)
    bar.close()
    lines = out.getvalue().splitlines()
    assert lines[1] == "train: 41/100 step (41.0%), 1.05 step/s, elapsed 20s, ETA 56s, loss=0.812"
    assert lines[2] == "train: 41 step done in 20s (1.05 step/s)"


def test_short_work_stays_silent_and_iteration_counts(capsys) -> None:
    bar = LineProgress(range(5), desc="eval", unit="pair", interval=60.0)
    assert list(bar) == [0, 1, 2, 3, 4] and bar.count == 5
    assert capsys.readouterr().err == ""
    assert list(progress_bar(range(3), desc="x", enabled=False)) == [0, 1, 2]  # stderr is captured: no terminal
    assert capsys.readouterr().err == ""


def test_durations_read_as_a_person_writes_them() -> None:
    assert [format_duration(s) for s in (7.2, 95, 3725, float("inf"))] == ["7s", "1m35s", "1h02m", "?"]


def test_prune_writes_progress_lines_to_a_log_while_it_works(tmp_path: Path) -> None:
    log = tmp_path / "log"
    env = {**os.environ, "EDGEFEAT_PROGRESS_SECONDS": "0", "OMP_NUM_THREADS": "1"}
    with open(log, "w") as handle:  # toolkit prune ... > log 2>&1
        result = subprocess.run([sys.executable, "-m", "toolkit", "prune", "--checkpoint", "default-relu", "--ratio", "0.3",
                                 "--steps", "3", "--no-eval", "-o", str(tmp_path / "p30.safetensors")],
                                stdout=handle, stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
    lines = log.read_text().splitlines()
    assert result.returncode == 0, lines[-5:]
    distil = [i for i, line in enumerate(lines) if line.startswith("distil: ")]
    assert lines[distil[0]] .startswith("distil: 1/3 step (33.3%), ") and "ETA" in lines[distil[0]]
    assert lines[distil[-1]].startswith("distil: 3 step done in ")
    # stdout reaches the log line by line too: the pruning line before the distillation, not at exit
    assert lines[0].startswith("pruned 30% of channels") and distil[0] > 0
    assert lines[-1].startswith(f"wrote {tmp_path / 'p30.safetensors'}")


def test_vo_reports_progress_in_a_log_and_says_where_it_wrote(shared_data, tmp_path, capsys, monkeypatch):
    from vo_runtime.cli import main as vo_main

    monkeypatch.setenv("EDGEFEAT_PROGRESS_SECONDS", "0")  # a line at every step (default: every 10 s)
    assert vo_main(["--features", "orb", "--images", str(shared_data / "tum_fr2_desk_snippet"), "--max-frames", "6",
                    "-o", str(tmp_path / "run")]) == 0
    captured = capsys.readouterr()
    assert any(line.startswith("vo: ") and "frame" in line for line in captured.err.splitlines())
    assert captured.out.splitlines()[-1].startswith(f"wrote {tmp_path / 'run'}: frames.json")
