"""One thread at a time inside an object that is not thread-safe: a second thread is refused at once with
`ConcurrentUseError` instead of interleaving with the first (two threads in `VisualOdometry.track` repeated
frame indices, merged states, or divided by zero). The same thread may re-enter (track -> skip)."""
from __future__ import annotations

import functools
import threading
from typing import Any, Callable, TypeVar

from vo_runtime.errors import ConcurrentUseError

Method = TypeVar("Method", bound=Callable[..., Any])


class SingleCaller:
    """Guards the methods marked with `single_caller` on one instance."""

    def __init__(self, what: str) -> None:
        self.what = what
        self._lock = threading.RLock()

    def enter(self) -> None:
        if not self._lock.acquire(blocking=False):
            raise ConcurrentUseError(f"{self.what} is already in use by another thread: one instance tracks one "
                                     "stream from one thread at a time (use an instance per thread, or a lock)")

    def leave(self) -> None:
        self._lock.release()


def single_caller(method: Method) -> Method:
    """Mark a method of an object with a ``_caller: SingleCaller`` as one thread at a time."""
    @functools.wraps(method)
    def guarded(self: Any, *args: Any, **kwargs: Any) -> Any:
        self._caller.enter()
        try:
            return method(self, *args, **kwargs)
        finally:
            self._caller.leave()

    return guarded  # type: ignore[return-value]
