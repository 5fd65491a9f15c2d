"""What this machine has to give: CPU cores, the bound for every thread-count option (a --threads of 100000
made onnxruntime and torch start thread pools until memory ran out instead of failing), and its memory."""
from __future__ import annotations

import os
from typing import Callable

from vo_runtime.errors import VORuntimeError


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one, e.g. under taskset or a cgroup)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS and Windows have no affinity call
        return max(1, os.cpu_count() or 1)


def check_thread_count(value: object, option: str, error: Callable[[str], Exception] = VORuntimeError,
                       allow_zero: bool = False) -> int:
    """``value`` as a thread count from 1 (0 too with ``allow_zero``: the library's choice) to the cores there
    are: more threads than cores only queue behind each other."""
    low = 0 if allow_zero else 1
    cores = available_cores()
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise error(f"{option} must be a whole number of at least {low}, got {value!r}")
    if value > cores:
        raise error(f"{option} {value} is more than the {cores} CPU core(s) this process can use; use at most {cores}")
    return value


def physical_memory_bytes() -> int | None:
    """The machine's RAM in bytes, or None where the OS does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return None
