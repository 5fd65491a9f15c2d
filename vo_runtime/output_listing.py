"""What a command wrote into an output folder, recorded there so ``--force`` can tell its files from the user's.

Every output folder written through `vo_runtime.outputs` carries a listing (`LISTING_NAME`): the kind of output
and, per regular file it wrote, the size and sha256. Ownership comes only from that record, never from names:
a folder named like one of our files, a file the listing does not hold, or a listed file that was changed
since is the user's, and its presence makes the whole folder not ours to replace.
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from vo_runtime.artefact import sha256_file

LISTING_NAME = ".edgefeat-output.json"
LISTING_FORMAT = "edgefeat-output/1"

# (relative path, "file" / "dir" / "link" / "other", inode, size, mtime in ns) per entry below a folder.
Entry = Tuple[str, str, int, int, int]


def _kind_of(stat_mode: int) -> str:
    if stat.S_ISLNK(stat_mode):
        return "link"
    if stat.S_ISDIR(stat_mode):
        return "dir"
    return "file" if stat.S_ISREG(stat_mode) else "other"


def tree_entries(root: Path) -> List[Entry]:
    """Every entry below ``root`` (links not followed), sorted: what the folder holds, as the disk says."""
    entries: List[Entry] = []
    for directory, folders, files in os.walk(root, followlinks=False):
        for name in folders + files:
            path = Path(directory) / name
            status = path.lstat()
            entries.append((path.relative_to(root).as_posix(), _kind_of(status.st_mode), status.st_ino,
                            status.st_size, status.st_mtime_ns))
    return sorted(entries)


def fingerprint(path: Path) -> Optional[Tuple[Any, ...]]:
    """What is at ``path`` now (None: nothing), compared before the final swap to notice any change since the
    check. A folder's own times are left out: moving it aside changes them, its contents do not."""
    try:
        status = path.lstat()
    except FileNotFoundError:
        return None
    kind = _kind_of(status.st_mode)
    if kind != "dir":
        return (kind, status.st_ino, status.st_size, status.st_mtime_ns)
    return ("dir", status.st_ino, tuple(tree_entries(path)))


def write_listing(folder: Path, kind: str) -> None:
    """Record every regular file under ``folder`` (written by one command of ``kind``) in its listing."""
    files: Dict[str, Dict[str, Any]] = {}
    for relative, entry_kind, _inode, size, _mtime in tree_entries(folder):
        if entry_kind == "file" and relative != LISTING_NAME:
            files[relative] = {"size": size, "sha256": sha256_file(folder / relative)}
    text = json.dumps({"format": LISTING_FORMAT, "kind": kind, "files": files}, indent=1) + "\n"
    (folder / LISTING_NAME).write_text(text, encoding="utf-8")


def read_listing(folder: Path) -> Optional[Dict[str, Any]]:
    """The listing of ``folder``, or None when it has none that is readable (then nothing there is ours)."""
    path = folder / LISTING_NAME
    if path.is_symlink() or not path.is_file():
        return None
    try:
        listing = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return None
    ok = (isinstance(listing, dict) and listing.get("format") == LISTING_FORMAT and isinstance(listing.get("kind"), str)
          and isinstance(listing.get("files"), dict))
    return listing if ok else None


def foreign_entries(folder: Path, listing: Dict[str, Any]) -> List[str]:
    """Entries of ``folder`` that are not what ``listing`` says the command wrote: anything but a regular file
    it holds with the recorded size and checksum (folders only as the parents of such files)."""
    recorded = listing["files"]
    parents = {Path(name).parent.as_posix() for name in recorded}
    parents = {p for name in parents for p in _with_ancestors(name)}
    foreign = []
    for relative, kind, _inode, size, _mtime in tree_entries(folder):
        if relative == LISTING_NAME and kind == "file":
            continue
        if kind == "dir" and relative in parents:
            continue
        entry = recorded.get(relative)
        if kind == "file" and isinstance(entry, dict) and entry.get("size") == size \
                and entry.get("sha256") == sha256_file(folder / relative):
            continue
        foreign.append(relative if kind != "dir" else relative + "/")
    return foreign


def _with_ancestors(relative: str) -> List[str]:
    """'a/b/c' -> ['a/b/c', 'a/b', 'a'] ('.' -> [])."""
    parts = [] if relative == "." else relative.split("/")
    return ["/".join(parts[:end]) for end in range(len(parts), 0, -1)]
