"""Output locations: where a command may write, what ``--force`` may replace, and writing all at once.

The rule every command follows: an output directory is created, or it is empty, or it holds what the same
command wrote before (recognised by that command's manifest or report) and nothing else; only then, and only
with ``--force`` where the command has it, is it replaced. Anything else is refused in one line, before any
work, and left exactly as it was.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from vo_runtime.errors import VORuntimeError

ErrorType = Callable[[str], Exception]


@dataclass(frozen=True)
class OutputKind:
    """What one command writes into its output directory, so it can recognise its own earlier output."""

    description: str                    # "an artefact written by toolkit export"
    is_own: Callable[[Path], bool]      # the directory carries the command's manifest or report marker
    owns_name: Callable[[str], bool]    # a file name the command writes there


def check_output_location(path: str | Path, error: ErrorType = VORuntimeError) -> None:
    """Refuse an output below a regular file (``-o /etc/passwd/x``) or in a directory nobody can write to."""
    path = Path(path)
    ancestor = path.absolute().parent
    while not ancestor.exists() and not ancestor.is_symlink():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise error(f"cannot write {path}: {ancestor} is a file, not a directory")
    try:
        with tempfile.TemporaryFile(dir=ancestor):  # a real write: permission bits lie to root and on read-only mounts
            pass
    except OSError:
        raise error(f"cannot write {path}: {ancestor} is not writable") from None


def check_replaceable(path: str | Path, kind: OutputKind, force: bool, error: ErrorType = VORuntimeError) -> None:
    """Raise ``error`` unless ``path`` may become the output: absent, empty, or ``kind``'s own output with ``force``."""
    path = Path(path)
    check_output_location(path, error)
    if path.is_symlink() and not path.exists():
        raise error(f"{path} is a broken symbolic link")
    if not path.exists():
        return
    if not path.is_dir():
        raise error(f"{path} exists and is not a directory")
    names = sorted(entry.name for entry in path.iterdir())
    if not names:
        return
    if not kind.is_own(path):
        raise error(f"{path} is not empty and is not {kind.description}: refusing to overwrite it")
    foreign = [name for name in names if not kind.owns_name(name)]
    if foreign:
        raise error(f"{path} also holds files that are not part of {kind.description} ({', '.join(foreign[:3])}"
                    f"{', ...' if len(foreign) > 3 else ''}): refusing to overwrite it")
    if not force:
        raise error(f"{path} already holds {kind.description}; pass --force to replace it")


def _apply_umask(directory: Path) -> None:
    """mkdtemp makes a private 0700 directory; give it the permissions a plain mkdir would."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(directory, 0o777 & ~umask)


@contextmanager
def atomic_directory(output: str | Path) -> Iterator[Path]:
    """Yield a staging directory beside ``output``; on success it replaces ``output``, on error it vanishes.

    An existing ``output`` is moved aside first and deleted only after the new one is in place. Callers
    check with `check_replaceable` first: this replaces whatever is there.
    """
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.tmp-", dir=output.parent))
    try:
        yield staging
        _apply_umask(staging)
        retired = None
        if output.exists():
            retired = Path(tempfile.mkdtemp(prefix=f".{output.name}.old-", dir=output.parent))
            os.rename(output, retired / output.name)
        os.rename(staging, output)
        if retired is not None:
            shutil.rmtree(retired, ignore_errors=True)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
