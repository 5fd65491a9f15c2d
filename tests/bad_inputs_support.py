"""Shared pieces of the bad-input matrix (tests/test_bad_inputs*.py): the user's files each case needs, a
byte-for-byte snapshot of every file a case could touch, and the one check every case must pass."""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

SHARED_DATA = (Path(__file__).resolve().parents[1] / ".." / "shared" / "data").resolve()
KITTI_06 = SHARED_DATA / "kitti_odom06_f000000-000050"
PAIRS = SHARED_DATA / "lowlight_pairs"
THESIS = b"Chapter 1. Nobody deletes this file.\n"


class PickledPayload:
    """A pickle that would create a marker file if anything ever unpickled it unsafely."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@dataclass
class Assets:
    """Built once per session, read-only for every case: a random FeatureNet checkpoint and its artefact."""

    root: Path
    checkpoint: Path
    artefact: Path


@dataclass
class Space:
    """One case's working folder, with helpers that create the user's files there on demand."""

    root: Path
    assets: Assets

    def file(self, name: str, data: bytes = b"") -> Path:
        path = self.root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return path

    def thesis(self) -> Path:
        """A folder of the user's own work: no command may ever replace it."""
        self.file("thesis/thesis.txt", THESIS)
        return self.root / "thesis"

    def below_a_file(self) -> Path:
        """An output path whose parent is a regular file (like -o /etc/passwd/x)."""
        return self.file("notes.txt", b"not a folder\n") / "x"

    def empty_pth(self) -> Path:
        return self.file("empty.pth")

    def evil_pth(self) -> Path:
        return self.file("evil.pth", pickle.dumps(PickledPayload(self.root / "PWNED")))

    def images(self, folder: str, count: int, side: int, flat: bool = False) -> Path:
        """``count`` PNGs of ``side`` px: noise, or one flat grey level."""
        directory = self._mkdir(folder)
        rng = np.random.default_rng(0)
        for index in range(count):
            image = np.full((side, side), 128, np.uint8) if flat else rng.integers(0, 256, (side, side), np.uint8)
            cv2.imwrite(str(directory / f"{index}.png"), image)
        return directory

    def corrupt_png(self, relative: str) -> Path:
        return self.file(relative, b"\x89PNG\r\n\x1a\n but the rest is not a PNG")

    def sequence(self, frames: int = 3) -> Path:
        """A KITTI-layout copy of the first frames of KITTI 06 (the user's own data)."""
        root = self._mkdir("seq")
        (root / "image_0").mkdir()
        for path in sorted((KITTI_06 / "image_0").iterdir())[:frames]:
            shutil.copy(path, root / "image_0" / path.name)
        for name in ("calib.txt", "poses.txt"):
            shutil.copy(KITTI_06 / name, root / name)
        return root

    def artefact_copy(self, extra: str | None = None) -> Path:
        copy = self.root / "art"
        shutil.copytree(self.assets.artefact, copy)
        if extra:
            (copy / extra).write_bytes(THESIS)
        return copy

    def artefact_without_sha256(self) -> Path:
        copy = self.artefact_copy()
        data = json.loads((copy / "manifest.json").read_text())
        del data["onnx"]["sha256"]
        (copy / "manifest.json").write_text(json.dumps(data))
        return copy

    def _mkdir(self, relative: str) -> Path:
        path = self.root / relative
        path.mkdir(parents=True, exist_ok=True)
        return path


def snapshot(*roots: Path) -> dict[str, str]:
    """Every path under ``roots`` -> the sha256 of its bytes ("dir" for folders): compared before and after."""
    state = {}
    for root in roots:
        for path in sorted(root.rglob("*")):
            key = str(path)
            state[key] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return state


def assert_refused(entry: Callable[[list[str]], int], argv: list[str], capsys, fragment: str,
                   *roots: Path) -> str:
    """Run a CLI ``entry`` on ``argv``: exit 2, one ``error:`` line naming ``fragment``, no traceback, and every
    file under ``roots`` (outputs and the user's files) byte for byte as it was. Returns the error line."""
    capsys.readouterr()
    before = snapshot(*roots)
    code = entry([str(arg) for arg in argv])
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and "Warning" not in err and "[ERROR" not in err, err
    assert fragment in lines[0], (fragment, lines[0])
    assert snapshot(*roots) == before, "a refused command changed files"
    return lines[0]
