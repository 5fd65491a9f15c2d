"""Frame timestamps: finite numbers, strictly increasing. A NaN stamp made a trajectory of NaN stamps, and a
repeated one made the evaluation's association fail at the very end ("degenerate covariance"), so a bad stamp
is refused where it enters, naming its source: a file when a sequence is opened, the call in the API."""
from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from vo_runtime.errors import TimestampError


def is_real_number(value: object) -> bool:
    """int, float or a numpy number, but not a bool (True is no timestamp)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def checked_timestamp(value: object, previous: Optional[float], source: str = "timestamp") -> Optional[float]:
    """``value`` as a float (None stays None), after checking it is finite and comes after ``previous``."""
    if value is None:
        return None
    if not is_real_number(value):
        raise TimestampError(f"{source} must be a number or None, got {value!r}")
    stamp = float(value)
    if not math.isfinite(stamp):
        raise TimestampError(f"{source} must be finite, got {stamp}")
    if previous is not None and stamp <= previous:
        raise TimestampError(f"{source} {stamp!r} does not come after the previous frame's {previous!r}: "
                             "timestamps must increase")
    return stamp


def check_timestamps(stamps: Sequence[float], source: str) -> None:
    """Every stamp of a sequence finite and each after the one before (``source`` names where they came from)."""
    values = np.asarray(stamps, np.float64)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise TimestampError(f"{source}: timestamp {bad[0] + 1} is {float(values[bad[0]])}, not a finite number")
    steps = np.flatnonzero(np.diff(values) <= 0)
    if steps.size:
        index = int(steps[0])
        what = "repeats" if values[index + 1] == values[index] else "goes back from"
        raise TimestampError(f"{source}: timestamp {index + 2} ({float(values[index + 1])!r}) {what} "
                             f"{float(values[index])!r}: timestamps must increase")


def nearest_samples(sample_times: np.ndarray, wanted: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``wanted``, the index of the nearest of ``sample_times`` (sorted, at least two) and how far it
    is (seconds): how a frame finds its pose in a denser ground-truth stream."""
    wanted = np.asarray(wanted, np.float64)
    after = np.clip(np.searchsorted(sample_times, wanted), 1, len(sample_times) - 1)
    nearest = np.where(np.abs(sample_times[after - 1] - wanted) <= np.abs(sample_times[after] - wanted), after - 1, after)
    return nearest, np.abs(sample_times[nearest] - wanted)
