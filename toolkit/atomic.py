"""Output directories for the toolkit's commands: the shared rules of `vo_runtime.outputs`, raising
`ToolkitError` (see that module for what ``--force`` may replace)."""
from __future__ import annotations

from pathlib import Path

from toolkit.errors import ToolkitError
from vo_runtime.outputs import OutputKind, atomic_directory, check_output_location, check_replaceable

__all__ = ["OutputKind", "atomic_directory", "check_output_path", "check_output_dir"]


def check_output_path(path: str | Path) -> None:
    """`ToolkitError` for an output below a regular file or in an unwritable directory."""
    check_output_location(path, ToolkitError)


def check_output_dir(path: str | Path, kind: OutputKind, force: bool) -> None:
    """`ToolkitError` unless ``path`` is absent, empty, or ``kind``'s own earlier output and ``force`` is set."""
    check_replaceable(path, kind, force, ToolkitError)
