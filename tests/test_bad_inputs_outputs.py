"""The bad-input matrix for output folders (issue 29, D1-D4 and D20-D22): what ``--force`` may replace comes from
the listing a command wrote, one writer per output at a time, a file that appears at ``-o`` mid-run is kept, a
killed run's staging folders are cleared by the next run, and no output goes inside an input artefact."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest

import toolkit.cli
import vo_runtime.cli
from bad_inputs_support import PAIRS, THESIS, Space, assert_refused, snapshot
from vo_runtime.outputs import OutputKind, claim_output

Build = Callable[[Space], list]


def vo(*argv) -> int:
    return vo_runtime.cli.main([str(arg) for arg in argv])


def sequence(space: Space) -> Path:
    """The case's KITTI copy, made on first use (an earlier run and the case read the same one)."""
    return space.root / "seq" if (space.root / "seq").is_dir() else space.sequence()


def orb(space: Space, *extra) -> list:
    return ["vo", "--features", "orb", "--images", sequence(space), "--no-progress", *extra]


def earlier_vo_run(space: Space) -> Path:
    """A VO run this command wrote (its listing records each file)."""
    run = space.root / "run"
    assert vo("--features", "orb", "--images", sequence(space), "--no-progress", "-o", run) == 0
    return run


def run_with_user_folder(space: Space, name: str) -> Path:
    """D3: an earlier VO run where the user made a folder named like one of the run's files."""
    run = earlier_vo_run(space)
    if (run / name).exists():
        (run / name).unlink()
    (run / name).mkdir()
    (run / name / "mine.txt").write_bytes(THESIS)
    return run


def artefact_with_user_readme_folder(space: Space) -> Path:
    copy = space.artefact_copy()
    (copy / "README.md").unlink()
    (copy / "README.md").mkdir()
    (copy / "README.md" / "notes.txt").write_bytes(THESIS)
    return copy


def run_with_edited_file(space: Space) -> Path:
    """An earlier VO run whose trajectory the user edited since: no longer what the command wrote."""
    run = earlier_vo_run(space)
    (run / "trajectory_tum.txt").write_bytes(THESIS)
    return run


def user_training_folder(space: Space) -> Path:
    """D2: a folder of the user's own with files named like a run's (no config.json)."""
    for name in ("log.csv", "loss.png", "best.safetensors"):
        space.file(f"mine/{name}", THESIS)
    return space.root / "mine"


def train(space: Space, *extra) -> list:
    return ["train", "--images", PAIRS / "low", "--labels", space.root / "labels", *extra]


CASES: list[tuple[str, str, Build]] = [
    # D2: train --out into a non-empty folder that is no run
    ("train-into-user-folder", "holds no training run", lambda s: train(s, "--out", user_training_folder(s))),
    ("train-into-thesis", "holds no training run", lambda s: train(s, "--out", s.thesis())),
    # D3: a user folder named like an output file makes the whole folder the user's
    ("vo-force-user-folder-named-trajectory.png", "trajectory.png/",
     lambda s: orb(s, "-o", run_with_user_folder(s, "trajectory.png"), "--force")),
    ("vo-force-user-folder-named-summary.json", "summary.json/",
     lambda s: orb(s, "-o", run_with_user_folder(s, "summary.json"), "--force")),
    ("vo-force-edited-trajectory", "trajectory_tum.txt", lambda s: orb(s, "-o", run_with_edited_file(s), "--force")),
    ("export-force-user-folder-named-README.md", "README.md/",
     lambda s: ["export", "--target", "x86-cpu", "--checkpoint", s.assets.checkpoint, "--input-size", "64x64",
                "-o", artefact_with_user_readme_folder(s), "--force"]),
    # D22: no output inside the input artefact
    ("quantise-output-inside-artefact", "is inside the input",
     lambda s: ["quantise", "--artefact", s.artefact_copy(), "--mode", "int8", "-o", s.root / "art" / "int8"]),
    ("profile-output-inside-artefact", "is inside the input",
     lambda s: ["profile", "--model", s.artefact_copy(), "--no-compare", "-o", s.root / "art" / "profile"]),
    ("vo-output-inside-artefact", "is inside the input",
     lambda s: ["vo", "--artefact", s.artefact_copy(), "--images", s.sequence(), "-o", s.root / "art" / "run"]),
]


@pytest.mark.parametrize("name, fragment, build", CASES, ids=[case[0] for case in CASES])
def test_output_row_is_one_error_line_and_changes_nothing(name, fragment, build, bad_input_assets, tmp_path, capsys):
    argv = build(Space(tmp_path, bad_input_assets))
    assert_refused(toolkit.cli.main, argv, capsys, fragment, tmp_path, bad_input_assets.root)


