"""Image discovery and the resumable label store.

Layout of a label folder::

    LABELS/store.json            format, teacher, adaptation settings (fixed at the first run)
    LABELS/items/<sha256>.npz    keypoints [N, 2] (x, y) and scores [N] of one image, named by the
                                 SHA-256 of the image file, so renamed or moved images still match
    LABELS/index.json            relative path -> SHA-256 of every image labelled so far

Every file is written to a temp name and renamed, so an interrupted run leaves only whole labels and a
rerun skips the images already done.
"""
from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import ToolkitError
from vo_runtime.atomic_file import write_atomic  # noqa: F401 (the store's writer; run_log and trainer use it)
from vo_runtime.errors import first_line
from vo_runtime.image_decode import decode_image

STORE_FORMAT = "edgefeat-labels/1"
# What a truncated or garbled .npz raises on opening or reading a member.
UNREADABLE_NPZ = (OSError, ValueError, EOFError, zipfile.BadZipFile)
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
# How images are brought to the label size; part of the settings because it changes coordinates.
PREPROCESS = "gray/center-crop-to-aspect/resize-area"


@dataclass
class ImageRecord:
    path: Path
    relative: str
    sha256: str
    gray: np.ndarray  # [H, W] float32 in [0, 1] at the label size


def find_images(folder: str | Path) -> list[Path]:
    """Image files under ``folder`` (recursive, sorted). Raises ToolkitError for a missing folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ToolkitError(f"image folder not found: {folder}")
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def to_label_size(gray: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Centre-crop [H, W] uint8 to the aspect of ``size`` = (height, width), resize; float32 in [0, 1]."""
    height, width = gray.shape
    target_h, target_w = size
    if height * target_w > width * target_h:  # too tall: crop rows
        crop = round(width * target_h / target_w)
        top = (height - crop) // 2
        gray = gray[top : top + crop]
    else:
        crop = round(height * target_w / target_h)
        left = (width - crop) // 2
        gray = gray[:, left : left + crop]
    resized = cv2.resize(gray, (target_w, target_h), interpolation=cv2.INTER_AREA)
    return resized.astype(np.float32) / 255.0


