"""The bad-input matrix for the VO command lines: every row through ``toolkit vo`` and ``python -m vo_runtime``
(exit 2, one ``error:`` line, nothing changed, the user's sequence intact byte for byte), then what a bad frame
mid-sequence does (skipped and flagged, the run goes on) and what ``--force`` may replace."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

import toolkit.cli
import vo_runtime.cli
from bad_inputs_support import KITTI_06, Space, assert_refused

ENTRIES: dict[str, Callable[[list[str]], int]] = {
    "toolkit vo": lambda argv: toolkit.cli.main(["vo", *argv]),
    "python -m vo_runtime": vo_runtime.cli.main,
}


def orb(space: Space, *extra) -> list:
    """ORB features on the user's own copy of a short KITTI sequence."""
    return ["--features", "orb", "--images", space.sequence(), "--no-progress", *extra]


CASES: list[tuple[str, str, Callable[[Space], list]]] = [
    # 1. the output may not replace the input sequence (or any folder that is not an earlier vo run)
    ("output-is-the-input", "is not a VO run", lambda s: orb(s, "-o", s.root / "seq")),
    ("output-is-the-input-with-force", "is not a VO run", lambda s: orb(s, "-o", s.root / "seq", "--force")),
    ("output-is-a-user-folder", "is not a VO run", lambda s: orb(s, "-o", s.thesis(), "--force")),
    # 6. an output below a regular file
    ("output-below-file", "is a file, not a directory", lambda s: orb(s, "-o", s.below_a_file())),
    # 9. a garbage ground-truth file, read before the run
    ("garbage-gt", "is not a KITTI poses file", lambda s: orb(s, "--gt", s.file("gt.txt", b"not poses\n"))),
    ("gt-with-too-few-poses", "poses for 3 frames", lambda s: orb(s, "--gt", s.file("gt.txt", b"1 0 0 0 0 1 0 0 0 0 1 0\n"))),
    ("gt-auto-without-gt", "has no poses.txt",
     lambda s: ["--features", "orb", "--images", s.images("frames", 3, 64), "--calib", KITTI_06 / "calib.txt",
                "--gt", "auto"]),
    # 11. options that ran with no features or no frames
    ("zero-keypoints", "--max-keypoints", lambda s: orb(s, "--max-keypoints", "0")),
    ("negative-keypoints", "--max-keypoints", lambda s: orb(s, "--max-keypoints=-5")),
    ("zero-frames", "--max-frames", lambda s: orb(s, "--max-frames", "0")),
    ("zero-threads", "--threads", lambda s: orb(s, "--threads", "0")),
    ("zero-blas-threads", "--blas-threads", lambda s: orb(s, "--blas-threads", "0")),
    ("negative-extract-ahead", "--extract-ahead", lambda s: orb(s, "--extract-ahead=-1")),
    ("nan-lowlight", "--lowlight", lambda s: orb(s, "--lowlight", "nan,3")),
    # --set: a typo or a wrong type never runs the sequence with the default it meant to change
    ("set-unknown-field", "VOConfig has no field 'init_wanted_landmark'",
     lambda s: orb(s, "--set", "init_wanted_landmark=100")),
    ("set-unknown-mapping-field", "MappingConfig has no field 'nope'", lambda s: orb(s, "--set", "mapping.nope=1")),
    ("set-not-json", "the value is not JSON", lambda s: orb(s, "--set", "init_wanted_landmarks=many")),
    ("set-wrong-type", "init_wanted_landmarks takes an integer, got 1.5", lambda s: orb(s, "--set", "init_wanted_landmarks=1.5")),
    ("set-no-equals", "expected FIELD=VALUE", lambda s: orb(s, "--set", "init_wanted_landmarks")),
    ("set-out-of-range", "speed_frames must be >= 1", lambda s: orb(s, "--set", "speed_frames=0")),
    # messages
    ("camera-without-images", "no image_9/ for --camera 9", lambda s: orb(s, "--camera", "9")),
    ("artefact-manifest-without-sha256", "records no sha256",
     lambda s: ["--artefact", s.artefact_without_sha256(), "--images", s.sequence()]),
    ("argparse-bad-int", "invalid int value", lambda s: orb(s, "--max-frames", "all")),
    ("argparse-bad-choice", "invalid choice", lambda s: ["--features", "sift", "--images", s.root]),
    ("every-frame-corrupt", "none of the 2 frames could be used",
     lambda s: ["--features", "orb", "--images", corrupt_frames(s, 2), "--calib", KITTI_06 / "calib.txt"]),
]


