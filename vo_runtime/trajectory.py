"""Writing trajectories in the TUM and KITTI text formats (readable by evo)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import numpy as np

from vo_runtime.atomic_file import write_atomic
from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import rotation_to_quaternion
from vo_runtime.odometry import VOResult

FORMATS = ("tum", "kitti")


def format_trajectory(results: Iterable[VOResult], fmt: str = "tum") -> str:
    """TUM: ``timestamp tx ty tz qx qy qz qw`` per frame (index when no timestamp).
    KITTI: the 12 values of the row-major 3x4 camera-to-world matrix per frame."""
    if fmt not in FORMATS:
        raise VORuntimeError(f"unknown trajectory format {fmt!r}; choose from {', '.join(FORMATS)}")
    lines = []
    for result in results:
        pose = np.asarray(result.pose)
        if fmt == "kitti":
            lines.append(" ".join(f"{v:.9e}" for v in pose[:3].reshape(-1)))
        else:
            stamp = float(result.index if result.timestamp is None else result.timestamp)
            values = [*pose[:3, 3], *rotation_to_quaternion(pose[:3, :3])]
            lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in values))
    return "\n".join(lines) + ("\n" if lines else "")


def write_trajectory(path: str | Path, results: Iterable[VOResult], fmt: str = "tum") -> None:
    """`format_trajectory` into ``path``, written all at once (a temporary sibling, then a rename)."""
    if not isinstance(path, (str, os.PathLike)):
        raise VORuntimeError(f"a trajectory is written to a file path, got {type(path).__name__}")
    write_atomic(path, format_trajectory(results, fmt).encode("ascii"))
