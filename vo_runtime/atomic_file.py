"""Writing one file all at once: a temporary sibling, then a rename, so a reader (or a crash) never meets half a
file. The folder-sized counterpart, with the output lock and ``--force`` rules, is `vo_runtime.outputs`."""
from __future__ import annotations

import json
import math
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for a writer that takes a file name (safetensors, savefig); when
    the body succeeds it replaces ``path``, otherwise it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(handle)
    try:
        yield Path(temporary)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary sibling and a rename."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data)


def write_json_atomic(path: str | Path, data: Any) -> None:
    """``data`` as strict JSON (NaN and infinities refused: they are no JSON), written with `write_atomic`."""
    write_atomic(path, (json.dumps(data, indent=2, allow_nan=False) + "\n").encode("utf-8"))


def nan_as_null(data: Any) -> Any:
    """``data`` with every NaN or infinite float replaced by None: for reports where such a value means "not
    measured" (a loss before the first step), written as JSON null rather than as invalid JSON."""
    if isinstance(data, dict):
        return {key: nan_as_null(value) for key, value in data.items()}
    if isinstance(data, (list, tuple)):
        return [nan_as_null(value) for value in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data
