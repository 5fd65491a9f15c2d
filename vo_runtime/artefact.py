"""Reading an exported artefact directory (torch-free).

An artefact is a directory written by `toolkit export`:

- ``model.onnx``: fixed input ``image`` float32 [1, 1, H, W], grayscale scaled to [0, 1].
  Keypoint mode outputs (K = ``postprocess.max_keypoints``):
    ``keypoints``   float32 [K, 2]  (x, y) in input pixels, pixel centres at integers,
    ``scores``      float32 [K]     sorted descending,
    ``descriptors`` float32 [K, D]  L2-normalised,
    ``num_valid``   int32   [1]     the first ``num_valid`` rows are real detections; the rest is padding.
  Dense mode (``--dense``) outputs ``heatmap`` [1, 1, H, W] and ``descriptors_coarse`` [1, D, H/8, W/8].
- ``manifest.json``: target, opset, input shape and normalisation, outputs, precision, deform strategy,
  ``onnx.sha256`` of model.onnx, source checkpoint hash, toolkit version and parity figures.
  ``onnx.checker`` records that model.onnx passed ``onnx.checker.check_model(full_check=True)`` (which
  includes topological node order) before it was written; artefacts older than that record lack the field.
  ``onnx.block_graphs`` (x86 CPU artefacts): [{block, file, sha256, chains}], the same graph padded with zero
  channels for onnxruntime's channel blocks; `FeatureExtractor` runs the one for this CPU (`vo_runtime.cpu_blocks`).
  The runtime does not re-run the check: it needs the onnx package, which is no runtime dependency.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

from vo_runtime.errors import ArtefactError, first_line

MANIFEST_NAME = "manifest.json"
MODEL_NAME = "model.onnx"
ARTEFACT_FORMAT = "edgefeat-artefact/1"


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(chunk), b""):
            digest.update(block)
    return digest.hexdigest()


def artefact_path(artefact_dir: object) -> Path:
    """``artefact_dir`` as a Path; `ArtefactError` for anything that is no path (None, a number)."""
    if not isinstance(artefact_dir, (str, os.PathLike)):
        raise ArtefactError(f"an artefact is a directory path, got {type(artefact_dir).__name__}")
    return Path(artefact_dir)


def load_manifest(artefact_dir: str | Path) -> dict[str, Any]:
    """Read ``manifest.json`` of an artefact directory; raise `ArtefactError` if absent or malformed."""
    directory = artefact_path(artefact_dir)
    if directory.exists() and not directory.is_dir():
        raise ArtefactError(f"{directory} is a file, not an artefact directory")
    if not directory.is_dir():
        raise ArtefactError(f"artefact directory not found: {directory}")
    path = directory / MANIFEST_NAME
    if not path.is_file():
        raise ArtefactError(f"{directory} is not an artefact: {MANIFEST_NAME} is missing")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ArtefactError(f"{path} is not valid JSON ({first_line(exc)})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != ARTEFACT_FORMAT:
        raise ArtefactError(f"{path} is not an {ARTEFACT_FORMAT} manifest")
    return manifest


def _check_fields(manifest: dict[str, Any], path: Path) -> None:
    """The fields every reader relies on: the model's checksum and the fixed input shape."""
    onnx_entry = manifest.get("onnx")
    expected = onnx_entry.get("sha256") if isinstance(onnx_entry, dict) else None
    if not isinstance(expected, str) or not re.fullmatch(r"[0-9a-f]{64}", expected):
        raise ArtefactError(f"{path} records no sha256 for the model (onnx.sha256): it was not written by toolkit "
                            "export, or was edited; re-export the artefact")
    entry = manifest.get("input")
    shape = entry.get("shape") if isinstance(entry, dict) else None
    if not (isinstance(shape, list) and len(shape) == 4 and all(isinstance(v, int) and v > 0 for v in shape)):
        raise ArtefactError(f"{path} has no valid input.shape (four positive integers): re-export the artefact")
    _check_file_name(onnx_entry.setdefault("file", MODEL_NAME), "onnx.file", path)
    blocks = onnx_entry.setdefault("block_graphs", [])
    if not isinstance(blocks, list):
        raise ArtefactError(f"{path}: onnx.block_graphs must be a list: re-export the artefact")
    for entry in blocks:
        if not (isinstance(entry, dict) and isinstance(entry.get("block"), int) and entry["block"] > 1
                and isinstance(entry.get("sha256"), str) and re.fullmatch(r"[0-9a-f]{64}", entry["sha256"])):
            raise ArtefactError(f"{path}: each onnx.block_graphs entry needs a block (> 1), a file and a sha256: "
                                "re-export the artefact")
        _check_file_name(entry.get("file"), "onnx.block_graphs file", path)


