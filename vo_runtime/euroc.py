"""The EuRoC MAV (ETH ASL) dataset layout: one camera's frames, its calibration and the body's ground truth.

A sequence folder holds ``mav0/`` (or is ``mav0/``):

- ``camN/data.csv``: ``#timestamp [ns],filename`` a line, the frames in ``camN/data/``;
- ``camN/sensor.yaml``: ``camera_model: pinhole``, ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model:
  radial-tangential`` with ``distortion_coefficients: [k1, k2, p1, p2]`` (OpenCV's order), ``resolution:
  [width, height]`` and ``T_BS`` (``data``: 16 numbers, row-major), the camera-to-body transform;
- ``state_groundtruth_estimate0/data.csv``: ``timestamp [ns], p_RS_R xyz [m], q_RS wxyz, ...`` a line: the pose
  of the body (IMU) frame in the world at 200 Hz, so the camera's pose is ``T_WB @ T_BS``.

Timestamps are nanoseconds in the files and seconds here (and in the trajectories written, as TUM's).
PyYAML parses sensor.yaml: its flow lists span lines and carry comments, which a hand-written reader gets
wrong in ways a user would not see.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vo_runtime.camera import Camera
from vo_runtime.errors import CalibrationError, VORuntimeError
from vo_runtime.timestamps import nearest_samples

MAX_ASSOCIATION_S = 0.005  # a frame takes the nearest ground-truth pose within 5 ms (EuRoC's is at 200 Hz)
GROUNDTRUTH_DIR = "state_groundtruth_estimate0"


@dataclass(frozen=True)
class EurocCamera:
    """One camera of an ASL folder: intrinsics with distortion, and its pose on the body (camera-to-body)."""

    camera: Camera
    body_from_camera: np.ndarray  # T_BS, 4x4


def euroc_root(path: str | Path) -> Path | None:
    """The ``mav0`` folder of ``path`` (a sequence folder holding it, or ``mav0`` itself); None otherwise."""
    root = Path(path)
    for candidate in (root / "mav0", root):
        if candidate.name == "mav0" and candidate.is_dir() and any(candidate.glob("cam*/data.csv")):
            return candidate
    return None


def read_sensor_yaml(path: str | Path) -> EurocCamera:
    """Read a camera's ``sensor.yaml``; `CalibrationError` naming the file and what is wrong."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"cannot read {path} ({exc.__class__.__name__})") from None
    except (yaml.YAMLError, RecursionError) as exc:
        raise CalibrationError(f"{path} is not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping (EuRoC sensor.yaml)")
    if data.get("camera_model", "pinhole") != "pinhole":
        raise CalibrationError(f"{path}: camera_model {data.get('camera_model')!r}; only pinhole is supported")
    intrinsics = _numbers(data, "intrinsics", 4, path)
    model = data.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan", "none"):
        raise CalibrationError(f"{path}: distortion_model {model!r}; only radial-tangential is supported")
    dist = () if model == "none" else tuple(_numbers(data, "distortion_coefficients", 4, path))
    width, height = _numbers(data, "resolution", 2, path)
    if width != int(width) or height != int(height):
        raise CalibrationError(f"{path}: resolution must be two integers, got {data['resolution']}")
    extrinsics = data.get("T_BS")
    values = _numbers(extrinsics, "data", 16, path, "T_BS.data") if isinstance(extrinsics, dict) else None
    if values is None:
        raise CalibrationError(f"{path}: no T_BS (rows, cols, data: the camera-to-body transform)")
    body_from_camera = np.array(values, np.float64).reshape(4, 4)
    rotation = body_from_camera[:3, :3]
    if not np.allclose(body_from_camera[3], (0, 0, 0, 1)) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4):
        raise CalibrationError(f"{path}: T_BS is not a rigid transform (rotation and translation, last row 0 0 0 1)")
    fx, fy, cx, cy = intrinsics
    camera = Camera(fx=fx, fy=fy, cx=cx, cy=cy, dist=dist, width=int(width), height=int(height))
    return EurocCamera(camera, body_from_camera)


def _numbers(data: object, key: str, count: int, path: Path, name: str | None = None) -> list[float]:
    values = data.get(key) if isinstance(data, dict) else None
    numbers = [_number(v) for v in values] if isinstance(values, list) else []
    if len(numbers) != count or not all(v is not None and math.isfinite(v) for v in numbers):
        shown = repr(values) if len(repr(values)) <= 80 else repr(values)[:77] + "..."
        raise CalibrationError(f"{path}: {name or key} must be a list of {count} finite numbers, got {shown}")
    return numbers


def _number(value: object) -> float | None:
    """A YAML scalar as a float: PyYAML (YAML 1.1) leaves exponents without a dot, ``1e-05``, as strings."""
    if isinstance(value, bool):
        return None
    try:
        return float(value) if isinstance(value, (int, float, str)) else None
    except ValueError:
        return None


