"""Real images for distillation, calibration and drift measurement, prepared as the runtime prepares frames."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from export.parity import IMAGE_SUFFIXES, prepare_image, shared_data_dir
from toolkit.errors import ToolkitError

DEFAULT_IMAGE_FOLDER = "train_images"


def default_image_dir() -> Path:
    """``../shared/data/train_images`` (or under ``$EDGEFEAT_DATA``); `ToolkitError` if absent."""
    data = shared_data_dir()
    if data is None or not (data / DEFAULT_IMAGE_FOLDER).is_dir():
        raise ToolkitError("no default image folder: train_images/ is neither under $EDGEFEAT_DATA nor in "
                          "../shared/data; pass --images DIR")
    return data / DEFAULT_IMAGE_FOLDER


def find_images(folder: str | Path) -> list[Path]:
    """Image files under ``folder``, recursive and sorted; `ToolkitError` for a missing or image-less folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ToolkitError(f"image folder not found: {folder}")
    paths = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise ToolkitError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return paths


def spread(paths: list[Path], count: int) -> list[Path]:
    """``count`` paths evenly spread over the sorted list, so a small sample still covers every subfolder."""
    if count >= len(paths):
        return list(paths)
    picks = np.linspace(0, len(paths) - 1, count).round().astype(int)
    return [paths[i] for i in picks]


def load_images(folder: str | Path, count: int, size: tuple[int, int]) -> tuple[np.ndarray, list[Path]]:
    """``count`` images of ``folder`` as gray [N, 1, H, W] float32 in [0, 1] (INTER_AREA resize) and their paths."""
    paths = spread(find_images(folder), count)
    return np.concatenate([prepare_image(path, *size) for path in paths]), paths
