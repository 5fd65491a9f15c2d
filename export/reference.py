"""Writing an artefact's reference inputs and outputs (`vo_runtime.references`) from its parity images.

`toolkit export` and `toolkit quantise` call `write_cpu_references` on the staged model, so every artefact they
write can be checked later with ``python -m vo_runtime verify``. `add_references` gives an artefact written
before 0.2.0 its references without touching its model (the shipped default artefacts got theirs this way):

    python -m export.reference vo_runtime/default_artefact
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

from export.parity import SHIPPED_PARITY_DIR, default_parity_paths, read_gray
from vo_runtime.artefact import MANIFEST_NAME, verify_artefact
from vo_runtime.output_listing import foreign_entries, read_listing, write_listing
from vo_runtime.providers import open_session
from vo_runtime.references import REFERENCE_IMAGES, onnx_runner, reference_cases, write_references


def reference_images(paths: list[Path], height: int, width: int) -> list[tuple[str, np.ndarray]]:
    """The first `REFERENCE_IMAGES` parity images as (name, uint8 [height, width]), resized as the runtime does."""
    images = []
    for path in paths[:REFERENCE_IMAGES]:
        gray = read_gray(path)
        if gray.shape != (height, width):
            gray = cv2.resize(gray, (width, height), interpolation=cv2.INTER_AREA)
        images.append((path.name, gray))
    return images


def write_cpu_references(directory: Path, model_file: str, images: list[tuple[str, np.ndarray]], scale: float,
                         mode: str) -> dict:
    """Run ``images`` through ``directory/model_file`` on onnxruntime's CPU provider and write reference.npz there;
    returns the manifest's ``reference`` entry."""
    import onnxruntime as ort

    session = open_session(Path(directory) / model_file, threads=1, providers="cpu")
    cases = reference_cases(onnx_runner(session), images, scale, mode)
    return write_references(directory, cases, f"onnxruntime {ort.__version__} cpu")


def _parity_paths(manifest: dict) -> list[Path]:
    """The artefact's own parity images where they are the shipped ones, else the shipped set."""
    names = manifest.get("parity", {}).get("images", [])
    paths = [SHIPPED_PARITY_DIR / name for name in names]
    return paths if paths and all(path.is_file() for path in paths) else default_parity_paths()


def add_references(directory: Path) -> dict:
    """Give an existing artefact reference.npz from its parity images and record it in its manifest (model.onnx and
    every other field stay as they are). Returns the new ``reference`` entry."""
    directory = Path(directory)
    manifest = verify_artefact(directory)
    listing = read_listing(directory)
    owned = listing is not None and not foreign_entries(directory, listing)  # --force may replace it
    height, width = manifest["input"]["shape"][2:]
    images = reference_images(_parity_paths(manifest), height, width)
    manifest["reference"] = write_cpu_references(directory, manifest["onnx"]["file"], images,
                                                 float(manifest["input"]["normalisation"]["scale"]), manifest["mode"])
    staging = directory / f".{MANIFEST_NAME}.tmp"
    staging.write_text(json.dumps(manifest, indent=2) + "\n")
    staging.replace(directory / MANIFEST_NAME)
    if owned:  # still the output of the command that wrote it, reference.npz included
        write_listing(directory, listing["kind"])
    return manifest["reference"]


if __name__ == "__main__":
    for folder in sys.argv[1:]:
        entry = add_references(Path(folder))
        print(f"wrote {Path(folder) / entry['file']} ({', '.join(entry['images'])}; {entry['outputs_from']})")
