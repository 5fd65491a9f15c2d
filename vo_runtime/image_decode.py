"""Decoding image bytes without library noise: libpng and libjpeg write their own lines straight to the
process's stderr ("libpng error: IDAT: incorrect data check") before OpenCV returns None, so a bad image
printed a foreign line beside our one-line error. `decode_image` catches that text and hands it back, for
the caller's message."""
from __future__ import annotations

import os
import sys
import tempfile
import threading
from typing import Optional, Tuple

import cv2
import numpy as np

# fd 2 is process-wide: one decode at a time holds it redirected (the extraction thread and the main one).
_STDERR_LOCK = threading.Lock()


def _decode_with_stderr_caught(data: np.ndarray, flags: int) -> Tuple[Optional[np.ndarray], str]:
    with _STDERR_LOCK, tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(caught.fileno(), 2)
            image = cv2.imdecode(data, flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        text = caught.read().decode("utf-8", "replace")
    return image, " ".join(text.split())


def decode_image(data: bytes | np.ndarray, flags: int = cv2.IMREAD_UNCHANGED) -> Tuple[Optional[np.ndarray], str]:
    """(the decoded image or None, what the decoder printed: "" when it printed nothing)."""
    buffer = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray)) else data
    if buffer.size == 0:
        return None, ""
    try:
        return _decode_with_stderr_caught(buffer, flags)
    except OSError:  # no fd 2 to redirect (a closed stderr): decode as it is
        return cv2.imdecode(buffer, flags), ""


def decode_problem(native: str) -> str:
    """`decode_image`'s captured text as a short suffix for an error message ("" when there is none)."""
    return f" ({native[:160]})" if native else ""
