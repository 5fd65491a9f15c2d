"""One writer per output path: a lock beside the output, held from the first check to the final swap.

The lock is an ``flock`` on a hidden file next to the output (`lock_path`), so the kernel releases it when its
holder dies, even by ``kill -9``: a later run is never blocked by a dead one. Holding it also proves that no
live run owns the staging folders left beside the output (`STAGING_MARK`, `RETIRED_MARK`), so the holder
clears those a killed run left behind, and first puts back an earlier output that a run killed mid-swap had
moved aside.
"""
from __future__ import annotations

import errno
import fcntl
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

ErrorType = Callable[[str], Exception]

STAGING_MARK = "tmp"    # .<name>.tmp-XXXX: a new output being written
RETIRED_MARK = "old"    # .<name>.old-XXXX/<name>: the output being replaced, moved aside during the swap


def lock_path(output: Path) -> Path:
    return output.parent / f".{output.name}.lock"


def hidden_prefix(output: Path, mark: str) -> str:
    """The name prefix of the hidden ``mark`` folders of ``output`` (its staging and retired folders)."""
    return f".{output.name}.{mark}-"


def _holder(path: Path) -> str:
    try:
        pid = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return "another run"
    return f"another run (process {pid})" if pid.isdigit() else "another run"


def _locked_descriptor(path: Path, output: Path, error: ErrorType) -> int:
    """An open, exclusively locked descriptor of ``path``; ``error`` if another process holds the lock."""
    while True:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(descriptor)
            if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            raise error(f"{output} is being written by {_holder(path)}: wait for it to finish or choose another "
                        "output") from None
        try:  # the previous holder unlinks the file as it lets go: a lock on that old file locks nothing
            if os.stat(path).st_ino == os.fstat(descriptor).st_ino:
                return descriptor
        except FileNotFoundError:
            pass
        os.close(descriptor)


@contextmanager
def output_lock(output: Path, error: ErrorType) -> Iterator[None]:
    """Hold the lock of ``output`` (whose parent folder exists) for the body; ``error`` if another run holds it."""
    path = lock_path(output)
    descriptor = _locked_descriptor(path, output, error)
    try:
        os.truncate(descriptor, 0)
        os.write(descriptor, str(os.getpid()).encode("ascii"))
        yield
    finally:
        try:
            os.unlink(path)  # unlinked while still held, so a waiting run re-opens a fresh file (see above)
        finally:
            os.close(descriptor)


def recover_after_killed_run(output: Path) -> None:
    """Under the lock: put back an output a killed run had moved aside and not replaced, then remove every
    staging and retired folder of ``output`` (no live run owns them while we hold the lock)."""
    parent = output.parent
    retired = sorted(parent.glob(hidden_prefix(output, RETIRED_MARK) + "*"))
    if not os.path.lexists(output):
        for folder in retired:
            moved = folder / output.name
            if os.path.lexists(moved):
                os.rename(moved, output)
                break
    for folder in retired + sorted(parent.glob(hidden_prefix(output, STAGING_MARK) + "*")):
        if folder.is_dir() and not folder.is_symlink():
            shutil.rmtree(folder, ignore_errors=True)
