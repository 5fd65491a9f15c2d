"""The bad-input matrix for the toolkit's commands (issue 12): what a new user might type, one row each.

Every row must end in exit code 2 and exactly one ``error:`` line on stderr (no traceback, no library warning or
log line above it), and must leave every file it could touch, the user's own and the output location, byte for
byte as it was. The VO command lines and the runtime API have their own tables (test_bad_inputs_vo.py,
test_bad_inputs_api.py). Cases never rely on the shipped default model or artefact.
"""
from __future__ import annotations

import pickle
from typing import Callable

import pytest
import torch

from bad_inputs_support import PAIRS, Space, assert_refused
from toolkit.cli import main

torch.set_num_threads(1)

Build = Callable[[Space], list]


def export(space: Space, *extra) -> list:
    return ["export", "--target", "x86-cpu", "--checkpoint", space.assets.checkpoint, "--input-size", "64x64", *extra]


def prune(space: Space, *extra) -> list:
    return ["prune", "--checkpoint", space.assets.checkpoint, "--ratio", "0.5", "--steps", "0", "--size", "64x64",
            "--images", PAIRS, "--no-eval", *extra]


def quantise(space: Space, *extra) -> list:
    return ["quantise", "--artefact", space.assets.artefact, "--mode", "int8", *extra]


def label(space: Space, *extra) -> list:
    return ["label", "--teacher", "shi-tomasi", "--images", PAIRS / "low", "--num-homographies", "1", *extra]


def profile(space: Space, *extra) -> list:
    return ["profile", "--model", space.assets.checkpoint, "--input-size", "64x64", "--no-compare", *extra]


def evaluate(space: Space, *extra) -> list:
    return ["eval", "pairs", "--data", PAIRS, "--model", "orb", *extra]


def train(space: Space, *extra) -> list:
    return ["train", "--images", PAIRS / "low", "--labels", space.root / "labels", *extra]


def corrupt_among_good(space: Space) -> object:
    folder = space.images("par", 1, 96)
    space.corrupt_png("par/zz.png")
    return folder


def corrupt_pair(space: Space) -> object:
    """A registered-pairs folder whose first image is corrupt (OpenCV would log its own line for it)."""
    space.images("pairs/high", 1, 96)
    space.corrupt_png("pairs/low/0.png")
    return space.root / "pairs"


