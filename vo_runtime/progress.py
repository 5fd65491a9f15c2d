"""Progress that reaches a log: a tqdm bar on a terminal, a line at intervals (with an ETA) anywhere else.

A bar redrawn with carriage returns is unreadable in a log file, CI output or an ssh pipe, and tqdm's
``disable=None`` shows nothing there at all, so a command writing to a log was silent for minutes. When stderr
is not a terminal, `progress_bar` returns a `LineProgress` instead: one plain line every `interval_seconds` (10 s;
``$EDGEFEAT_PROGRESS_SECONDS`` changes it), none for work that ends sooner, and a closing line after one was
printed. Both expose what the commands use of tqdm: iteration, ``update``, ``set_postfix``, ``close``.
"""
from __future__ import annotations

import math
import os
import sys
import time
from typing import Any, Callable, Iterable, Iterator, Optional, TextIO

INTERVAL_VARIABLE = "EDGEFEAT_PROGRESS_SECONDS"
DEFAULT_INTERVAL_S = 10.0


def interval_seconds() -> float:
    """Seconds between progress lines: ``$EDGEFEAT_PROGRESS_SECONDS`` when it is a number >= 0, else 10."""
    try:
        value = float(os.environ.get(INTERVAL_VARIABLE, DEFAULT_INTERVAL_S))
    except ValueError:
        return DEFAULT_INTERVAL_S
    return value if value >= 0 else DEFAULT_INTERVAL_S


def format_duration(seconds: float) -> str:
    """3725 -> '1h02m', 95 -> '1m35s', 7.2 -> '7s'."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    if seconds >= 60:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds}s"


class LineProgress:
    """A progress counter that prints a line to ``file`` at most every ``interval`` seconds (see the module doc)."""

    def __init__(self, iterable: Optional[Iterable[Any]] = None, total: Optional[int] = None, desc: str = "",
                 unit: str = "it", initial: int = 0, file: Optional[TextIO] = None, interval: Optional[float] = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)  # type: ignore[arg-type]
        self.total, self.desc, self.unit = total, desc, unit
        self.count = self.initial = initial
        self.file = file or sys.stderr
        self.interval = interval_seconds() if interval is None else interval
        self.clock = clock
        self.start = self.last = clock()
        self.postfix = ""
        self.printed = False

    def __iter__(self) -> Iterator[Any]:
        for item in self.iterable or ():
            yield item
            self.update(1)
        self.close()

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.count += n
        now = self.clock()
        if now - self.last >= self.interval:
            self.last = now
            self.print_line(now)

    def set_postfix(self, **fields: Any) -> None:
        self.postfix = ", ".join(f"{key}={value}" for key, value in fields.items())

    def line(self, now: float) -> str:
        """'train: 120/20000 step (0.6%), 1.95 step/s, elapsed 1m01s, ETA 2h49m, loss=0.812'."""
        elapsed = now - self.start
        done = self.count - self.initial
        rate = done / elapsed if elapsed > 0 else 0.0
        parts = [f"{self.count}/{self.total} {self.unit} ({self.count / self.total:.1%})" if self.total
                 else f"{self.count} {self.unit}", f"{rate:.3g} {self.unit}/s", f"elapsed {format_duration(elapsed)}"]
        if self.total and self.count < self.total:
            parts.append(f"ETA {format_duration((self.total - self.count) / rate) if rate > 0 else '?'}")
        if self.postfix:
            parts.append(self.postfix)
        return f"{self.desc}: {', '.join(parts)}"

    def print_line(self, now: float) -> None:
        print(self.line(now), file=self.file, flush=True)
        self.printed = True

    def close(self) -> None:
        """Say how it ended, if anything was said while it ran (short work stays silent)."""
        if self.printed:
            elapsed = self.clock() - self.start
            rate = (self.count - self.initial) / elapsed if elapsed > 0 else 0.0
            print(f"{self.desc}: {self.count} {self.unit} done in {format_duration(elapsed)} ({rate:.3g} {self.unit}/s)",
                  file=self.file, flush=True)
            self.printed = False


def progress_bar(iterable: Optional[Iterable[Any]] = None, *, total: Optional[int] = None, desc: str, unit: str = "it",
             initial: int = 0, enabled: bool = True, leave: bool = True) -> Any:
    """A tqdm bar when stderr is a terminal (and tqdm is installed), else a `LineProgress`; silent when not
    ``enabled`` (another process reports, or the caller asked for no progress)."""
    if enabled and sys.stderr.isatty():
        try:
            from tqdm import tqdm

            return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, file=sys.stderr, leave=leave)
        except ImportError:  # a runtime-only install has no tqdm: lines instead
            pass
    return LineProgress(iterable, total, desc, unit, initial, interval=None if enabled else math.inf)