def read_image(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, str] | None:
    """(gray [H, W] float32 at ``size``, sha256 of the file) or None when the file cannot be decoded."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    gray, _native = decode_image(data, cv2.IMREAD_GRAYSCALE)  # an unreadable image is counted and skipped
    if gray is None or min(gray.shape) < 8:
        return None
    return to_label_size(gray, size), hashlib.sha256(data).hexdigest()


def hash_file(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _describe_difference(old: dict, new: dict, prefix: str = "") -> str:
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            found = _describe_difference(a, b, f"{prefix}{key}.")
            if found:
                return found
        elif a != b:
            return f"{prefix}{key}: {a} vs {b}"
    return ""


class LabelStore:
    """A label folder bound to one teacher and one settings dict."""

    def __init__(self, root: Path, teacher: str, settings: dict) -> None:
        self.root = Path(root)
        self.teacher = teacher
        self.settings = settings
        self.index: dict[str, str] = {}

    @property
    def items(self) -> Path:
        return self.root / "items"

    @staticmethod
    def create_or_open(root: str | Path, teacher: str, settings: dict) -> "LabelStore":
        """Open ``root`` for labelling; refuses a folder made with another teacher or other settings."""
        root = Path(root)
        if (root / "store.json").exists():
            store = LabelStore.open(root)
            if store.teacher != teacher:
                raise ToolkitError(
                    f"{root} holds labels from teacher {store.teacher}, not {teacher}: use another --out folder"
                )
            difference = _describe_difference(store.settings, settings)
            if difference:
                raise ToolkitError(f"{root} holds labels made with other settings ({difference}): use another --out folder")
            return store
        if root.exists() and not root.is_dir():
            raise ToolkitError(f"--out {root} exists and is not a folder")
        if root.is_dir() and any(root.iterdir()):
            raise ToolkitError(f"--out {root} is a non-empty folder without a store.json: refusing to write into it")
        store = LabelStore(root, teacher, settings)
        header = {"format": STORE_FORMAT, "teacher": teacher, "preprocess": PREPROCESS, "settings": settings}
        write_atomic(root / "store.json", json.dumps(header, indent=2).encode())
        store.items.mkdir(parents=True, exist_ok=True)
        return store

    @staticmethod
    def open(root: str | Path) -> "LabelStore":
        """Open an existing label folder for reading. Raises ToolkitError if it is not one."""
        root = Path(root)
        try:
            header = json.loads((root / "store.json").read_text())
        except FileNotFoundError:
            raise ToolkitError(f"not a label folder (no store.json): {root}") from None
        except (OSError, ValueError) as exc:
            raise ToolkitError(f"unreadable label store {root / 'store.json'}: {exc}") from None
        if header.get("format") != STORE_FORMAT or header.get("preprocess") != PREPROCESS:
            raise ToolkitError(f"{root} is not an {STORE_FORMAT} label folder")
        store = LabelStore(root, header["teacher"], header["settings"])
        try:
            store.index = json.loads((root / "index.json").read_text())
        except FileNotFoundError:
            store.index = {}
        except (OSError, ValueError) as exc:
            raise ToolkitError(f"unreadable label index {root / 'index.json'}: {exc}") from None
        store.items.mkdir(parents=True, exist_ok=True)
        return store

    @property
    def size(self) -> tuple[int, int]:
        height, width = self.settings["size"]
        return int(height), int(width)

    def has(self, sha256: str) -> bool:
        """Whether whole labels of this image are stored: a file cut short (a disk that filled, a copy that
        stopped) counts as absent, so a resumed run labels the image again instead of training failing later."""
        wanted = ("keypoints", "scores", "descriptors") if self.descriptor_stride else ("keypoints", "scores")
        try:
            with np.load(self.items / f"{sha256}.npz") as data:
                for name in wanted:
                    data[name]  # reading checks the member's CRC
        except FileNotFoundError:
            return False
        except UNREADABLE_NPZ + (KeyError,):
            return False
        return True

    @property
    def descriptor_stride(self) -> int:
        """Resolution divisor of the stored teacher descriptor maps; 0 when the store holds none."""
        return int(self.settings.get("descriptor_stride", 0))

    def put(
        self, sha256: str, relative: str, keypoints: np.ndarray, scores: np.ndarray, descriptors: np.ndarray | None = None
    ) -> None:
        """Store one image's labels, and the teacher's descriptor map [D, h, w] when given (atomic)."""
        arrays = {"keypoints": keypoints.astype(np.float32), "scores": scores.astype(np.float32)}
        if descriptors is not None:
            arrays["descriptors"] = descriptors.astype(np.float16)
        buffer = _npz_bytes(**arrays)
        write_atomic(self.items / f"{sha256}.npz", buffer)
        self.index[relative] = sha256

    def get(self, sha256: str) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints [N, 2], scores [N]) of the image with this hash. Raises ToolkitError when absent."""
        path = self.items / f"{sha256}.npz"
        try:
            with np.load(path) as data:
                return data["keypoints"], data["scores"]
        except FileNotFoundError:
            raise ToolkitError(f"no labels for image {sha256[:12]} in {self.root}") from None
        except UNREADABLE_NPZ + (KeyError,) as exc:
            raise ToolkitError(f"corrupt label file {path}: {first_line(exc)}: label the folder again") from None

    def get_descriptors(self, sha256: str) -> np.ndarray:
        """The teacher's descriptor map [D, H/stride, W/stride] float16 of one image.

        Raises:
            ToolkitError: absent, or the store was made without ``--descriptors``.
        """
        path = self.items / f"{sha256}.npz"
        try:
            with np.load(path) as data:
                return data["descriptors"]
        except KeyError:
            raise ToolkitError(
                f"{self.root} holds no teacher descriptors: label with `toolkit label --descriptors` for the distill recipe"
            ) from None
        except FileNotFoundError:
            raise ToolkitError(f"no labels for image {sha256[:12]} in {self.root}") from None
        except UNREADABLE_NPZ as exc:
            raise ToolkitError(f"corrupt label file {path}: {first_line(exc)}: label the folder again") from None

    def save_index(self) -> None:
        write_atomic(self.root / "index.json", json.dumps(self.index, indent=1, sort_keys=True).encode())


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()
