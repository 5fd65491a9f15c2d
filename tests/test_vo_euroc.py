"""The EuRoC ASL reader on a tiny mav0/ folder the test writes: frames and timestamps, the camera with its
radial-tangential distortion, the body ground truth composed with T_BS into camera poses, and bad files."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vo_runtime import CalibrationError, VORuntimeError
from vo_runtime.cli import main
from vo_runtime.datasets import open_sequence
from vo_runtime.euroc import camera_groundtruth, read_sensor_yaml

T0 = 1403638538577829376  # EuRoC MH_05's first frame, in ns
FRAME_NS = 50_000_000     # 20 Hz
SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [{t_bs}]
rate_hz: 20
resolution: [96, 64]
camera_model: pinhole
intrinsics: [60.5, 59.5, 47.2, 31.8] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
# A camera turned 90 deg about the body's z axis and offset 10 cm, as a VI-sensor sits on a drone.
BODY_FROM_CAMERA = np.array([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, -0.05], [0.0, 0.0, 1.0, 0.02], [0, 0, 0, 1]])


def _body_pose(t: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [0.1 * t, 0.3 * t, 0.05]).as_matrix()
    pose[:3, 3] = (1.0 + t, -2.0 * t, 0.5)
    return pose


def write_mav0(root, frames: int = 6, gt_offset_ns: int = 0, yaml_text: str | None = None):
    """A sequence folder holding mav0/ with cam0 (frames, data.csv, sensor.yaml) and 200 Hz ground truth."""
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    rng = np.random.default_rng(0)
    lines = ["#timestamp [ns],filename"]
    for i in range(frames):
        stamp = T0 + i * FRAME_NS
        cv2.imwrite(str(cam / "data" / f"{stamp}.png"), rng.integers(0, 255, (64, 96), dtype=np.uint8))
        lines.append(f"{stamp},{stamp}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    t_bs = ", ".join(repr(float(v)) for v in BODY_FROM_CAMERA.reshape(-1))
    (cam / "sensor.yaml").write_text(yaml_text if yaml_text is not None else SENSOR_YAML.format(t_bs=t_bs))
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    for k in range(-200, frames * 10 + 200):  # 200 Hz, 1 s either side, as EuRoC's
        stamp = T0 + k * 5_000_000 + gt_offset_ns
        pose = _body_pose((stamp - T0) * 1e-9)
        x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
        rows.append(",".join(str(v) for v in (stamp, *pose[:3, 3], w, x, y, z, 0, 0, 0)))
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    return root


def test_reads_frames_camera_and_timestamps_in_seconds(tmp_path):
    root = write_mav0(tmp_path / "seq")
    for path in (root, root / "mav0"):  # the folder holding mav0/, or mav0/ itself
        sequence = open_sequence(path)
        assert sequence.layout == "euroc" and len(sequence) == 6
        assert [p.name for p in sequence.frames] == [f"{T0 + i * FRAME_NS}.png" for i in range(6)]
        np.testing.assert_allclose(np.diff(sequence.timestamps), 0.05, atol=1e-6)
        assert sequence.timestamps[0] == pytest.approx(1403638538.5778294, abs=1e-6)
    camera = sequence.camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height) == (60.5, 59.5, 47.2, 31.8, 96, 64)
    assert camera.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    np.testing.assert_array_equal(sequence.body_from_camera, BODY_FROM_CAMERA)


def test_radtan_undistortion_round_trip(tmp_path):
    """Points projected with the radial-tangential model come back to their normalised coordinates."""
    camera = open_sequence(write_mav0(tmp_path / "seq")).camera
    normalised = np.array([[0.0, 0.0], [0.3, -0.2], [-0.5, 0.35], [0.6, 0.45]])
    rays = np.hstack([normalised, np.ones((4, 1))])
    pixels, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.matrix, np.asarray(camera.dist))
    pixels = pixels.reshape(-1, 2)
    assert np.abs(pixels[3] - (camera.cx + camera.fx * 0.6, camera.cy + camera.fy * 0.45)).max() > 3  # it distorts
    # OpenCV iterates 5 times: 1e-4 of a normalised unit at the corners, 0.04 px on the real EuRoC camera
    np.testing.assert_allclose(camera.normalise(pixels), normalised, atol=2e-4)


def test_groundtruth_is_the_camera_pose_t_wb_times_t_bs(tmp_path):
    sequence = open_sequence(write_mav0(tmp_path / "seq", gt_offset_ns=1_500_000))  # 1.5 ms off the frames
    stamps, poses = camera_groundtruth(sequence.groundtruth, sequence.body_from_camera, sequence.timestamps)
    np.testing.assert_allclose(stamps, sequence.timestamps)
    for i, pose in enumerate(poses):
        # by hand: the body pose at the nearest ground-truth stamp (1.5 ms after the frame), then the camera on it
        body = _body_pose((i * FRAME_NS + 1_500_000) * 1e-9)
        expected = np.eye(4)
        expected[:3, :3] = body[:3, :3] @ BODY_FROM_CAMERA[:3, :3]
        expected[:3, 3] = body[:3, :3] @ BODY_FROM_CAMERA[:3, 3] + body[:3, 3]
        np.testing.assert_allclose(pose, expected, atol=1e-9)


def test_cli_runs_a_euroc_folder_with_auto_groundtruth(tmp_path, capsys):
    root = write_mav0(tmp_path / "seq")
    assert main(["--features", "orb", "--images", str(root), "--gt", "auto", "--no-progress", "--json",
                 "-o", str(tmp_path / "run")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["layout"] == "euroc" and summary["frames"] == 6
    stamps = [float(line.split()[0]) for line in (tmp_path / "run" / "trajectory_tum.txt").read_text().splitlines()]
    np.testing.assert_allclose(stamps, open_sequence(root).timestamps, atol=1e-6)  # TUM stamps in seconds


def _corrupt(root, relative: str, text: str) -> None:
    (root / "mav0" / relative).write_text(text)


@pytest.mark.parametrize("relative, text, message", [
    ("cam0/sensor.yaml", "intrinsics: [1, 2\nresolution: [", "is not valid YAML"),
    ("cam0/sensor.yaml", SENSOR_YAML.format(t_bs="1, 0, 0"), "T_BS.data must be a list of 16"),
    ("cam0/sensor.yaml", "camera_model: pinhole\nintrinsics: [1, 2, 3]\n", "intrinsics must be a list of 4"),
    ("cam0/sensor.yaml", "camera_model: omni\n", "only pinhole"),
    ("cam0/data.csv", "#timestamp [ns],filename\n1403638538577829376\n", "1 fields, expected 2"),
    ("cam0/data.csv", "#t,f\n1403638538577829376,1403638538577829376.png\n1403638538477829376,x.png\n", "must increase"),
    ("cam0/data.csv", "#t,f\n1403638538577829376,nothere.png\n", "lists 1 frames that are not in"),
    ("cam0/data.csv", "#t,f\n14036385.5,a.png\n", "not a whole number of nanoseconds"),
])
def test_bad_files_are_one_error_line(tmp_path, capsys, relative, text, message):
    root = write_mav0(tmp_path / "seq")
    _corrupt(root, relative, text)
    assert main(["--features", "orb", "--images", str(root), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and message in err and len(err.splitlines()) == 1


def test_bad_groundtruth_and_missing_files(tmp_path, capsys):
    root = write_mav0(tmp_path / "far", gt_offset_ns=3_000_000_000)  # ground truth 3 s away from every frame
    assert main(["--features", "orb", "--images", str(root), "--gt", "auto", "--no-progress"]) == 2
    assert "no ground-truth pose within 5 ms of any frame" in capsys.readouterr().err
    root = write_mav0(tmp_path / "nan")
    _corrupt(root, "state_groundtruth_estimate0/data.csv", f"#t\n{T0},nan,0,0,1,0,0,0\n")
    assert main(["--features", "orb", "--images", str(root), "--gt", "auto", "--no-progress"]) == 2
    assert "holds 1 pose" in capsys.readouterr().err  # one line: nothing to associate frames with
    _corrupt(root, "state_groundtruth_estimate0/data.csv", f"#t\n{T0},nan,0,0,1,0,0,0\n{T0 + 5_000_000},0,0,0,1,0,0,0\n")
    assert main(["--features", "orb", "--images", str(root), "--gt", "auto", "--no-progress"]) == 2
    assert "non-finite poses" in capsys.readouterr().err
    with pytest.raises(CalibrationError, match="no cam1/ for --camera 1"):
        open_sequence(root, camera=1)
    (root / "mav0" / "cam0" / "sensor.yaml").unlink()
    with pytest.raises(CalibrationError, match="no sensor.yaml"):
        open_sequence(root)
    with pytest.raises(CalibrationError, match="not valid YAML"):
        read_sensor_yaml(_write(tmp_path / "deep.yaml", "a: " + "[" * 5000))
    assert issubclass(CalibrationError, VORuntimeError)


def _write(path, text):
    path.write_text(text)
    return path


def test_the_shipped_artefact_is_chosen_by_the_cameras_aspect(tmp_path, monkeypatch):
    """A 4:3 camera (and one of no known aspect) gets the 240x320 artefact; a camera whose aspect another shipped
    artefact has gets that one (a stand-in manifest at 240x376 for EuRoC's 752x480)."""
    import json as json_module

    import vo_runtime.artefact as artefact

    wide = tmp_path / "wide"
    wide.mkdir()
    manifest = json_module.loads((artefact.DEFAULT_ARTEFACT_DIR / "manifest.json").read_text())
    manifest["input"]["shape"] = [1, 1, 240, 376]
    (wide / "manifest.json").write_text(json_module.dumps(manifest))
    monkeypatch.setattr(artefact, "WIDE_ARTEFACT_DIR", tmp_path / "not-installed")
    assert artefact.default_artefact(752, 480) == artefact.DEFAULT_ARTEFACT_DIR  # none for it: the 4:3 one
    monkeypatch.setattr(artefact, "WIDE_ARTEFACT_DIR", wide)
    assert artefact.default_artefact(752, 480) == wide
    assert artefact.default_artefact(640, 480) == artefact.DEFAULT_ARTEFACT_DIR
    assert artefact.default_artefact(1226, 370) == artefact.DEFAULT_ARTEFACT_DIR  # KITTI: neither fits, the 4:3 one
    assert artefact.default_artefact() == artefact.DEFAULT_ARTEFACT_DIR
