"""Output folders for the toolkit's commands: the shared rules of `vo_runtime.outputs`, raising `ToolkitError`
(see that module for the lock, the listing ``--force`` trusts, and the re-checked final swap)."""
from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path
from typing import Iterable

from toolkit.errors import ToolkitError
from vo_runtime.outputs import (FilesClaim, OutputClaim, OutputKind, check_output_location, claim_files, claim_output,
                                locked_output)

__all__ = ["FilesClaim", "OutputClaim", "OutputKind", "check_output_path", "claim_output_dir", "claim_output_files",
           "locked_output_dir"]


def check_output_path(path: str | Path) -> None:
    """`ToolkitError` for an output below a regular file or in an unwritable directory."""
    check_output_location(path, ToolkitError)


def claim_output_dir(path: str | Path, kind: OutputKind, force: bool,
                     inputs: Iterable[Path | None] = ()) -> AbstractContextManager[OutputClaim]:
    """`vo_runtime.outputs.claim_output` with `ToolkitError` for every refusal."""
    return claim_output(path, kind, force, inputs, ToolkitError)


def locked_output_dir(path: str | Path) -> AbstractContextManager[None]:
    """`vo_runtime.outputs.locked_output` with `ToolkitError`: one writer at a time for a folder filled in place."""
    return locked_output(path, ToolkitError)


def claim_output_files(paths: Iterable[str | Path]) -> AbstractContextManager[FilesClaim]:
    """`vo_runtime.outputs.claim_files` with `ToolkitError`: single-file outputs under one lock, re-checked."""
    return claim_files(paths, ToolkitError)
