"""The source frames of `toolkit eval synth`: found in any folders of images, identified by content, picked
evenly.

Frames are found recursively (KITTI ``image_0/``, TUM ``rgb/``, EuRoC ``mav0/cam0/data/`` alike) and put in an
order that depends on the images alone, not on the order the folders were given or the file system lists
them: by the name of the folder given and the path below it (so the frames of a video stay in time order and
picks spread over it), ties broken by content. A frame that is byte for byte another is kept once.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from toolkit.errors import ToolkitError

FRAME_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".bmp")
# (kind index, kinds): the pick of a kind is offset inside each stride, so kinds use different frames while
# there are enough; the index is fixed per kind, so `--kinds darkness` alone picks what a full run picks.
KIND_COUNT = 2


@dataclass(frozen=True)
class Frame:
    """One source image: ``path`` on disk, ``key`` (``<folder given>/<path below it>``, the sort order) and
    ``sha256`` of its bytes (its identity: names and seeds of its sequences derive from it)."""

    path: Path
    key: str
    sha256: str


def _walk_error(error: OSError) -> None:
    raise ToolkitError(f"cannot read the image folder {error.filename} ({error.strerror or error})")


def _image_files(root: Path) -> list[Path]:
    """Image files below ``root`` (links to folders not followed), in no particular order."""
    found = []
    for directory, _, files in os.walk(root, onerror=_walk_error):
        found += [Path(directory) / name for name in files if Path(name).suffix.lower() in FRAME_EXTENSIONS]
    return found


def _content_hash(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ToolkitError(f"cannot read the image {path} ({exc.strerror or exc})") from None


def find_frames(folders: list[Path]) -> list[Frame]:
    """Every distinct image below ``folders``, in the order of the module doc.

    Raises `ToolkitError` for a folder that is missing, not a folder or unreadable, and when none holds an image.
    """
    frames: dict[str, Frame] = {}
    for root in folders:
        if not root.is_dir():
            raise ToolkitError(f"--images {root}: {'not a directory' if root.exists() else 'no such directory'}")
        name = root.resolve().name
        for path in _image_files(root):
            frame = Frame(path, f"{name}/{path.relative_to(root).as_posix()}", _content_hash(path))
            kept = frames.get(frame.sha256)
            if kept is None or (frame.key, str(frame.path)) < (kept.key, str(kept.path)):
                frames[frame.sha256] = frame
    if not frames:
        raise ToolkitError(f"no images ({', '.join(FRAME_EXTENSIONS)}) found below "
                           f"{', '.join(str(f) for f in folders)}")
    return sorted(frames.values(), key=lambda f: (f.key, f.sha256))


def pick_frames(frames: list[Frame], count: int, kind_index: int) -> list[tuple[Frame, int]]:
    """``count`` (frame, repeat) picks for the kind ``kind_index``, evenly spread over ``frames``.

    Pick i takes the frame at ``floor((i + (kind_index + 0.5) / KIND_COUNT) * len(frames) / count)``: one
    frame per stride of ``len(frames) / count`` frames, the kinds at different places in the stride. With fewer
    frames than picks a frame is picked again; ``repeat`` counts its earlier picks (0 the first time), which
    gives the repeat its own seed and name.
    """
    offset = (kind_index + 0.5) / KIND_COUNT
    picks: list[tuple[Frame, int]] = []
    seen: dict[int, int] = {}
    for i in range(count):
        index = min(int((i + offset) * len(frames) / count), len(frames) - 1)
        picks.append((frames[index], seen.get(index, 0)))
        seen[index] = seen.get(index, 0) + 1
    return picks
