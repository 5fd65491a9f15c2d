"""End to end on the shared sequences (frames -> features -> VO -> trajectory -> ATE through evo), and the
CLI on bad input: black frames, repeated frames, a frame of another size, a missing calibration."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from test_vo_artefact import write_artefact

from vo_runtime import CalibrationError, OrbExtractor, VisualOdometry
from vo_runtime.cli import main
from vo_runtime.datasets import open_sequence
from vo_runtime.evaluate import evaluate
from vo_runtime.odometry import LOST, TRACKING
from vo_runtime.sequence import read_frames


@pytest.fixture(scope="module")
def artefact(tmp_path_factory):
    return write_artefact(tmp_path_factory.mktemp("harris"))


def test_cli_with_an_artefact_on_tum(shared_data, artefact, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["--artefact", str(artefact), "--images", str(shared_data / "tum_fr2_desk_snippet"),
                 "--gt", "auto", "-o", str(out), "--json", "--no-progress"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 20 and "lost" not in summary["states"]
    # 0.44 m of hand-held camera path; this Harris fixture measured 0.007 m.
    assert summary["ate_rmse_m"] < 0.03 and summary["frames_evaluated"] >= 15
    assert sorted(p.name for p in out.iterdir()) == [
        ".edgefeat-output.json", "frames.json", "summary.json", "trajectory.png", "trajectory_kitti.txt", "trajectory_tum.txt"]
    assert len((out / "trajectory_tum.txt").read_text().splitlines()) == 20


def test_orb_on_kitti_tracks_every_frame_and_keeps_scale(shared_data):
    sequence = open_sequence(shared_data / "kitti_odom06_f000000-000050")
    vo = VisualOdometry(OrbExtractor(2000, levels=1), sequence.camera)
    for image, stamp in zip(read_frames(sequence.frames), sequence.timestamps):
        vo.track(image, stamp)
    states = [r.status for r in vo.results]
    # The initialisation waits for a 2 degree median ray angle (VOConfig.init_min_median_deg): frame 7 here.
    assert LOST not in states and states.index(TRACKING) <= 10
    report = evaluate(vo.results, sequence.groundtruth, "kitti", sequence.timestamps)
    # 60 m of straight driving (52 m of it after the initialisation); measured 0.3-1.8 m depending on the
    # ORB feature count and the VO settings.
    assert report["path_length_m"] > 45 and report["ate_rmse_m"] < 3.0


def _write_frames(folder, images):
    folder.mkdir()
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"{i:06d}.png"), image)
    return folder


def _tum_frames(shared_data, count):
    sequence = open_sequence(shared_data / "tum_fr2_desk_snippet")
    return list(read_frames(sequence.frames[:count]))


def test_black_and_repeated_frames_hold_the_pose_without_crashing(shared_data, tmp_path):
    frames = _tum_frames(shared_data, 12)
    black = np.zeros_like(frames[0])
    images = [black, black, *frames[:6], black, frames[6], frames[6], frames[6], *frames[7:]]
    vo = VisualOdometry(OrbExtractor(2000), open_sequence(shared_data / "tum_fr2_desk_snippet").camera)
    returned = [vo.track(image, float(i)).pose.copy() for i, image in enumerate(images)]  # as an app sees them
    states = [r.status for r in vo.results]
    assert states[:2] == ["initialising", "initialising"] and states[8] == LOST and states[-1] == TRACKING
    np.testing.assert_array_equal(returned[8], returned[7])  # the black frame holds the pose
    # A repeated frame shows (almost) no motion: far less than the camera moves between real frames.
    steps = np.linalg.norm(np.diff(np.array(returned)[:, :3, 3], axis=0), axis=1)
    assert steps[10] < 0.2 * np.median(steps[12:]) and steps[9] > 0
    # The same through the CLI: every frame gets a finite pose and a state.
    folder = _write_frames(tmp_path / "frames", images)
    assert main(["--features", "orb", "--images", str(folder), "--calib", "tum-fr2", "-o", str(tmp_path / "run"),
                 "--no-progress"]) == 0
    assert [f["state"] for f in json.loads((tmp_path / "run" / "frames.json").read_text())] == states
    assert np.isfinite(np.loadtxt(tmp_path / "run" / "trajectory_kitti.txt")).all()


def test_frame_of_another_size_is_skipped_and_flagged(shared_data, tmp_path, capsys):
    # Never tracked with intrinsics that do not fit it: the frame is skipped (pose held) and reported.
    frames = _tum_frames(shared_data, 3)
    folder = _write_frames(tmp_path / "frames", [frames[0], frames[1], cv2.resize(frames[2], (320, 240))])
    assert main(["--features", "orb", "--images", str(folder), "--calib", "tum-fr2", "--no-progress", "--json",
                 "-o", str(tmp_path / "run")]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["skipped_frames"] == 1
    assert "frame is 320x240 but the calibration is for 640x480" in captured.err
    records = json.loads((tmp_path / "run" / "frames.json").read_text())
    assert records[2]["state"] == "skipped" and "320x240" in records[2]["problem"]


def test_missing_or_bad_calibration_is_a_clean_error(shared_data, tmp_path, capsys):
    folder = _write_frames(tmp_path / "frames", _tum_frames(shared_data, 2))
    assert main(["--features", "orb", "--images", str(folder), "--no-progress"]) == 2
    assert "no calib.txt: pass a calibration file" in capsys.readouterr().err
    assert main(["--features", "orb", "--images", str(folder), "--calib", str(tmp_path / "absent.txt")]) == 2
    assert "calibration not found" in capsys.readouterr().err
    (tmp_path / "calib.txt").write_text("P0: 1 2 3\n")
    assert main(["--features", "orb", "--images", str(folder), "--calib", str(tmp_path / "calib.txt")]) == 2
    assert "3 values" in capsys.readouterr().err
    _write_frames(tmp_path / "tum_other", [])
    (tmp_path / "tum_other").rename(tmp_path / "rgb")
    _write_frames(tmp_path / "tum_other", [])
    (tmp_path / "rgb").rename(tmp_path / "tum_other" / "rgb")
    cv2.imwrite(str(tmp_path / "tum_other" / "rgb" / "1.0.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(CalibrationError, match="without a known camera"):
        open_sequence(tmp_path / "tum_other")


def test_cli_argument_errors(shared_data, tmp_path, capsys, monkeypatch):
    tum = str(shared_data / "tum_fr2_desk_snippet")
    import vo_runtime.artefact

    monkeypatch.setattr(vo_runtime.artefact, "DEFAULT_ARTEFACT_DIR", tmp_path / "not-installed")
    assert main(["--images", tum]) == 2  # no --artefact and an install without the shipped one
    assert "shipped default artefact is missing" in capsys.readouterr().err
    monkeypatch.undo()
    assert main(["--features", "orb", "--images", tum, "--lowlight", "dusk"]) == 2  # not a preset, not numbers
    assert "GAMMA,SIGMA" in capsys.readouterr().err
    assert main(["--artefact", str(tmp_path), "--images", tum]) == 2
    assert "manifest.json is missing" in capsys.readouterr().err
    assert main(["--features", "orb", "--images", str(tmp_path / "absent")]) == 2
    assert "sequence folder not found" in capsys.readouterr().err


def test_sequence_readers(shared_data):
    kitti = open_sequence(shared_data / "kitti_odom07_f000000-000159" / "image_0")
    assert kitti.layout == "kitti" and len(kitti) == 160 and kitti.groundtruth.name == "poses.txt"
    assert kitti.timestamps[1] == pytest.approx(0.1038752) and kitti.camera.fx == pytest.approx(707.0912)
    tum = open_sequence(shared_data / "tum_fr2_desk_snippet")
    assert tum.layout == "tum" and len(tum) == 20 and tum.camera.dist[0] == pytest.approx(0.231222)
    assert tum.timestamps[0] == pytest.approx(1311868169.163498)


def test_all_black_sequence_reports_why_there_is_no_ate(shared_data, tmp_path, capsys):
    kitti = shared_data / "kitti_odom06_f000000-000050"
    root = tmp_path / "dark_kitti"
    _write_frames(tmp_path / "image_0", [np.zeros((370, 1226), np.uint8)] * 5)
    root.mkdir()
    (tmp_path / "image_0").rename(root / "image_0")
    (root / "calib.txt").write_text((kitti / "calib.txt").read_text())
    (root / "poses.txt").write_text("".join((kitti / "poses.txt").read_text().splitlines(True)[:5]))
    code = main(["--features", "orb", "--images", str(root), "--gt", "auto", "-o", str(tmp_path / "run"),
                 "--json", "--no-progress"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["states"] == {"initialising": 5} and summary["ate_rmse_m"] is None
    assert "nothing to evaluate" in summary["evaluation_error"]
    assert len((tmp_path / "run" / "trajectory_tum.txt").read_text().splitlines()) == 5


def test_cli_runs_the_shipped_artefact_by_default(shared_data, tmp_path, capsys):
    tum = str(shared_data / "tum_fr2_desk_snippet")
    assert main(["--images", tum, "--max-frames", "6", "--no-progress", "--json", "-o", str(tmp_path / "out")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["features"].endswith("default_artefact") and summary["frames"] == 6
