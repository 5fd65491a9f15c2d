"""Output locations: where a command may write, what ``--force`` may replace, and writing all at once.

The rule every command follows (`claim_output`): an output folder is created, or it is empty, or it holds what
the same command wrote before (its listing, `vo_runtime.output_listing`, holds every file there, unchanged)
and nothing else; only then, and only with ``--force`` where the command has it, is it replaced. Anything else
is refused in one line, before any work, and left exactly as it was. The claim holds the output's lock
(`vo_runtime.output_lock`) until the command ends, so a second run at the same output is refused, and the
final swap re-checks that the output is still what was checked: a file the user put there meanwhile is kept
and the command fails instead of replacing it.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, List, Optional

from vo_runtime.errors import VORuntimeError
from vo_runtime.output_listing import fingerprint, foreign_entries, read_listing, write_listing
from vo_runtime.output_lock import RETIRED_MARK, STAGING_MARK, hidden_prefix, output_lock, recover_after_killed_run

ErrorType = Callable[[str], Exception]


@dataclass(frozen=True)
class OutputKind:
    """One command's kind of output folder: ``name`` is recorded in the folder's listing, ``description`` is
    what messages call it ("an artefact written by toolkit export")."""

    name: str
    description: str


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


def check_outside_inputs(path: str | Path, inputs: Iterable[Optional[Path]], error: ErrorType = VORuntimeError) -> None:
    """Refuse an output that is an input, lies inside one (``-o art/int8`` of ``--artefact art``) or holds one:
    writing there would change what was read, or block replacing the input later."""
    output = os.path.realpath(path)
    for given in inputs:
        if given is None:
            continue
        source = os.path.realpath(given)
        if output == source:
            raise error(f"-o {path} is the input {given}: write the output somewhere else")
        if output.startswith(source.rstrip(os.sep) + os.sep):
            raise error(f"-o {path} is inside the input {given}: write the output somewhere else")
        if source.startswith(output.rstrip(os.sep) + os.sep):
            raise error(f"-o {path} holds the input {given}: write the output somewhere else")


def check_replaceable(path: str | Path, kind: OutputKind, force: bool,
                      error: ErrorType = VORuntimeError) -> Optional[tuple]:
    """Raise ``error`` unless ``path`` may become ``kind``'s output: absent, an empty folder, or with ``force``
    a folder holding exactly what ``kind`` recorded it wrote there. Returns the `fingerprint` of what is there."""
    path = Path(path)
    check_output_location(path, error)
    found = fingerprint(path)
    if found is None:
        return None
    if path.is_symlink():
        raise error(f"{path} is a symbolic link: name the folder itself")
    if not path.is_dir():
        raise error(f"{path} exists and is not a directory")
    if not any(path.iterdir()):
        return found
    listing = read_listing(path)
    if listing is None or listing["kind"] != kind.name:
        raise error(f"{path} is not empty and is not {kind.description}: refusing to overwrite it")
    foreign = foreign_entries(path, listing)
    if foreign:
        raise error(f"{path} also holds files that are not part of {kind.description} or were changed since "
                    f"({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}): refusing to overwrite it")
    if not force:
        raise error(f"{path} already holds {kind.description}; pass --force to replace it")
    return found


def _apply_umask(directory: Path) -> None:
    """mkdtemp makes a private 0700 directory; give it the permissions a plain mkdir would."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(directory, 0o777 & ~umask)


def _make_parents(path: Path) -> List[Path]:
    """Create the missing parent folders of ``path``; return those created, deepest first."""
    created = []
    ancestor = path.absolute().parent
    while not ancestor.exists():
        created.append(ancestor)
        ancestor = ancestor.parent
    path.absolute().parent.mkdir(parents=True, exist_ok=True)
    return created


