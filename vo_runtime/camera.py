"""Pinhole camera with optional OpenCV distortion, and loaders for the calibration files we meet.

Supported files (`load_camera`):

- KITTI odometry ``calib.txt``: lines ``P0: <12 floats>`` ... (rectified, no distortion); ``camera`` picks P0..P3.
- JSON: ``{"fx": .., "fy": .., "cx": .., "cy": .., "dist": [k1, k2, p1, p2, k3], "width": .., "height": ..}``;
  ``dist``, ``width`` and ``height`` are optional.

The intrinsics refer to the frames handed to `MonoVO` (not to the network input): `FeatureExtractor` maps
keypoints back to the frame's own pixels.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vo_runtime.errors import CalibrationError, first_line

_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)  # the coefficient counts OpenCV accepts


def _is_real(value: object) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _is_whole(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels (pixel centres at integers, OpenCV convention)."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = field(default=())
    width: int | None = None
    height: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.dist, (tuple, list, np.ndarray)):
            raise CalibrationError(f"dist must be a sequence of numbers, got {type(self.dist).__name__}")
        names = ("fx", "fy", "cx", "cy") + tuple(f"dist[{i}]" for i in range(len(self.dist)))
        values = (self.fx, self.fy, self.cx, self.cy, *self.dist)
        for name, value in zip(names, values):
            if not _is_real(value):  # True is no focal length; numpy scalars are fine
                raise CalibrationError(f"camera parameter {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise CalibrationError(f"camera parameter {name} must be finite, got {value}")
        # Plain floats from here on: numpy scalars would leak into JSON and change arithmetic types.
        for name, value in zip(("fx", "fy", "cx", "cy"), values):
            object.__setattr__(self, name, float(value))
        object.__setattr__(self, "dist", tuple(float(v) for v in self.dist))
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if len(self.dist) not in _DIST_LENGTHS:
            raise CalibrationError(f"{len(self.dist)} distortion coefficients; OpenCV takes {_DIST_LENGTHS}")
        if (self.width is None) != (self.height is None):
            raise CalibrationError("give both width and height, or neither")
        if self.width is not None:
            for name, side in (("width", self.width), ("height", self.height)):
                if not _is_whole(side) or side <= 0:
                    raise CalibrationError(f"image {name} must be a positive whole number of pixels, got {side!r}")
            object.__setattr__(self, "width", int(self.width))
            object.__setattr__(self, "height", int(self.height))

    @property
    def matrix(self) -> np.ndarray:
        """3x3 intrinsic matrix K (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def focal(self) -> float:
        """Mean focal length, to turn pixel thresholds into normalised-plane thresholds."""
        return 0.5 * (self.fx + self.fy)

    def resized(self, source: tuple[int, int], target: tuple[int, int]) -> "Camera":
        """The same camera for frames resized from ``source`` (width, height) to ``target``.

        Pixel centres sit at integers, so the principal point scales about the -0.5 corner. Distortion
        coefficients act on normalised coordinates and do not change.
        """
        sx, sy = target[0] / source[0], target[1] / source[1]
        return Camera(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                      self.dist, int(target[0]), int(target[1]))

    def check_frame(self, height: int, width: int) -> None:
        """Raise `CalibrationError` if the calibration names a size and the frame has another."""
        if self.width is not None and (width, height) != (self.width, self.height):
            raise CalibrationError(
                f"frame is {width}x{height} but the calibration is for {self.width}x{self.height}"
            )

    def normalise(self, points: np.ndarray) -> np.ndarray:
        """Pixel (x, y) [N, 2] -> undistorted normalised image-plane coordinates [N, 2] (float64)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(points) == 0:
            return points
        if not self.dist:
            return (points - (self.cx, self.cy)) / (self.fx, self.fy)
        return cv2.undistortPoints(points[:, None, :], self.matrix, np.asarray(self.dist)).reshape(-1, 2)


def load_kitti_calib(path: str | Path, camera: int = 0) -> Camera:
    """Read projection matrix ``P<camera>`` of a KITTI odometry ``calib.txt``.

    Lines are ``P0: <12 floats>`` ...; files without the ``Pn:`` labels (12 floats a line) are read by order.
    """
    key = f"P{camera}"
    unlabelled = []
    found = None
    for line in _read_text(path).splitlines():
        name, colon, rest = line.partition(":")
        if not colon:
            if line.strip():
                unlabelled.append(line)
        elif name.strip() == key:
            found = rest
            break
    if found is None and camera < len(unlabelled):
        found = unlabelled[camera]
    if found is None:
        raise CalibrationError(f"{path}: no {key} line (is this a KITTI calib.txt?)")
    try:
        values = [float(v) for v in found.split()]
    except ValueError:
        raise CalibrationError(f"{path}: {key} holds non-numbers") from None
    if len(values) != 12:
        raise CalibrationError(f"{path}: {key} has {len(values)} values, expected 12 (3x4 row-major)")
    proj = np.array(values).reshape(3, 4)
    if proj[0, 1] != 0 or proj[1, 0] != 0 or proj[2, 0] != 0 or proj[2, 1] != 0 or proj[2, 2] != 1:
        raise CalibrationError(f"{path}: {key} is not a rectified pinhole projection [K | t]")
    return Camera(fx=float(proj[0, 0]), fy=float(proj[1, 1]), cx=float(proj[0, 2]), cy=float(proj[1, 2]))


def load_json_calib(path: str | Path) -> Camera:
    """Read a JSON calibration (see the module docstring)."""
    try:
        data = json.loads(_read_text(path))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise CalibrationError(f"{path} is not valid JSON ({first_line(exc)})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{path} holds a JSON {type(data).__name__}, expected an object with fx, fy, cx, cy")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise CalibrationError(f"{path}: missing {', '.join(missing)}")
    try:
        # The values as written: Camera refuses true, "500" or a width of 12.7 instead of reading them as numbers.
        return Camera(fx=data["fx"], fy=data["fy"], cx=data["cx"], cy=data["cy"], dist=data.get("dist", ()),
                      width=data.get("width"), height=data.get("height"))
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None


def load_camera(path: str | Path, camera: int = 0) -> Camera:
    """Load a calibration file, choosing the reader by content: JSON object, else KITTI ``calib.txt``."""
    text = _read_text(path)
    is_json = text.lstrip()[:1] in ("{", "[")  # an array is JSON too: say so rather than read it as calib.txt
    return load_json_calib(path) if is_json else load_kitti_calib(path, camera)


def _read_text(path: str | Path) -> str:
    if not isinstance(path, (str, os.PathLike)):
        raise CalibrationError(f"a calibration is a file path, got {type(path).__name__}")
    if Path(path).is_dir():
        raise CalibrationError(f"calibration {path} is a folder, not a file")
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise CalibrationError(f"calibration {path} is not UTF-8 text") from None
    except OSError as exc:
        raise CalibrationError(f"cannot read calibration {path} ({exc.__class__.__name__})") from None