def corrupt_frames(space: Space, count: int) -> Path:
    for index in range(count):
        space.corrupt_png(f"bad/{index:06d}.png")
    return space.root / "bad"


@pytest.mark.parametrize("entry", ENTRIES, ids=list(ENTRIES))
@pytest.mark.parametrize("name, fragment, build", CASES, ids=[case[0] for case in CASES])
def test_vo_bad_input_is_one_error_line_and_changes_nothing(entry, name, fragment, build, bad_input_assets,
                                                            tmp_path, capsys):
    argv = build(Space(tmp_path, bad_input_assets))
    assert_refused(ENTRIES[entry], argv, capsys, fragment, tmp_path, bad_input_assets.root)


def test_module_entry_point_has_no_traceback(tmp_path):
    sequence = Space(tmp_path, None).sequence()
    result = subprocess.run([sys.executable, "-m", "vo_runtime", "--features", "orb", "--images", str(sequence),
                             "-o", str(sequence)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and result.stderr.startswith("error: ") and len(result.stderr.splitlines()) == 1


def _kitti_copy(space: Space, frames: int, bit16: bool = False) -> Path:
    """A KITTI-layout copy of the first ``frames`` frames, optionally re-encoded as 16-bit PNGs."""
    root = space.sequence(frames)
    if bit16:
        for path in (root / "image_0").iterdir():
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 256  # same high byte
            cv2.imwrite(str(path), image)
    return root


def _states(run: Path) -> list[str]:
    return [frame["state"] for frame in json.loads((run / "frames.json").read_text())]


@pytest.mark.parametrize("entry", ENTRIES, ids=list(ENTRIES))
def test_corrupt_frame_mid_sequence_is_skipped_and_tracking_resumes(entry, tmp_path, capsys):
    space = Space(tmp_path, None)
    sequence = _kitti_copy(space, 17)  # ORB initialises at frame 10 here (the 2 degree gate)
    (sequence / "image_0" / "000012.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    before = (sequence / "image_0" / "000004.png").read_bytes()
    code = ENTRIES[entry](["--features", "orb", "--images", str(sequence), "--no-progress", "--json",
                           "-o", str(tmp_path / "run")])
    captured = capsys.readouterr()
    assert code == 0
    summary = json.loads(captured.out)
    assert summary["skipped_frames"] == 1 and summary["frames"] == 17
    assert captured.err.startswith("warning: skipped 1 of 17 frames") and "000012.png" in captured.err
    assert "[ERROR" not in captured.err and "Traceback" not in captured.err
    states = _states(tmp_path / "run")
    assert states[11] == "tracking" and states[12] == "skipped" and states[13:] == ["tracking"] * 4
    assert (sequence / "image_0" / "000004.png").read_bytes() == before  # the input is only read
    # Rerunning into the same folder needs --force, and --force replaces the earlier run.
    assert ENTRIES[entry](["--features", "orb", "--images", str(sequence), "-o", str(tmp_path / "run")]) == 2
    assert "pass --force" in capsys.readouterr().err
    assert ENTRIES[entry](["--features", "orb", "--images", str(sequence), "--max-frames", "4",
                           "-o", str(tmp_path / "run"), "--force"]) == 0
    assert len(_states(tmp_path / "run")) == 4


def test_16_bit_frames_track_like_their_8_bit_originals(tmp_path, capsys):
    runs = {}
    for bit16 in (False, True):
        space = Space(tmp_path / str(bit16), None)
        space.root.mkdir()
        sequence = _kitti_copy(space, 13, bit16=bit16)  # ORB tracks from frame 10
        assert vo_runtime.cli.main(["--features", "orb", "--images", str(sequence), "--no-progress",
                                    "-o", str(space.root / "run")]) == 0
        runs[bit16] = json.loads((space.root / "run" / "frames.json").read_text())
    capsys.readouterr()
    assert [f["state"] for f in runs[True]] == [f["state"] for f in runs[False]]
    assert [f["features"] for f in runs[True]] == [f["features"] for f in runs[False]]
    assert "tracking" in [f["state"] for f in runs[True]]