class OutputClaim:
    """A checked, locked output: `writing` stages a new folder and swaps it in if the output is unchanged."""

    def __init__(self, path: Path, kind: OutputKind, found: Any, error: ErrorType) -> None:
        self.path, self.kind, self.found, self.error = path, kind, found, error

    def _changed(self) -> Exception:
        return self.error(f"{self.path} changed while this command ran (something else wrote there): it was left "
                          "as it is and nothing was written")

    @contextmanager
    def writing(self) -> Iterator[Path]:
        """Yield a staging folder beside the output; when the body succeeds it becomes the output."""
        staging = Path(tempfile.mkdtemp(prefix=hidden_prefix(self.path, STAGING_MARK), dir=self.path.parent))
        try:
            yield staging
            write_listing(staging, self.kind.name)
            _apply_umask(staging)
            self._swap(staging)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)

    def _swap(self, staging: Path) -> None:
        if fingerprint(self.path) != self.found:
            raise self._changed()
        if self.found is None:
            try:  # fails on a file or a non-empty folder that appeared since the check above
                os.rename(staging, self.path)
            except OSError:
                raise self._changed() from None
            return
        retired = Path(tempfile.mkdtemp(prefix=hidden_prefix(self.path, RETIRED_MARK), dir=self.path.parent))
        moved = retired / self.path.name
        os.rename(self.path, moved)
        if _contents(fingerprint(moved)) != _contents(self.found):  # changed between the check and the move
            os.rename(moved, self.path)
            os.rmdir(retired)
            raise self._changed()
        try:
            os.rename(staging, self.path)
        except OSError:
            os.rename(moved, self.path)
            os.rmdir(retired)
            raise self._changed() from None
        shutil.rmtree(retired, ignore_errors=True)


def _contents(found: Any) -> Any:
    """A folder's fingerprint without its inode line, which a rename keeps but some filesystems do not."""
    return found[2] if isinstance(found, tuple) and found and found[0] == "dir" else found


@contextmanager
def locked_output(path: str | Path, error: ErrorType = VORuntimeError) -> Iterator[None]:
    """Hold the lock of ``path`` for the body, for writers that fill their output in place (label, train) and
    for `claim_output`: a second run at the same output is refused. Folders made above ``path`` for the lock
    are removed again when they stay empty."""
    path = Path(path)
    check_output_location(path, error)
    created = _make_parents(path)
    try:
        with output_lock(path, error):
            yield
    finally:
        for folder in created:
            try:
                folder.rmdir()
            except OSError:  # not empty: the output (or something else) lives there now
                break


@contextmanager
def claim_output(path: str | Path, kind: OutputKind, force: bool, inputs: Iterable[Optional[Path]] = (),
                 error: ErrorType = VORuntimeError) -> Iterator[OutputClaim]:
    """Check ``path`` as `check_replaceable` does and hold its lock for the body (see the module doc)."""
    path = Path(path)
    check_output_location(path, error)
    check_outside_inputs(path, inputs, error)
    with locked_output(path, error):
        recover_after_killed_run(path)
        yield OutputClaim(path, kind, check_replaceable(path, kind, force, error), error)


class FilesClaim:
    """Single-file outputs (a checkpoint and its report) under one lock: `check_unchanged` before writing
    refuses when any of them changed since the claim began."""

    def __init__(self, paths: List[Path], error: ErrorType) -> None:
        self.paths, self.error = paths, error
        self.found = [fingerprint(path) for path in paths]

    def check_unchanged(self) -> None:
        for path, found in zip(self.paths, self.found):
            if fingerprint(path) != found:
                raise self.error(f"{path} changed while this command ran (something else wrote there): it was "
                                 "left as it is and nothing was written")


@contextmanager
def claim_files(paths: Iterable[str | Path], error: ErrorType = VORuntimeError) -> Iterator[FilesClaim]:
    """Hold the lock of the first of ``paths`` (the one every writer of this set takes) for the body."""
    paths = [Path(path) for path in paths]
    with locked_output(paths[0], error):
        yield FilesClaim(paths, error)
