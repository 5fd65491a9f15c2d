"""Readers for the two evaluation layouts: HPatches sequences and registered image pairs.

HPatches layout (one or many sequence folders under ``--data``)::

    <seq>/1.ppm .. <seq>/6.ppm      reference image 1 and five target images
    <seq>/H_1_k                     3x3 homography, text, mapping pixels of image 1 to image k

Registered-pairs layout (e.g. ``lowlight_pairs``)::

    low/<n>.png, high/<n>.png       the same view under two conditions
    homographies/<n>.txt            optional 3x3 homography low -> high; the identity when absent

All homographies map pixel coordinates of the first image to the second (``x_b ~ H [x_a, y_a, 1]^T``),
pixel centres at integers (OpenCV's convention).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import ToolkitError
from toolkit.sizes import MAX_SIDE, MIN_SIDE, parse_hxw
from vo_runtime.image_decode import decode_image, decode_problem

HPATCHES_IMAGE_EXTENSIONS = (".ppm", ".png", ".jpg")
PAIR_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".ppm", ".bmp")


@dataclass(frozen=True)
class ImagePair:
    """One evaluation pair: image ``path_a`` is mapped onto ``path_b`` by ``homography`` (3x3, float64).

    ``group`` is ``"i"`` (illumination), ``"v"`` (viewpoint), ``"dark"`` (synthetic darkness), ``"other"`` or
    ``"pairs"``; ``name`` is unique in a dataset.
    """

    name: str
    group: str
    path_a: Path
    path_b: Path
    homography: np.ndarray


def parse_homography_file(path: str | Path) -> np.ndarray:
    """Read a text file of 9 numbers (3 rows of 3) into a 3x3 float64 matrix.

    Raises `ToolkitError` if the file is missing, has another count of numbers, non-numbers,
    non-finite values, or a singular matrix.
    """
    path = Path(path)
    if not path.is_file():
        raise ToolkitError(f"homography file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ToolkitError(f"cannot read homography file {path} ({exc})") from None
    tokens = text.replace(",", " ").split()
    try:
        values = np.array([float(token) for token in tokens], dtype=np.float64)
    except ValueError:
        raise ToolkitError(f"malformed homography file {path}: expected 9 numbers (3x3)") from None
    if values.size != 9:
        raise ToolkitError(f"malformed homography file {path}: expected 9 numbers (3x3), found {values.size}")
    matrix = values.reshape(3, 3)
    if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix)) < 1e-12:
        raise ToolkitError(f"malformed homography file {path}: the matrix is not finite and invertible")
    return matrix / matrix[2, 2] if abs(matrix[2, 2]) > 1e-12 else matrix


def _find_image(folder: Path, stem: str, extensions: tuple[str, ...]) -> Path | None:
    for extension in extensions:
        candidate = folder / f"{stem}{extension}"
        if candidate.is_file():
            return candidate
    return None


def _sequence_group(name: str) -> str:
    """HPatches' ``i_`` and ``v_`` groups, and ``dark_`` (the darkness sequences `toolkit eval synth` writes)."""
    for prefix in ("i", "v", "dark"):
        if name.startswith(prefix + "_"):
            return prefix
    return "other"


def _is_hpatches_sequence(folder: Path) -> bool:
    return _find_image(folder, "1", HPATCHES_IMAGE_EXTENSIONS) is not None or any(folder.glob("H_1_*"))


def read_hpatches_sequence(folder: Path) -> list[ImagePair]:
    """Pairs (1, k) of one HPatches sequence folder, k = 2.. in order. Raises `ToolkitError` on gaps."""
    reference = _find_image(folder, "1", HPATCHES_IMAGE_EXTENSIONS)
    if reference is None:
        raise ToolkitError(f"HPatches sequence {folder} has no reference image 1.ppm")
    indices = sorted(int(m.group(1)) for p in folder.glob("H_1_*") if (m := re.fullmatch(r"H_1_(\d+)", p.name)))
    if not indices:
        raise ToolkitError(f"HPatches sequence {folder} has no homography files H_1_k")
    pairs = []
    for index in indices:
        target = _find_image(folder, str(index), HPATCHES_IMAGE_EXTENSIONS)
        if target is None:
            raise ToolkitError(f"HPatches sequence {folder}: H_1_{index} exists but image {index}.ppm is missing")
        homography = parse_homography_file(folder / f"H_1_{index}")
        pairs.append(ImagePair(f"{folder.name}/1-{index}", _sequence_group(folder.name), reference, target, homography))
    return pairs


