"""vo_runtime building blocks: calibration files, matching, pose helpers, trajectory files, sequences."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from vo_runtime import CalibrationError, Camera, VORuntimeError, load_camera
from vo_runtime.geometry import make_pose, rotation_to_quaternion, triangulate
from vo_runtime.matching import match_mutual_nn
from vo_runtime.odometry import VOResult
from vo_runtime.sequence import frame_timestamps, list_frames, read_frames
from vo_runtime.trajectory import format_trajectory

KITTI_P = "7.070912e+02 0 6.018873e+02 0 0 7.070912e+02 1.831104e+02 0 0 0 1 0"


# ---------------------------------------------------------------------------------------------- camera
def test_kitti_calib_labelled_and_unlabelled(tmp_path, shared_data):
    labelled = load_camera(shared_data / "kitti_odom07_f000000-000159" / "calib.txt")
    unlabelled = load_camera(shared_data / "kitti_odom06_f000000-000050" / "calib.txt")
    for cam in (labelled, unlabelled):
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((707.0912, 707.0912, 601.8873, 183.1104))
        assert cam.dist == ()
    (tmp_path / "calib.txt").write_text(f"P0: {KITTI_P}\nP1: {KITTI_P.replace(' 0 0 7', ' -3.798145e+02 0 7', 1)}\n")
    assert load_camera(tmp_path / "calib.txt", camera=1).fx == pytest.approx(707.0912)


@pytest.mark.parametrize(
    "text, message",
    [
        ("P0: 1 2 3\n", "3 values"),
        ("P0: 700 5 600 0 0 700 180 0 0 0 1 0\n", "not a rectified pinhole"),
        ("P0: a b c d e f g h i j k l\n", "non-numbers"),
        ("P1: " + KITTI_P + "\n", "no P0 line"),
        ("", "no P0 line"),
    ],
)
def test_bad_kitti_calib(tmp_path, text, message):
    (tmp_path / "calib.txt").write_text(text)
    with pytest.raises(CalibrationError, match=message):
        load_camera(tmp_path / "calib.txt")


def test_json_calib(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7,
                                "dist": [0.23, -0.78, -0.003, -0.0001, 0.92], "width": 640, "height": 480}))
    cam = load_camera(path)
    assert cam.dist == pytest.approx((0.23, -0.78, -0.003, -0.0001, 0.92))
    assert (cam.width, cam.height) == (640, 480)
    path.write_text(json.dumps({"fx": 1, "fy": 1, "cx": 0}))
    with pytest.raises(CalibrationError, match="missing cy"):
        load_camera(path)
    path.write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_camera(path)
    with pytest.raises(CalibrationError, match="cannot read"):
        load_camera(tmp_path / "absent.json")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(fx=0, fy=1, cx=0, cy=0), "positive"),
        (dict(fx=1, fy=1, cx=float("nan"), cy=0), "finite"),
        (dict(fx=1, fy=1, cx=0, cy=0, dist=(0.1, 0.2, 0.3)), "3 distortion"),
        (dict(fx=1, fy=1, cx=0, cy=0, width=640), "both width and height"),
    ],
)
def test_camera_validation(kwargs, message):
    with pytest.raises(CalibrationError, match=message):
        Camera(**kwargs)


def test_normalise_undoes_projection_with_distortion():
    cam = Camera(520.9, 521.0, 325.1, 249.7, (0.231222, -0.784899, -0.003257, -0.000105, 0.917205))
    rng = np.random.default_rng(0)
    plane = rng.uniform(-0.5, 0.5, size=(50, 2))
    pixels, _ = cv2.projectPoints(np.c_[plane, np.ones(50)], np.zeros(3), np.zeros(3), cam.matrix, np.array(cam.dist))
    np.testing.assert_allclose(cam.normalise(pixels.reshape(-1, 2)), plane, atol=1e-5)
    plain = Camera(500, 400, 320, 240)
    np.testing.assert_allclose(plain.normalise([[820, 640]]), [[1.0, 1.0]])


# ---------------------------------------------------------------------------------------------- matching
def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_mutual_nn_recovers_a_permutation():
    rng = np.random.default_rng(1)
    a = _unit(rng.normal(size=(300, 32)))
    perm = rng.permutation(300)
    b = _unit(a[perm] + 0.05 * rng.normal(size=(300, 32)))
    matches = match_mutual_nn(a, b)
    assert len(matches) == 300
    np.testing.assert_array_equal(perm[matches[:, 1]], matches[:, 0])


def test_mutual_nn_thresholds_and_ties():
    a = _unit(np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]))
    b = _unit(np.array([[1.0, 0.05, 0], [0, 1, 1], [-1, 0, 0]]))
    # row 1 and row 2 tie for column 1: no mutual best there; column 2 is too far from everything.
    np.testing.assert_array_equal(match_mutual_nn(a, b, max_distance=0.9, ratio=None), [[0, 0]])
    # The ratio test rejects a best match that is not clearly better than the second.
    c = _unit(np.array([[1.0, 0.1, 0], [1.0, -0.105, 0]]))
    assert len(match_mutual_nn(a[:1], c, ratio=0.9)) == 0
    assert len(match_mutual_nn(a[:1], c, ratio=None)) == 1
    assert match_mutual_nn(a[:0], b).shape == (0, 2)
    with pytest.raises(ValueError, match="sizes differ"):
        match_mutual_nn(a, b[:, :2])


# ---------------------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("rvec", [(0, 0, 0), (0.3, -0.2, 0.1), (np.pi, 0, 0), (0, 3.0, 0.5), (0, 0, -3.1)])
def test_rotation_to_quaternion(rvec):
    rot = cv2.Rodrigues(np.array(rvec, float))[0]
    x, y, z, w = rotation_to_quaternion(rot)
    assert w >= 0 and np.linalg.norm([x, y, z, w]) == pytest.approx(1)
    back = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    np.testing.assert_allclose(back, rot, atol=1e-9)


def test_triangulate_and_cheirality():
    world = np.array([[0.5, -0.2, 5.0], [-1.0, 0.3, 8.0]])
    pose_a = np.eye(4)
    pose_b = make_pose(cv2.Rodrigues(np.array([0.0, 0.05, 0.0]))[0], [-0.5, 0, 0])
    def project(pose, pts):
        cam = pts @ pose[:3, :3].T + pose[:3, 3]
        return cam[:, :2] / cam[:, 2:]
    points, error = triangulate(pose_a, pose_b, project(pose_a, world), project(pose_b, world))
    np.testing.assert_allclose(points, world, atol=1e-9)
    assert np.all(error < 1e-9)
    behind = np.array([[0.0, 0.0, -5.0]])
    _, error = triangulate(pose_a, pose_b, project(pose_a, behind), project(pose_b, behind))
    assert np.isinf(error[0])


# ---------------------------------------------------------------------------------------------- trajectory
def _result(index, pose, timestamp=None):
    return VOResult(index, timestamp, pose, "tracking", 0, 0, 0, 0, 0.0, 0.0)


def test_trajectory_formats():
    pose = make_pose(cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0], [1, 2, 3])
    results = [_result(0, np.eye(4), 0.5), _result(1, pose)]
    tum = format_trajectory(results, "tum").splitlines()
    assert tum[0].split() == ["0.500000", *["0.000000000"] * 6, "1.000000000"]
    values = [float(v) for v in tum[1].split()]
    assert values[0] == 1.0  # no timestamp: the index
    np.testing.assert_allclose(values[1:], [1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-9)
    kitti = format_trajectory(results, "kitti").splitlines()
    np.testing.assert_allclose(np.array(kitti[1].split(), float).reshape(3, 4), pose[:3])
    with pytest.raises(VORuntimeError, match="unknown trajectory format"):
        format_trajectory(results, "csv")


# ---------------------------------------------------------------------------------------------- sequences
def test_sequence_listing_and_timestamps(tmp_path, shared_data):
    tum = list_frames(shared_data / "tum_fr2_desk_snippet" / "rgb")
    assert len(tum) == 20
    stamps = frame_timestamps(tum)
    assert stamps[0] == pytest.approx(1311868169.163498) and stamps == sorted(stamps)
    kitti = shared_data / "kitti_odom07_f000000-000159"
    frames = list_frames(kitti / "image_0")[:5]
    assert frame_timestamps(frames, kitti / "times.txt")[1] == pytest.approx(0.1038752)
    assert next(read_frames(frames)).shape == (370, 1226)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"frame_{i}.png"), np.zeros((4, 4), np.uint8))
    assert frame_timestamps(list_frames(tmp_path)) == [0.0, 1.0, 2.0]
    (tmp_path / "times.txt").write_text("0\n0.1\n")
    with pytest.raises(VORuntimeError, match="2 timestamps for 3 frames"):
        frame_timestamps(list_frames(tmp_path), tmp_path / "times.txt")
    (tmp_path / "frame_9.png").write_bytes(b"not a png")
    with pytest.raises(VORuntimeError, match="cannot decode"):
        list(read_frames(list_frames(tmp_path)))
    with pytest.raises(VORuntimeError, match="not found"):
        list_frames(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VORuntimeError, match="holds no images"):
        list_frames(tmp_path / "empty")


# ---------------------------------------------------------------------------------------------- bundle adjustment
@pytest.mark.parametrize("solver", ["scipy", "schur"])
def test_bundle_adjustment_reduces_pose_and_point_error(solver):
    from vo_runtime.bundle import bundle_adjust
    from vo_runtime.schur import schur_bundle_adjust

    rng = np.random.default_rng(0)
    truth = np.c_[rng.uniform(-5, 5, 200), rng.uniform(-2, 2, 200), rng.uniform(8, 30, 200)]
    poses = [make_pose(cv2.Rodrigues(np.array([0, 0.01 * i, 0]))[0], [-0.3 * i, 0, -0.5 * i]) for i in range(6)]
    frames = np.repeat(np.arange(6), 200)
    points = np.tile(np.arange(200), 6)
    observed = np.concatenate([
        (lambda cam: cam[:, :2] / cam[:, 2:])(truth @ p[:3, :3].T + p[:3, 3]) for p in poses
    ]) + rng.normal(scale=0.5 / 500, size=(1200, 2))  # 0.5 px noise at f = 500
    noisy_poses = [p.copy() for p in poses]
    for p in noisy_poses[2:]:  # the first two are fixed: they set the gauge and the scale
        p[:3, 3] += rng.normal(scale=0.05, size=3)
    noisy_points = truth + rng.normal(scale=0.2, size=truth.shape)
    adjust = bundle_adjust if solver == "scipy" else schur_bundle_adjust  # the local BA's own solver
    result = adjust(noisy_poses, 2, noisy_points, frames, points, observed, focal=500.0)
    def pose_error(ps):
        return np.mean([np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(ps[2:], poses[2:])])
    assert result.final_cost < 0.01 * result.initial_cost
    assert np.median(result.residual_px) < 1.0
    assert pose_error(result.poses_cw) < 0.2 * pose_error(noisy_poses)
    # Points: depth along 1-3 m baselines at 8-30 m stays uncertain at 0.5 px; measured 0.32 -> 0.22 m.
    point_error = np.median(np.linalg.norm(result.points - truth, axis=1))
    assert point_error < 0.8 * np.median(np.linalg.norm(noisy_points - truth, axis=1))
    np.testing.assert_array_equal(result.poses_cw[0], noisy_poses[0])


def test_schur_point_block_inverse_matches_numpy():
    from vo_runtime.schur import _inverse_3x3

    rng = np.random.default_rng(3)
    blocks = rng.normal(size=(50, 3, 3))
    blocks = blocks @ blocks.transpose(0, 2, 1) + 1e-3 * np.eye(3)  # symmetric positive definite, as in BA
    np.testing.assert_allclose(_inverse_3x3(blocks), np.linalg.inv(blocks), rtol=1e-7, atol=1e-9)
