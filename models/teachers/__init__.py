"""Teachers for self-supervised labelling: anything mapping image [B, 1, H, W] in [0, 1] to a dense
keypoint score map [B, 1, H, W] in [0, 1].

``--teacher`` strings:
    alike-t | alike-s | alike-n | alike-l      ALIKE (BSD-3 weights in ../shared/data/weights_alike)
    aliked-t16 | aliked-n16                   ALIKED (same folder)
    superpoint:PATH                            a Magic Leap superpoint_v1.pth
    shi-tomasi                                 OpenCV minimum-eigenvalue corners, no weights
The ALIKE weights folder is ``$EDGEFEAT_ALIKE_WEIGHTS`` if set, else ``../shared/data/weights_alike``
beside the repository.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import torch
from torch import nn

from models.keypoints import Refinement
from models.teachers.alike import ALIKE_CONFIGS, load_alike
from models.teachers.aliked import ALIKED_CONFIGS, load_aliked
from models.teachers.classical import ShiTomasiTeacher
from models.errors import TeacherError
from vo_runtime.errors import first_line

Teacher = Callable[[torch.Tensor], torch.Tensor]

TEACHER_NAMES = [*ALIKE_CONFIGS, *ALIKED_CONFIGS, "superpoint:PATH", "shi-tomasi"]
# ALIKE's own sub-pixel keypoints (its DKD detector): a soft-argmax of the score map over the 5x5 window
# around each NMS peak, temperature 0.1.
TEACHER_REFINEMENT = Refinement("softargmax", radius=2, temperature=0.1)
DEFAULT_WEIGHTS_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "weights_alike"


def alike_weights_dir() -> Path:
    return Path(os.environ.get("EDGEFEAT_ALIKE_WEIGHTS", DEFAULT_WEIGHTS_DIR)).resolve()


def build_teacher(name: str, weights_dir: str | Path | None = None) -> nn.Module:
    """Parse a ``--teacher`` string into an eval-mode teacher module.

    Raises:
        TeacherError: unknown name, missing or unreadable weight file.
    """
    if name in ALIKE_CONFIGS or name in ALIKED_CONFIGS:
        folder = Path(weights_dir) if weights_dir else alike_weights_dir()
        path = folder / f"{name}.pth"
        if not path.is_file():
            raise TeacherError(f"teacher {name}: weight file not found: {path}")
        loader = load_alike if name in ALIKE_CONFIGS else load_aliked
        try:
            return loader(name, folder)
        except Exception as exc:  # torch.load raises many types (zip, pickle, shape): one message
            raise TeacherError(f"teacher {name}: cannot load {path}: {first_line(exc)}") from None
    if name.startswith("superpoint:"):
        from models.teachers.superpoint import load_superpoint_teacher

        path = Path(name.split(":", 1)[1]).expanduser()
        if not path.is_file():
            raise TeacherError(f"teacher superpoint: weight file not found: {path}")
        try:
            return load_superpoint_teacher(path)
        except Exception as exc:  # torch.load raises many types (zip, pickle, shape): one message
            raise TeacherError(f"teacher superpoint: cannot load {path}: {first_line(exc)}") from None
    if name == "shi-tomasi":
        return ShiTomasiTeacher()
    raise TeacherError(f"unknown teacher {name!r} (expected one of: {', '.join(TEACHER_NAMES)})")