# (case id, fragment of the error line, argv built in the case's folder)
CASES: list[tuple[str, str, Build]] = [
    # 2. --force replaces only what the same command wrote: the user's files stay, byte for byte
    ("export-force-onto-user-folder", "is not an artefact written by toolkit export",
     lambda s: export(s, "-o", s.thesis(), "--force")),
    ("export-force-onto-artefact-with-user-file", "also holds files that are not part of an artefact",
     lambda s: export(s, "-o", s.artefact_copy(extra="thesis.txt"), "--force")),
    ("export-without-force", "pass --force", lambda s: export(s, "-o", s.artefact_copy())),
    ("quantise-force-onto-user-folder", "is not a quantised artefact written by toolkit quantise",
     lambda s: quantise(s, "-o", s.thesis(), "--force")),
    ("quantise-force-onto-exported-artefact", "is not a quantised artefact",
     lambda s: quantise(s, "-o", s.artefact_copy(), "--force")),
    ("profile-force-onto-user-folder", "is not a profile report", lambda s: profile(s, "-o", s.thesis(), "--force")),
    ("profile-calibration-over-user-file", "not a calibration file",
     lambda s: ["profile", "--calibrate", "--calibration", s.file("mine.json", b'{"mine": 1}\n')]),
    ("eval-onto-user-folder", "is not an eval report", lambda s: evaluate(s, "-o", s.thesis())),
    ("prune-over-its-source", "never replaces its source", lambda s: prune(s, "-o", s.assets.checkpoint, "--force")),
    ("prune-over-user-json", "not a report written by toolkit prune",
     lambda s: prune(s, "-o", s.file("mine.json", b'{"mine": 1}\n').with_suffix(".safetensors"), "--force")),
    ("prune-over-user-safetensors", "not a checkpoint written by toolkit prune",
     lambda s: prune(s, "-o", s.file("mine.safetensors", b"user bytes"), "--force")),
    ("label-into-user-folder", "without a store.json", lambda s: label(s, "--out", s.thesis())),
    # 3. an empty .pth
    ("export-empty-pth", "is empty",
     lambda s: ["export", "--target", "x86-cpu", "--checkpoint", s.empty_pth(), "-o", s.root / "out"]),
    ("prune-empty-pth", "is empty", lambda s: ["prune", "--checkpoint", s.empty_pth(), "--ratio", "0.5"]),
    ("eval-empty-pth", "is empty", lambda s: ["eval", "pairs", "--data", PAIRS, "--model", s.empty_pth()]),
    ("eval-empty-superpoint", "is empty",
     lambda s: ["eval", "pairs", "--data", PAIRS, "--model", f"superpoint:{s.empty_pth()}"]),
    ("profile-empty-pth", "is empty", lambda s: ["profile", "--model", s.empty_pth(), "--input-size", "64x64"]),
    ("label-empty-superpoint", "is empty",
     lambda s: ["label", "--teacher", f"superpoint:{s.empty_pth()}", "--images", PAIRS / "low", "--out", s.root / "l"]),
    # 4. pickled payloads are refused without running (the payload would create PWNED in the case folder)
    ("eval-pickle-superpoint", "refused without running",
     lambda s: ["eval", "pairs", "--data", PAIRS, "--model", f"superpoint:{s.evil_pth()}"]),
    ("export-pickle", "refused without running",
     lambda s: ["export", "--target", "x86-cpu", "--checkpoint", s.evil_pth(), "-o", s.root / "out"]),
    ("label-pickle-superpoint", "refused without running",
     lambda s: ["label", "--teacher", f"superpoint:{s.evil_pth()}", "--images", PAIRS / "low", "--out", s.root / "l"]),
    # 5. sizes bounded up front
    ("export-huge-size", "between 16 and 4096", lambda s: export(s, "--input-size", "100000x100000", "-o", s.root / "o")),
    ("label-huge-size", "between 16 and 4096", lambda s: label(s, "--size", "100000x100000", "--out", s.root / "l")),
    ("prune-huge-size", "between 16 and 4096", lambda s: prune(s, "--size", "100000x100000")),
    ("profile-huge-size", "between 16 and 4096", lambda s: profile(s, "--input-size", "100000x100000")),
    ("eval-huge-size", "16 to 4096", lambda s: evaluate(s, "--size", "100000x100000")),
    # 6. an output below a regular file
    ("export-below-file", "is a file, not a directory", lambda s: export(s, "-o", s.below_a_file())),
    ("quantise-below-file", "is a file, not a directory", lambda s: quantise(s, "-o", s.below_a_file())),
    ("label-below-file", "is a file, not a directory", lambda s: label(s, "--out", s.below_a_file())),
    ("train-below-file", "is a file, not a directory", lambda s: train(s, "--out", s.below_a_file())),
    ("prune-below-file", "is a file, not a directory",
     lambda s: prune(s, "-o", s.below_a_file().with_suffix(".safetensors"))),
    ("profile-below-file", "is a file, not a directory", lambda s: profile(s, "-o", s.below_a_file())),
    ("eval-below-file", "is a file, not a directory", lambda s: evaluate(s, "-o", s.below_a_file())),
    # 7. label options
    ("label-negative-max-keypoints", "--max-keypoints must be between 1",
     lambda s: label(s, "--max-keypoints=-1", "--out", s.root / "l")),
    ("label-tpu", "expected cpu or cuda", lambda s: label(s, "--device", "tpu", "--out", s.root / "l")),
    ("label-missing-cuda", "--device cuda:99", lambda s: label(s, "--device", "cuda:99", "--out", s.root / "l")),
    # 8. train config types (and the worker count)
    ("train-config-wrong-type", "lr", lambda s: train(s, "--config", s.file("c.json", b'{"lr": "fast"}'),
                                                      "--out", s.root / "run")),
    ("train-negative-workers", "--workers", lambda s: train(s, "--workers", "-1", "--out", s.root / "run")),
    # 10. export settings that produced empty or invalid artefacts
    ("export-nan-threshold", "--threshold", lambda s: export(s, "--threshold", "nan", "-o", s.root / "o")),
    ("export-negative-border", "--border", lambda s: export(s, "--border=-3", "-o", s.root / "o")),
    ("export-negative-nms", "--nms-radius", lambda s: export(s, "--nms-radius=-1", "-o", s.root / "o")),
    ("export-zero-keypoints", "--max-keypoints", lambda s: export(s, "--max-keypoints", "0", "-o", s.root / "o")),
    # 11. label --max-keypoints 0 wrote empty labels
    ("label-zero-keypoints", "--max-keypoints", lambda s: label(s, "--max-keypoints", "0", "--out", s.root / "l")),
    # 14. parity needs real content
    ("parity-one-flat-4x4", "at least 2",
     lambda s: export(s, "--parity-images", s.images("flat", 1, 4, flat=True), "-o", s.root / "o")),
    ("parity-tiny-images", "at least 64 px", lambda s: export(s, "--parity-images", s.images("tiny", 3, 8), "-o", s.root / "o")),
    ("parity-flat-images", "is flat",
     lambda s: export(s, "--parity-images", s.images("flat", 2, 96, flat=True), "-o", s.root / "o")),
    # messages that misled, or were not one line
    ("argparse-bad-int", "invalid int value", lambda s: export(s, "--max-keypoints", "many", "-o", s.root / "o")),
    ("argparse-missing-option", "required", lambda s: ["export", "--target", "tx2"]),
    ("argparse-unknown-option", "unrecognized arguments", lambda s: export(s, "--turbo", "-o", s.root / "o")),
    ("plain-pickle-pth-no-warning", "not a plain tensor state dict",
     lambda s: ["export", "--target", "x86-cpu", "--checkpoint", s.file("plain.pth", pickle.dumps({"a": 1})),
                "-o", s.root / "out"]),
    ("parity-corrupt-png", "cannot read image",
     lambda s: export(s, "--parity-images", corrupt_among_good(s), "-o", s.root / "o")),
    ("quantise-calibration-corrupt-png", "cannot read image",
     lambda s: quantise(s, "--calibration", s.corrupt_png("cal/a.png").parent, "-o", s.root / "q")),
    ("eval-nan-threshold", "--threshold a positive number", lambda s: evaluate(s, "--threshold", "nan")),
    ("eval-corrupt-png", "cannot decode image", lambda s: ["eval", "pairs", "--data", corrupt_pair(s), "--model", "orb"]),
    ("label-only-corrupt-images", "none of the 1 image files",
     lambda s: ["label", "--teacher", "shi-tomasi", "--images", s.corrupt_png("bad/a.png").parent, "--out", s.root / "l"]),
    ("quantise-manifest-without-sha256", "records no sha256",
     lambda s: ["quantise", "--artefact", s.artefact_without_sha256(), "--mode", "int8", "-o", s.root / "q"]),
    ("eval-manifest-without-sha256", "records no sha256",
     lambda s: ["eval", "pairs", "--data", PAIRS, "--model", s.artefact_without_sha256()]),
    ("profile-manifest-without-sha256", "records no sha256",
     lambda s: ["profile", "--model", s.artefact_without_sha256(), "--no-compare"]),
]


