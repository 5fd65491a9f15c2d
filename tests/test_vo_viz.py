"""--viz: per-frame overlays of a real run, readable, in the run folder; the trajectory plot marks start and end."""
from __future__ import annotations

import json

import cv2
import numpy as np

from vo_runtime.cli import main
from vo_runtime.config import VOResult
from vo_runtime.viz import STATE_COLOURS, draw_frame, stretch


def test_viz_writes_overlays_of_every_tenth_and_every_untracked_frame(shared_data, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["--features", "orb", "--images", str(shared_data / "tum_fr2_desk_snippet"), "--gt", "auto",
                 "-o", str(out), "--viz", "--no-progress", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    frames = json.loads((out / "frames.json").read_text())
    untracked = {f["index"] for f in frames if f["state"] not in ("tracking", "relocalised", "reinitialised")}
    expected = sorted({i for i in range(summary["frames"]) if i % 10 == 0} | untracked)
    pngs = sorted(out.glob("viz/*.png"))
    assert [int(p.stem) for p in pngs] == expected
    tracked = next(p for p in pngs if int(p.stem) not in untracked)
    overlay = cv2.imread(str(tracked))
    assert overlay.shape == (480, 640, 3)
    green = np.all(overlay == STATE_COLOURS["tracking"], axis=2)
    assert np.count_nonzero(green) > 200  # tracked landmarks ringed (and the banner) in the tracking colour
    if (out / "viz.mp4").exists():
        video = cv2.VideoCapture(str(out / "viz.mp4"))
        assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == summary["frames"]
    assert (out / "trajectory.png").stat().st_size > 10_000


def test_viz_needs_an_output_folder(shared_data, capsys):
    assert main(["--features", "orb", "--images", str(shared_data / "tum_fr2_desk_snippet"), "--viz"]) == 2
    assert "give -o DIR" in capsys.readouterr().err


def test_a_dark_frame_is_stretched_and_a_lost_one_framed_in_red():
    dark = (np.random.default_rng(0).random((60, 80)) * 20).astype(np.uint8)
    assert stretch(dark).max() >= 250 and dark.max() < 20
    lost = VOResult(index=3, timestamp=None, pose=np.eye(4), status="lost", num_features=10, num_matches=0,
                    num_inliers=0, num_landmarks=0, extract_ms=0.0, track_ms=0.0)
    overlay = draw_frame(dark, lost, np.array([[10.0, 30.0]]), None)
    assert tuple(overlay[-1, 40]) == STATE_COLOURS["lost"]
