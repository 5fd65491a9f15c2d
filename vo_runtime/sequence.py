"""Reading an image sequence from a folder (frames sorted by name) with optional timestamps."""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from vo_runtime.errors import FrameError, TimestampError, VORuntimeError
from vo_runtime.image_decode import decode_image, decode_problem
from vo_runtime.timestamps import check_timestamps

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


def list_frames(folder: str | Path) -> list[Path]:
    """Image files of a folder, sorted by name (KITTI ``000000.png``, TUM ``<timestamp>.png``)."""
    directory = Path(folder)
    if directory.exists() and not directory.is_dir():
        raise VORuntimeError(f"{directory} is a file, not a folder of frames")
    if not directory.is_dir():
        raise VORuntimeError(f"frame folder not found: {directory}")
    frames = sorted(p for p in directory.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not frames:
        raise VORuntimeError(f"{directory} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return frames


def frame_timestamps(frames: list[Path], times_file: str | Path | None = None) -> list[float]:
    """One timestamp per frame: from ``times_file`` (one number a line, KITTI ``times.txt``; finite and
    increasing, else `TimestampError`), else from file names that are increasing numbers (TUM), else the
    frame index."""
    if times_file is not None:
        try:
            text = Path(times_file).read_text(encoding="utf-8")
            times = [float(line.split()[0]) for line in text.splitlines() if line.strip()]
        except (OSError, ValueError, IndexError) as exc:  # UnicodeDecodeError is a ValueError
            raise VORuntimeError(f"cannot read timestamps from {times_file} ({exc.__class__.__name__})") from None
        if len(times) < len(frames):
            raise VORuntimeError(f"{times_file} has {len(times)} timestamps for {len(frames)} frames")
        check_timestamps(times[: len(frames)], str(times_file))
        return times[: len(frames)]
    try:
        stamps = [float(p.stem) for p in frames]
        check_timestamps(stamps, "frame names")
    except (ValueError, TimestampError):  # names that are no increasing times (0.png, 1.png, 10.png, 2.png)
        return [float(i) for i in range(len(frames))]
    return stamps


def read_frame(path: str | Path) -> np.ndarray:
    """One frame as OpenCV loads it (gray stays gray, colour is BGR, 16-bit stays 16-bit); `FrameError` when
    the file cannot be read or decoded."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise FrameError(f"cannot read image {path} ({exc.strerror or type(exc).__name__})") from None
    image, native = decode_image(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FrameError(f"cannot decode image {path}{decode_problem(native)}")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def read_frames(frames: list[Path]) -> Iterator[np.ndarray]:
    """Yield each frame as `read_frame` loads it; raises `FrameError` at the first unreadable one."""
    for path in frames:
        yield read_frame(path)