def _check_file_name(name: object, field: str, path: Path) -> None:
    # A name, never a path: a manifest pointing at ../../x or /x would load a file outside the artefact.
    if not (isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name and "\\" not in name):
        raise ArtefactError(f"{path}: {field} must name a file inside the artefact, got {name!r}")


def verify_artefact(artefact_dir: str | Path) -> dict[str, Any]:
    """Load the manifest and check that model.onnx (and each graph of ``onnx.block_graphs``, the same network
    padded for a CPU's channel blocks: `vo_runtime.cpu_blocks`) matches its recorded sha256.

    Returns the manifest. Raises `ArtefactError` naming what is wrong.
    """
    directory = artefact_path(artefact_dir)
    manifest = load_manifest(directory)
    _check_fields(manifest, directory / MANIFEST_NAME)
    graphs = [manifest["onnx"]] + manifest["onnx"]["block_graphs"]
    for entry in graphs:
        model_path = directory / entry["file"]
        if not model_path.is_file():
            raise ArtefactError(f"{directory}: {model_path.name} is missing")
        expected, actual = entry["sha256"], sha256_file(model_path)
        if expected != actual:
            raise ArtefactError(
                f"{model_path} fails its manifest checksum (sha256 {actual[:12]}..., manifest says "
                f"{expected[:12]}...): the file was changed or truncated after export"
            )
    return manifest


DEFAULT_ARTEFACT_DIR = Path(__file__).resolve().parent / "default_artefact"
# The shipped artefacts, one per camera aspect: the 4:3 one is the default of every camera the others do not
# fit; a camera of another aspect takes the one exported at its own aspect (no squeezed view, docs/vo.md).
WIDE_ARTEFACT_DIR = Path(__file__).resolve().parent / "default_artefact_wide"
ASPECT_TOLERANCE = 0.1  # a frame stretched by at most 10 % on one axis counts as the artefact's aspect


def default_artefact(width: int | None = None, height: int | None = None) -> Path:
    """The artefact shipped with the package for frames of ``width`` x ``height``: the one whose input has
    the frames' aspect (within `ASPECT_TOLERANCE`), else the 4:3 featurenet-relu x86-cpu artefact at 240x320
    (also without a size). Raises ArtefactError when an install lacks it."""
    chosen = DEFAULT_ARTEFACT_DIR
    if width and height:
        fitting = [(aspect_distortion(_input_size(directory), height, width), directory)
                   for directory in (DEFAULT_ARTEFACT_DIR, WIDE_ARTEFACT_DIR) if (directory / MANIFEST_NAME).is_file()]
        fitting = [item for item in fitting if item[0] <= ASPECT_TOLERANCE]
        if fitting:
            chosen = min(fitting)[1]
    if not (chosen / MANIFEST_NAME).is_file():
        raise ArtefactError(f"the shipped default artefact is missing from {chosen}: pass --artefact DIR")
    return chosen


def _input_size(artefact_dir: Path) -> tuple[int, int]:
    shape = load_manifest(artefact_dir)["input"]["shape"]
    return int(shape[2]), int(shape[3])


def aspect_distortion(input_size: tuple[int, int], height: int, width: int) -> float:
    """How much resizing ``height`` x ``width`` frames to an ``input_size`` (height, width) network input
    stretches one axis against the other (0: the same aspect; 1.48 for KITTI's 1226x370 into 320x240)."""
    ratio = (width / height) / (input_size[1] / input_size[0])
    return max(ratio, 1.0 / ratio) - 1.0