@pytest.mark.parametrize("name, fragment, build", CASES, ids=[case[0] for case in CASES])
def test_bad_input_is_one_error_line_and_changes_nothing(name, fragment, build, bad_input_assets, tmp_path, capsys):
    space = Space(tmp_path, bad_input_assets)
    argv = build(space)
    line = assert_refused(main, argv, capsys, fragment, tmp_path, bad_input_assets.root)
    assert not (tmp_path / "PWNED").exists()
    if "calibration" in name:  # calibration images are not "parity images"
        assert "parity" not in line


def test_every_subcommand_has_rows():
    commands = {case[0].split("-")[0] for case in CASES}
    assert {"export", "quantise", "prune", "profile", "eval", "label", "train"} <= commands


def test_help_keeps_argparse_usage_and_names_the_environment(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: toolkit") and "EDGEFEAT_DATA" in out
    assert main(["prune", "--help"]) == 0
    assert "$EDGEFEAT_DATA" in capsys.readouterr().out


def test_a_first_label_run_that_fails_leaves_no_store(bad_input_assets, tmp_path, capsys, monkeypatch):
    """A store that holds nothing would refuse the corrected rerun (other settings): a failed first run removes it."""
    import toolkit.cmd_label as cmd_label

    def out_of_memory(*_args, **_kwargs):
        raise MemoryError

    monkeypatch.setattr(cmd_label, "label_image", out_of_memory)
    space = Space(tmp_path, bad_input_assets)
    assert_refused(main, label(space, "--out", tmp_path / "labels"), capsys, "out of memory", tmp_path)
    monkeypatch.undo()
    rerun = label(space, "--out", tmp_path / "labels", "--size", "64x96")
    assert main([str(arg) for arg in rerun]) == 0  # the corrected rerun is not refused
