"""Writing output directories all at once: readers see the old directory or the new one, never half of one."""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _apply_umask(directory: Path) -> None:
    """mkdtemp makes a private 0700 directory; give it the permissions a plain mkdir would."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(directory, 0o777 & ~umask)


@contextmanager
def atomic_directory(output: str | Path) -> Iterator[Path]:
    """Yield a staging directory beside ``output``; on success it replaces ``output``, on error it vanishes.

    An existing ``output`` is moved aside first and deleted only after the new one is in place.
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
