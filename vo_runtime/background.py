"""One job at a time on a second thread: how the VO overlaps a keyframe's mapping with the next extraction.

The tracking thread hands the keyframe work (triangulation, local bundle adjustment, culling) to `Background`
and returns; the next frame's features are extracted (onnxruntime releases the GIL while it runs) while the
job runs, and the tracking thread waits for the job before it touches the map again. The map is therefore
never read and written at once, and every result is the same as with mapping inline: only the time moves.
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable


class Background:
    """Runs submitted jobs on one worker thread, one at a time; `wait` returns the seconds spent waiting."""

    def __init__(self) -> None:
        self._executor: ThreadPoolExecutor | None = None
        self._pending: Future | None = None

    def submit(self, job: Callable[[], None]) -> None:
        """Start ``job`` once the previous one has finished (waiting for it here if needed)."""
        self.wait()
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vo-mapping")
        self._pending = self._executor.submit(job)

    def wait(self) -> float:
        """Block until the pending job is done; its exception, if any, is raised here."""
        if self._pending is None:
            return 0.0
        start = time.perf_counter()
        pending, self._pending = self._pending, None
        pending.result()
        return time.perf_counter() - start

    def close(self) -> None:
        """Finish the pending job and stop the worker thread (a later `submit` starts a new one)."""
        try:
            self.wait()
        finally:
            if self._executor is not None:
                self._executor.shutdown(wait=True)
                self._executor = None
