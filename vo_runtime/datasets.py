"""Readers for image sequences: the KITTI odometry layout, the TUM RGB-D layout, or a plain folder.

- KITTI: ``image_0/000000.png ...``, ``calib.txt`` (P0..P3), optional ``times.txt`` and ``poses.txt``
  (row-major 3x4 camera-to-world per frame).
- TUM RGB-D: ``rgb/<timestamp>.png``, optional ``groundtruth.txt`` (``t tx ty tz qx qy qz qw``); TUM ships
  no calibration file, so ``calib`` names a file or the preset ``tum-fr2`` (chosen automatically when the
  folder name says fr2 / freiburg2).
- EuRoC MAV (ASL): ``mav0/camN/data.csv``, ``sensor.yaml`` (pinhole + radial-tangential, T_BS) and
  ``mav0/state_groundtruth_estimate0/data.csv`` (`euroc.py`); ``camera`` picks camN.
- Anything else: a folder of images plus a calibration file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vo_runtime.camera import Camera, load_camera
from vo_runtime.errors import CalibrationError, FrameError, VORuntimeError
from vo_runtime.euroc import euroc_root, open_euroc
from vo_runtime.sequence import frame_timestamps, list_frames, read_frame

# TUM RGB-D "freiburg2" RGB intrinsics (OpenCV distortion order), from the dataset's calibration page.
CAMERA_PRESETS = {
    "tum-fr2": Camera(fx=520.908620, fy=521.007327, cx=325.141442, cy=249.701764,
                      dist=(0.231222, -0.784899, -0.003257, -0.000105, 0.917205), width=640, height=480),
}


@dataclass
class Sequence:
    """Frames in order, their timestamps, the camera, and the ground-truth file if there is one."""

    layout: str                 # "kitti", "tum", "euroc" or "folder"
    frames: list[Path]
    timestamps: list[float]     # seconds (KITTI times.txt, TUM and EuRoC stamps), or frame indices
    camera: Camera
    groundtruth: Path | None    # KITTI poses.txt, TUM groundtruth.txt or EuRoC state_groundtruth_estimate0/data.csv
    body_from_camera: np.ndarray | None = None  # EuRoC T_BS: ground truth is of the body, the VO's of the camera

    def __len__(self) -> int:
        return len(self.frames)


def frame_size(camera: Camera, frames: list[Path]) -> tuple[int | None, int | None]:
    """(height, width) of the frames: the calibration's, or for one without a size (KITTI's) the first frame's;
    (None, None) when neither is known."""
    if camera.height and camera.width:
        return camera.height, camera.width
    try:  # read_frame: a corrupt first frame prints no decoder line here (it is reported when it is skipped)
        first = read_frame(frames[0]) if frames else None
    except FrameError:
        first = None
    return (None, None) if first is None else first.shape[:2]


def resolve_camera(calib: str | Path, camera: int = 0) -> Camera:
    """A calibration file (KITTI calib.txt or JSON) or a preset name from `CAMERA_PRESETS`."""
    if str(calib) in CAMERA_PRESETS:
        return CAMERA_PRESETS[str(calib)]
    if Path(calib).is_dir():
        raise CalibrationError(f"calibration {calib} is a folder, not a file")
    if not Path(calib).is_file():
        raise CalibrationError(f"calibration not found: {calib} (a file, or one of {', '.join(CAMERA_PRESETS)})")
    return load_camera(calib, camera)


def open_sequence(path: str | Path, calib: str | Path | None = None, camera: int = 0) -> Sequence:
    """Open a sequence folder (or a folder of images inside one) and detect its layout."""
    root = Path(path)
    if root.exists() and not root.is_dir():
        raise VORuntimeError(f"{root} is a file, not a sequence folder")
    if not root.is_dir():
        raise VORuntimeError(f"sequence folder not found: {root}")
    mav0 = euroc_root(root)
    if mav0 is not None:
        euroc = open_euroc(mav0, camera)
        return Sequence("euroc", euroc.frames, euroc.timestamps,
                        euroc.camera.camera if calib is None else resolve_camera(calib, camera),
                        euroc.groundtruth, euroc.camera.body_from_camera)
    if root.name.startswith("image_") and (root.parent / "calib.txt").is_file():
        root = root.parent
    if root.name == "rgb" and (root.parent / "groundtruth.txt").is_file():
        root = root.parent
    kitti_images = root / f"image_{camera}"
    if (root / "calib.txt").is_file() and not kitti_images.is_dir():
        found = sorted(p.name for p in root.glob("image_*") if p.is_dir())
        if found:  # a KITTI folder, but not for this camera: say so rather than "no calib.txt"
            raise CalibrationError(f"{root} has calib.txt but no {kitti_images.name}/ for --camera {camera} "
                                   f"(found {', '.join(found)}/)")
    if kitti_images.is_dir() and calib is None and not (root / "calib.txt").is_file():
        raise CalibrationError(f"{root} has {kitti_images.name}/ but no calib.txt: pass --calib")
    if kitti_images.is_dir() and (calib is not None or (root / "calib.txt").is_file()):  # --calib stands in
        frames = list_frames(kitti_images)
        times = root / "times.txt"
        return Sequence(
            "kitti", frames, frame_timestamps(frames, times if times.is_file() else None),
            resolve_camera(calib if calib is not None else root / "calib.txt", camera),
            root / "poses.txt" if (root / "poses.txt").is_file() else None,
        )
    if (root / "rgb").is_dir():
        frames = list_frames(root / "rgb")
        if calib is None:
            if "fr2" not in root.name and "freiburg2" not in root.name:
                raise CalibrationError(f"{root} is a TUM sequence without a known camera: pass a calibration")
            calib = "tum-fr2"
        groundtruth = root / "groundtruth.txt"
        return Sequence("tum", frames, frame_timestamps(frames), resolve_camera(calib, camera),
                        groundtruth if groundtruth.is_file() else None)
    if calib is None:
        raise CalibrationError(f"{root} has no calib.txt: pass a calibration file")
    frames = list_frames(root)
    return Sequence("folder", frames, frame_timestamps(frames), resolve_camera(calib, camera), None)
