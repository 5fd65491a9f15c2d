"""Reading ``.pth`` weight files without unpickling arbitrary objects, and without torch's warnings."""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch

from vo_runtime.errors import first_line


def load_weights_only(path: str | Path) -> Any:
    """``torch.load(weights_only=True)`` on the CPU; `ValueError` with a one-line reason (callers name the file)
    for any unreadable file.

    A pickle that holds anything but tensors and containers is refused before any of it runs. torch's own
    UserWarnings (pickle protocol, legacy format) would print above our one-line error, so they are muted.
    """
    import pickle

    if Path(path).is_file() and Path(path).stat().st_size == 0:
        raise ValueError("the file is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise ValueError("not a plain tensor state dict saved by torch.save: refused without running any of it") from None
    except Exception as exc:  # torch.load raises many unrelated types (zip, EOF, OS, runtime) for a bad file
        raise ValueError(f"not a readable PyTorch weights file ({first_line(exc)})") from None