def _csv_rows(path: Path, columns: int) -> list[list[str]]:
    """The data lines of an ASL csv (``#`` comment lines skipped), each split at commas, at least ``columns``."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise VORuntimeError(f"cannot read {path} ({exc.__class__.__name__})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = [field.strip() for field in line.split(",")]
        if len(fields) < columns:
            raise VORuntimeError(f"{path} line {number}: {len(fields)} fields, expected {columns}")
        rows.append(fields)
    if not rows:
        raise VORuntimeError(f"{path} holds no data lines")
    return rows


def _nanoseconds(value: str, path: Path) -> int:
    if not value.isdigit():
        raise VORuntimeError(f"{path}: timestamp {value!r} is not a whole number of nanoseconds")
    return int(value)


def _increasing(stamps: list[int], path: Path) -> None:
    steps = np.diff(np.asarray(stamps, np.int64))
    if np.any(steps <= 0):
        bad = int(np.argmax(steps <= 0))
        raise VORuntimeError(f"{path}: timestamps must increase (line {bad + 2} of the data: {stamps[bad + 1]} after "
                             f"{stamps[bad]})")


def read_frame_list(camera_dir: str | Path) -> tuple[list[Path], list[float]]:
    """Frames (paths) and their timestamps in seconds from ``camN/data.csv``; every listed file must exist."""
    camera_dir = Path(camera_dir)
    csv = camera_dir / "data.csv"
    if not csv.is_file():
        raise VORuntimeError(f"{camera_dir} has no data.csv (EuRoC frame list)")
    rows = _csv_rows(csv, 2)
    stamps = [_nanoseconds(row[0], csv) for row in rows]
    _increasing(stamps, csv)
    frames = [camera_dir / "data" / row[1] for row in rows]
    missing = [p for p in frames if not p.is_file()]
    if missing:
        raise VORuntimeError(f"{csv} lists {len(missing)} frames that are not in {camera_dir / 'data'} "
                             f"(first: {missing[0].name})")
    return frames, [stamp * 1e-9 for stamp in stamps]


def read_body_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``state_groundtruth_estimate0/data.csv``: timestamps [N] in seconds and body-to-world poses [N, 4, 4]."""
    path = Path(path)
    rows = _csv_rows(path, 8)
    if len(rows) < 2:
        raise VORuntimeError(f"{path} holds {len(rows)} pose: nothing to evaluate against")
    stamps = [_nanoseconds(row[0], path) for row in rows]
    _increasing(stamps, path)
    try:
        values = np.array([[float(v) for v in row[1:8]] for row in rows], np.float64)
    except ValueError:
        raise VORuntimeError(f"{path}: position and quaternion columns must be numbers") from None
    if not np.all(np.isfinite(values)):
        raise VORuntimeError(f"{path} holds non-finite poses")
    norms = np.linalg.norm(values[:, 3:7], axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-2):
        raise VORuntimeError(f"{path}: quaternion q_RS (w x y z) of line {int(np.argmax(np.abs(norms - 1) > 1e-2)) + 1} "
                             f"of the data is not a unit quaternion")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(values[:, [4, 5, 6, 3]]).as_matrix()  # scipy takes x y z w (normalises)
    poses[:, :3, 3] = values[:, :3]
    return np.asarray(stamps, np.float64) * 1e-9, poses


def camera_groundtruth(path: str | Path, body_from_camera: np.ndarray, frame_times: list[float],
                       max_difference: float = MAX_ASSOCIATION_S) -> tuple[np.ndarray, np.ndarray]:
    """The camera's ground truth at the frames: each frame takes the nearest body pose within
    ``max_difference`` seconds and becomes ``T_WB @ T_BS`` (camera-to-world). Returns the frames' timestamps
    and poses of those that have one; `VORuntimeError` when none has."""
    stamps, body_poses = read_body_groundtruth(path)
    frame_times = np.asarray(frame_times, np.float64)
    nearest, gaps = nearest_samples(stamps, frame_times)
    close = gaps <= max_difference
    if not np.any(close):
        raise VORuntimeError(f"{path}: no ground-truth pose within {1e3 * max_difference:.0f} ms of any frame "
                             f"(frames {frame_times[0]:.3f}-{frame_times[-1]:.3f} s, ground truth "
                             f"{stamps[0]:.3f}-{stamps[-1]:.3f} s)")
    return frame_times[close], body_poses[nearest[close]] @ body_from_camera


@dataclass
class EurocSequence:
    """What `open_euroc` reads: frames and timestamps (s), the camera and its extrinsics, the ground truth file."""

    frames: list[Path]
    timestamps: list[float]
    camera: EurocCamera
    groundtruth: Path | None


def open_euroc(root: Path, camera: int = 0) -> EurocSequence:
    """Read camera ``camera`` of the ``mav0`` folder ``root``."""
    camera_dir = root / f"cam{camera}"
    if not camera_dir.is_dir():
        found = sorted(p.name for p in root.glob("cam*") if p.is_dir())
        raise CalibrationError(f"{root} has no cam{camera}/ for --camera {camera} (found {', '.join(found) or 'none'})")
    sensor = camera_dir / "sensor.yaml"
    if not sensor.is_file():
        raise CalibrationError(f"{camera_dir} has no sensor.yaml (the camera's calibration)")
    frames, stamps = read_frame_list(camera_dir)
    groundtruth = root / GROUNDTRUTH_DIR / "data.csv"
    return EurocSequence(frames, stamps, read_sensor_yaml(sensor), groundtruth if groundtruth.is_file() else None)
