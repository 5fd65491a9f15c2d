"""What a keypoint artefact's graph must hand back, read from its manifest once and checked on every run.

A checksum proves the file is the one exported, not that the graph keeps the manifest's promise: a graph whose
``num_valid`` is -5 or 1e9, whose descriptors are 128-d where the manifest says 256, whose keypoints are
[K, 3] or NaN, or whose input is not the manifest's shape would give wrong features without a word.
`read_contract` reads the promise (refusing a manifest that makes none), `check_graph` compares it with what
the graph declares when it is loaded, and `checked_detections` holds every run's outputs to it. All raise
`ArtefactError` naming the artefact.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from vo_runtime.errors import ArtefactError

KEYPOINT_OUTPUTS = ("keypoints", "scores", "descriptors", "num_valid")
MODES = ("keypoints", "dense")


@dataclass(frozen=True)
class KeypointContract:
    """The shapes and scale a keypoint artefact promises (rows = K, the fixed number of output rows)."""

    directory: Path
    height: int
    width: int
    scale: float
    rows: int
    descriptor_dim: Optional[int]  # None when the manifest does not say (older fixtures list output names only)

    def broken(self, what: str) -> ArtefactError:
        return ArtefactError(f"{self.directory}: {what}; the graph does not keep its manifest's promise, re-export "
                             "the artefact")


def _positive_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _declared_shape(manifest: Dict[str, Any], name: str) -> Optional[list]:
    outputs = manifest.get("outputs")
    entry = outputs.get(name) if isinstance(outputs, dict) else None
    shape = entry.get("shape") if isinstance(entry, dict) else None
    return shape if isinstance(shape, list) else None


def _check_mode(manifest: Dict[str, Any], directory: Path) -> None:
    mode = manifest.get("mode")
    if mode is None:
        raise ArtefactError(f"{directory}: the manifest records no mode (keypoints or dense): re-export the artefact")
    if mode == "dense":
        raise ArtefactError(f"{directory} is a dense artefact; FeatureExtractor needs keypoint mode")
    if mode not in MODES:
        raise ArtefactError(f"{directory}: unknown artefact mode {mode!r} (keypoints or dense)")


def _scale(manifest: Dict[str, Any], directory: Path) -> float:
    entry = manifest["input"].get("normalisation")
    scale = entry.get("scale") if isinstance(entry, dict) else None
    if isinstance(scale, bool) or not isinstance(scale, (int, float)):
        raise ArtefactError(f"{directory}: the manifest has no input.normalisation.scale")
    if not (math.isfinite(scale) and scale > 0):
        raise ArtefactError(f"{directory}: input.normalisation.scale must be a positive number, got {scale}")
    return float(scale)


def read_contract(manifest: Dict[str, Any], directory: Path) -> KeypointContract:
    """The promise of a verified keypoint manifest (`vo_runtime.artefact.verify_artefact`)."""
    _check_mode(manifest, directory)
    shape = manifest["input"]["shape"]
    keypoints, descriptors = _declared_shape(manifest, "keypoints"), _declared_shape(manifest, "descriptors")
    postprocess = manifest.get("postprocess")
    rows = postprocess.get("max_keypoints") if isinstance(postprocess, dict) else None
    if not _positive_int(rows):
        rows = keypoints[0] if keypoints and _positive_int(keypoints[0]) else None
    if rows is None:
        raise ArtefactError(f"{directory}: the manifest gives no postprocess.max_keypoints: re-export the artefact")
    if keypoints is not None and keypoints != [rows, 2]:
        raise ArtefactError(f"{directory}: the manifest's keypoints shape {keypoints} is not [{rows}, 2]")
    dim = None
    if descriptors is not None:
        if not (len(descriptors) == 2 and descriptors[0] == rows and _positive_int(descriptors[1])):
            raise ArtefactError(f"{directory}: the manifest's descriptors shape {descriptors} is not [{rows}, D]")
        dim = descriptors[1]
    return KeypointContract(directory, int(shape[2]), int(shape[3]), _scale(manifest, directory), rows, dim)


def _fits(declared: Sequence[Any], expected: Tuple[Optional[int], ...]) -> bool:
    """A graph's declared shape against the expected one; symbolic dimensions (str/None) and None pass."""
    if len(declared) != len(expected):
        return False
    return all(not isinstance(d, int) or e is None or d == e for d, e in zip(declared, expected))


def check_graph(session: Any, contract: KeypointContract) -> None:
    """The loaded graph's declared input and outputs against the manifest (before any frame is run)."""
    inputs = session.get_inputs()
    if len(inputs) != 1 or inputs[0].type != "tensor(float)":
        raise contract.broken(f"the graph takes {len(inputs)} input(s), not one float image")
    image = (1, 1, contract.height, contract.width)
    if not _fits(list(inputs[0].shape or []), image):
        raise contract.broken(f"the graph's input is {list(inputs[0].shape)}, the manifest says {list(image)}")
    declared = {output.name: list(output.shape or []) for output in session.get_outputs()}
    missing = [name for name in KEYPOINT_OUTPUTS if name not in declared]
    if missing:
        raise contract.broken(f"the graph has no {', '.join(missing)} output")
    expected = {"keypoints": (contract.rows, 2), "scores": (contract.rows,),
                "descriptors": (contract.rows, contract.descriptor_dim), "num_valid": (1,)}
    for name, shape in expected.items():
        if not _fits(declared[name], shape):
            raise contract.broken(f"the graph's {name} output is {declared[name]}, the manifest says "
                                  f"{['D' if d is None else d for d in shape]}")


def checked_detections(outputs: Sequence[Any], contract: KeypointContract
                       ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The real rows (keypoints, scores, descriptors) of one run's outputs, in `KEYPOINT_OUTPUTS` order, after
    checking them against the contract: shapes, a ``num_valid`` within the rows, finite values."""
    keypoints, scores, descriptors, num_valid = (np.asarray(output) for output in outputs)
    rows = contract.rows
    if keypoints.shape != (rows, 2) or scores.shape != (rows,) or descriptors.ndim != 2 \
            or descriptors.shape[0] != rows:
        raise contract.broken(f"the graph returned keypoints {list(keypoints.shape)}, scores {list(scores.shape)} "
                              f"and descriptors {list(descriptors.shape)} for {rows} rows")
    if contract.descriptor_dim is not None and descriptors.shape[1] != contract.descriptor_dim:
        raise contract.broken(f"the graph returned {descriptors.shape[1]}-d descriptors, the manifest says "
                              f"{contract.descriptor_dim}")
    if num_valid.size != 1 or not np.issubdtype(num_valid.dtype, np.integer):
        raise contract.broken(f"the graph's num_valid is {num_valid.dtype} {list(num_valid.shape)}, not one integer")
    count = int(num_valid.reshape(-1)[0])
    if not 0 <= count <= rows:
        raise contract.broken(f"the graph says num_valid = {count}, outside 0..{rows}")
    real = (keypoints[:count], scores[:count], descriptors[:count])
    if not all(np.all(np.isfinite(values)) for values in real):
        raise contract.broken("the graph returned NaN or infinite values among its valid rows")
    return tuple(values.astype(np.float32) for values in real)
