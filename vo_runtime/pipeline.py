"""Extraction ahead of tracking: the network runs on the next frames while the VO tracks this one.

A frame's features do not depend on the map, so `MonoVO.extract` (which touches no VO state) runs on one
worker thread up to ``ahead`` frames in front of the tracking thread; onnxruntime and OpenCV release the GIL
while they work, so on two cores the network and the tracking overlap, and the throughput is that of the
slower of the two rather than their sum. Frames are tracked in order, by the same code as `MonoVO.process`,
so the poses are the same; only when each result is ready changes (a result waits for its own extraction and
tracking, never for a later frame's).

Why a queue deeper than one frame: tracking costs ~6 ms on an ordinary frame and ~20 ms on a keyframe
(triangulation and bundle adjustment), extraction ~7-8 ms on every frame. With one frame ahead, the worker
idles through each keyframe and the tracker then waits on the next extraction; two ahead absorb it.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Optional, Protocol

import numpy as np

from vo_runtime.config import Extraction, VOResult
from vo_runtime.errors import CalibrationError, FrameError, VORuntimeError


class Tracker(Protocol):
    """What the pipeline needs of a VO (`MonoVO` is one), named here so this module does not import the VO
    that imports it: extraction that touches no state, then tracking (or skipping) in order."""

    def extract(self, image: Optional[np.ndarray]) -> Extraction: ...

    def process_extraction(self, extraction: Extraction, timestamp: Optional[float] = None) -> VOResult: ...

    def skip(self, problem: str, timestamp: Optional[float] = None) -> VOResult: ...


_END = object()


@dataclass
class StreamFrame:
    """One frame of a stream. ``image`` is an image array (None: no frame) or a loader returning one, run on
    the worker thread (reading and decoding overlap the tracking too); a `FrameError` it raises skips the
    frame. ``name`` prefixes the problem of a skipped frame (e.g. its file name)."""

    image: np.ndarray | None | Callable[[], np.ndarray]
    timestamp: float | None = None
    name: str | None = None


def _as_frame(item: object) -> StreamFrame:
    if isinstance(item, StreamFrame):
        return item
    if isinstance(item, tuple) and len(item) == 2:
        return StreamFrame(item[0], item[1])
    raise FrameError(f"a stream holds (image, timestamp) pairs or StreamFrames, got {type(item).__name__}")


def _extract(vo: Tracker, frame: StreamFrame) -> Extraction:
    """Load (if ``frame.image`` is a loader) and extract one frame; a loader's `FrameError` is its problem."""
    image = frame.image
    if callable(image):
        try:
            image = image()
        except FrameError as exc:
            return Extraction(None, None, str(exc), usable=False)
    return vo.extract(image)


def _named(frame: StreamFrame, problem: str) -> str:
    return f"{frame.name}: {problem}" if frame.name else problem


def track_stream(vo: Tracker, frames: Iterable, ahead: int = 2, skip_wrong_size: bool = False) -> Iterator[VOResult]:
    """An iterator over `vo`'s result for each frame of ``frames``, extracting up to ``ahead`` frames in
    front on a worker thread (0: inline). See `MonoVO.stream`; a bad ``ahead`` raises here, at once."""
    if isinstance(ahead, bool) or not isinstance(ahead, (int, np.integer)) or ahead < 0:
        raise VORuntimeError(f"ahead must be an integer >= 0, got {ahead!r}")
    return _results(vo, iter(frames), int(ahead), skip_wrong_size)


def _results(vo: Tracker, items: Iterator, ahead: int, skip_wrong_size: bool) -> Iterator[VOResult]:
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vo-extract") if ahead > 0 else None
    pending: deque[tuple[StreamFrame, Future | None]] = deque()

    def refill() -> None:
        while len(pending) <= ahead:
            item = next(items, _END)
            if item is _END:
                return
            frame = _as_frame(item)
            pending.append((frame, executor.submit(_extract, vo, frame) if executor is not None else None))

    try:
        refill()
        while pending:
            frame, future = pending.popleft()
            refill()  # the worker starts on the next frames before this one is tracked
            extraction = future.result() if future is not None else _extract(vo, frame)
            if extraction.problem is not None:
                extraction.problem = _named(frame, extraction.problem)
            try:
                result = vo.process_extraction(extraction, frame.timestamp)
            except CalibrationError as exc:
                if not skip_wrong_size:
                    raise
                result = vo.skip(_named(frame, str(exc)), frame.timestamp)
            yield result
    finally:
        for _, future in pending:  # a consumer that stops early: drop the frames not yet tracked
            if future is not None:
                future.cancel()
        if executor is not None:
            executor.shutdown(wait=True)