def read_hpatches(root: str | Path) -> list[ImagePair]:
    """All pairs under ``root``: ``root`` is one sequence folder or a folder of sequence folders (searched
    two levels deep, so a dataset folder holding ``hpatches-sequences-release/`` also works)."""
    root = Path(root)
    if not root.is_dir():
        raise ToolkitError(f"data directory not found: {root}")
    if _is_hpatches_sequence(root):
        return read_hpatches_sequence(root)
    sequences = sorted(p for p in root.iterdir() if p.is_dir() and _is_hpatches_sequence(p))
    if not sequences:
        sequences = sorted(p for d in root.iterdir() if d.is_dir() for p in d.iterdir()
                           if p.is_dir() and _is_hpatches_sequence(p))
    if not sequences:
        raise ToolkitError(f"no HPatches sequence folders (1.ppm + H_1_k) under {root}")
    return [pair for sequence in sequences for pair in read_hpatches_sequence(sequence)]


def read_registered_pairs(root: str | Path, first: str = "low", second: str = "high",
                          homography_dir: str = "homographies") -> list[ImagePair]:
    """Pairs ``first/<n>`` -> ``second/<n>`` under ``root``, with ``homography_dir/<n>.txt`` or the identity.

    Raises `ToolkitError` if a folder is missing, a stem has no partner, or an H file is malformed.
    """
    root = Path(root)
    if not root.is_dir():
        raise ToolkitError(f"data directory not found: {root}")
    folder_a, folder_b = root / first, root / second
    for folder in (folder_a, folder_b):
        if not folder.is_dir():
            raise ToolkitError(f"{root} is not a pairs dataset: folder {folder.name}/ is missing")
    stems = sorted({p.stem for p in folder_a.iterdir() if p.suffix.lower() in PAIR_IMAGE_EXTENSIONS},
                   key=lambda s: (len(s), s))
    if not stems:
        raise ToolkitError(f"no images in {folder_a}")
    pairs = []
    for stem in stems:
        path_a = _find_image(folder_a, stem, PAIR_IMAGE_EXTENSIONS)
        path_b = _find_image(folder_b, stem, PAIR_IMAGE_EXTENSIONS)
        if path_a is None or path_b is None:
            raise ToolkitError(f"image {stem} is in {folder_a.name}/ but not in {folder_b.name}/")
        h_file = root / homography_dir / f"{stem}.txt"
        homography = parse_homography_file(h_file) if h_file.exists() else identity_for(path_a, path_b, h_file)
        pairs.append(ImagePair(stem, "pairs", path_a, path_b, homography))
    return pairs


def identity_for(path_a: Path, path_b: Path, h_file: Path) -> np.ndarray:
    """The identity homography of a pair without an H file, which only registers two images of one size
    (metrics against the identity for differently sized images would be numbers about nothing)."""
    size_a, size_b = load_gray(path_a).shape, load_gray(path_b).shape
    if size_a != size_b:
        raise ToolkitError(f"{path_a} is {size_a[1]}x{size_a[0]} but {path_b} is {size_b[1]}x{size_b[0]}, and there "
                           f"is no {h_file} to register them: the identity fits only images of one size")
    return np.eye(3)


def load_gray(path: str | Path) -> np.ndarray:
    """Read an image file as HxW uint8 gray; raise `ToolkitError` if missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ToolkitError(f"image not found: {path}")
    image, native = decode_image(path.read_bytes(), cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ToolkitError(f"cannot decode image {path}{decode_problem(native)}")
    return image


def parse_size(text: str) -> tuple[int, int] | None:
    """``"240x320"`` -> (240, 320) as (height, width), each side within `toolkit.sizes` bounds; ``"native"`` -> None."""
    if text.strip().lower() == "native":
        return None
    try:
        return parse_hxw(text, "--size")
    except ToolkitError:
        raise ToolkitError(f"bad --size {text!r}: expected HxW such as 240x320 (each side {MIN_SIDE} to {MAX_SIDE}), "
                           "or native") from None


def resize_with_matrix(image: np.ndarray, size: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray]:
    """Resize an HxW image to ``size`` (height, width) and return the 3x3 matrix S mapping old pixels to new.

    With pixel centres at integers, ``x' = (x + 0.5) * s_x - 0.5``, which is how cv2.resize samples.
    ``size=None`` keeps the image and returns the identity.
    """
    if size is None or tuple(image.shape[:2]) == tuple(size):
        return image, np.eye(3)
    height, width = image.shape[:2]
    scale_x, scale_y = size[1] / width, size[0] / height
    shrinking = scale_x < 1.0 and scale_y < 1.0
    resized = cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    matrix = np.array([[scale_x, 0.0, 0.5 * scale_x - 0.5],
                       [0.0, scale_y, 0.5 * scale_y - 0.5],
                       [0.0, 0.0, 1.0]])
    return resized, matrix


def scale_homography(homography: np.ndarray, scale_a: np.ndarray, scale_b: np.ndarray) -> np.ndarray:
    """H' = S_b H S_a^-1: the homography between resized images (all 3x3)."""
    scaled = scale_b @ homography @ np.linalg.inv(scale_a)
    return scaled / scaled[2, 2]
