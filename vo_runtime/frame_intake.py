"""`FrameIntake`: what `MonoVO` checks of a frame before it tracks it (the array, its size against the calibration,
its timestamp) and the extractor run on it.

A base class of `MonoVO` only, over its state (``self.extractor``, ``self.camera``, ``self._frame_size``,
``self.results``), as `MapLifecycle` and `KeyframeUpkeep` are: split from odometry.py so that file keeps the
frame-by-frame states.
"""
from __future__ import annotations

import time

import numpy as np

from vo_runtime.config import Extraction
from vo_runtime.errors import CalibrationError, FrameError
from vo_runtime.features import check_frame
from vo_runtime.timestamps import checked_timestamp


class FrameIntake:
    def extract(self, image: np.ndarray | None) -> Extraction:
        """Check one frame and run the extractor on it. It reads and writes no state of the VO, so `stream`
        runs it on a worker thread; `process_extraction` then tracks the frame."""
        return self._unusable(image) or self._run_extractor(image)

    @staticmethod
    def _unusable(image: np.ndarray | None) -> Extraction | None:
        """The frame as an unusable `Extraction` when `check_frame` refuses it, else None."""
        if image is not None and not isinstance(image, np.ndarray):
            raise FrameError(f"expected an HxW or HxWx3 image array, got {type(image).__name__}")
        try:
            check_frame(image)
        except FrameError as exc:
            return Extraction(image, None, str(exc), usable=False)
        return None

    def _run_extractor(self, image: np.ndarray) -> Extraction:
        start = time.perf_counter()
        try:
            features = self.extractor(image)
        except FrameError as exc:  # e.g. an extractor whose resize policy rejects this size
            return Extraction(image, None, str(exc))
        return Extraction(image, features, seconds=time.perf_counter() - start)

    def _checked_timestamp(self, timestamp: float | None) -> float | None:
        """`TimestampError` (nothing changed) unless the stamp is None or finite and after the last frame's."""
        return checked_timestamp(timestamp, self.results[-1].timestamp if self.results else None)

    def _check_size(self, height: int, width: int) -> None:
        """Intrinsics fit one frame size: the calibration's, or when it names none, the first frame's."""
        self.camera.check_frame(height, width)
        if self._frame_size is not None and (height, width) != self._frame_size:
            raise CalibrationError(f"frame is {width}x{height} but this sequence's frames are "
                                   f"{self._frame_size[1]}x{self._frame_size[0]} (the size of its first frame, "
                                   "which the intrinsics were bound to: an odd first frame misfits all the others)")