HOLD_LOCK = """
import sys, time
from vo_runtime.outputs import locked_output
with locked_output(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def test_a_second_writer_to_the_same_output_is_refused(tmp_path, capsys):
    """D4: while one run holds -o, another is refused in one line; once the holder dies (even by kill -9) the
    output is free again."""
    space = Space(tmp_path, None)
    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(out)], stdout=subprocess.PIPE, text=True,
                              cwd=Path(__file__).resolve().parents[1])
    try:
        assert holder.stdout.readline().strip() == "held"
        line = assert_refused(toolkit.cli.main, orb(space, "-o", out), capsys, "is being written by another run",
                              tmp_path)
        assert str(holder.pid) in line
    finally:
        holder.kill()
        holder.wait()
    assert vo("--features", "orb", "--images", sequence(space), "--no-progress", "-o", out) == 0
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # no lock or staging left


def test_a_file_created_at_the_output_mid_run_is_kept(tmp_path, capsys, monkeypatch):
    """D1: the final swap re-checks the output: what the user put there while the run went on stays."""
    space = Space(tmp_path, None)
    out = tmp_path / "run"
    original = vo_runtime.cli.write_trajectory

    def user_writes_meanwhile(*args, **kwargs):
        if not out.exists():
            out.write_bytes(THESIS)
        return original(*args, **kwargs)

    monkeypatch.setattr(vo_runtime.cli, "write_trajectory", user_writes_meanwhile)
    capsys.readouterr()
    assert vo("--features", "orb", "--images", space.sequence(), "--no-progress", "-o", out) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.splitlines()) == 1 and "changed while this command ran" in err
    assert out.read_bytes() == THESIS
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_file_added_to_a_replaced_output_mid_run_is_kept(bad_input_assets, tmp_path, capsys, monkeypatch):
    """D1 with --force: the earlier artefact is replaced only if it is still exactly what was checked."""
    import export.artefact as artefact_module

    out = Space(tmp_path, bad_input_assets).artefact_copy()
    original = artefact_module.artefact_readme

    def user_writes_meanwhile(*args, **kwargs):
        (out / "thesis.txt").write_bytes(THESIS)
        return original(*args, **kwargs)

    monkeypatch.setattr(artefact_module, "artefact_readme", user_writes_meanwhile)
    before = snapshot(out)
    code = toolkit.cli.main(["export", "--target", "x86-cpu", "--checkpoint", str(bad_input_assets.checkpoint),
                             "--input-size", "64x64", "-o", str(out), "--force"])
    err = capsys.readouterr().err
    assert code == 2 and "changed while this command ran" in err.splitlines()[-1]
    assert (out / "thesis.txt").read_bytes() == THESIS
    assert {k: v for k, v in snapshot(out).items() if not k.endswith("thesis.txt")} == before


KILLED_WHILE_WRITING = """
import os, signal, sys
from vo_runtime.outputs import OutputKind, claim_output
with claim_output(sys.argv[1], OutputKind("test", "a test output"), force=True) as claim:
    with claim.writing() as staging:
        (staging / "big.bin").write_bytes(b"x" * 100000)
        os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_run_killed_while_writing_leaves_nothing_the_next_run_keeps(tmp_path):
    """D21: kill -9 during the final write leaves a hidden staging folder; the next run at -o removes it."""
    out = tmp_path / "out"
    killed = subprocess.run([sys.executable, "-c", KILLED_WHILE_WRITING, str(out)],
                            cwd=Path(__file__).resolve().parents[1])
    assert killed.returncode == -9
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.tmp-")]
    kind = OutputKind("test", "a test output")
    with claim_output(out, kind, force=True) as claim:
        with claim.writing() as staging:
            (staging / "result.txt").write_text("done")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_an_output_moved_aside_by_a_killed_swap_is_put_back(tmp_path):
    """A run killed between moving the earlier output aside and renaming the new one in: the next run finds
    the earlier output back in place (and, without --force, leaves it there)."""
    kind = OutputKind("test", "a test output")
    out = tmp_path / "out"
    with claim_output(out, kind, force=False) as claim:
        with claim.writing() as staging:
            (staging / "result.txt").write_text("first")
    aside = tmp_path / ".out.old-killed"
    aside.mkdir()
    os.rename(out, aside / "out")
    with pytest.raises(Exception, match="pass --force"):
        with claim_output(out, kind, force=False):
            pass
    assert (out / "result.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_training_stopped_before_its_first_checkpoint_resumes(tmp_path, capsys, monkeypatch):
    """D20: killed before the first checkpoint, the run folder is refused by a fresh run (naming --resume), and
    --resume starts it again from step 0 with its own config; D11: a batch beyond the machine's memory is refused."""
    import toolkit.training.trainer as trainer

    labels = tmp_path / "labels"
    assert toolkit.cli.main(["label", "--teacher", "shi-tomasi", "--images", str(PAIRS / "low"), "--size", "64x96",
                             "--num-homographies", "1", "--out", str(labels)]) == 0
    config = tmp_path / "small.json"
    config.write_text(json.dumps({"recipe": "paper", "device": "cpu", "steps": 2, "batch": 2, "log_every": 1,
                                  "model": {"widths": [8, 16, 32, 32], "blocks": [0, 1, 1, 1], "head_channels": 32,
                                            "descriptor_dim": 64}}))
    run = tmp_path / "run"
    base = ["train", "--images", str(PAIRS / "low"), "--labels", str(labels), "--out", str(run), "--threads", "1"]
    assert_refused(toolkit.cli.main, base + ["--config", str(config), "--batch", "100000000"], capsys,
                   "more than this machine's", tmp_path)
    assert not run.exists()

    def killed(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer, "save_checkpoint", killed)
    assert toolkit.cli.main(base + ["--config", str(config)]) == 130
    monkeypatch.undo()
    assert (run / "config.json").is_file() and not (run / "train_state.pt").exists()
    assert_refused(toolkit.cli.main, base + ["--config", str(config)], capsys, "--resume starts it again", tmp_path)
    assert toolkit.cli.main(base + ["--resume"]) == 0
    assert (run / "train_state.pt").is_file() and (run / "last.safetensors").is_file()
