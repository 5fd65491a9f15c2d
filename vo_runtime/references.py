"""The reference inputs and outputs an artefact ships (``reference.npz``), and how a run is compared with them.

`toolkit export` (and `toolkit quantise`) write them in the parity run: the first `REFERENCE_IMAGES` parity images at
the artefact's input size (uint8, so the network input is exactly reproducible) and the artefact's own outputs for
them on onnxruntime's CPU provider, the run that matched PyTorch (manifest ``parity``). Another runtime (TensorRT,
CUDA, an engine built on a Jetson) is then checked against the same inputs by ``python -m vo_runtime verify``.

What is kept of an output stays small (about 100 KB an image at 240x320): keypoint mode keeps every valid keypoint
and score, and the descriptors of the `DESCRIPTOR_ROWS` best keypoints in float16; dense mode keeps the heatmap in
float16 and every `COARSE_STRIDE`-th cell's descriptor.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import numpy as np

from vo_runtime.artefact import sha256_file
from vo_runtime.errors import ArtefactError

REFERENCE_NAME = "reference.npz"
REFERENCE_IMAGES = 2
DESCRIPTOR_ROWS = 128
COARSE_STRIDE = 4
MATCH_RADIUS_PX = 1.0  # a keypoint that moved to the neighbouring pixel (an FP16 near-tie) is still the same point

Outputs = Dict[str, np.ndarray]
# Runs one network input [1, 1, H, W] float32 and returns the graph's outputs by name.
Runner = Callable[[np.ndarray], Outputs]


@dataclass
class ReferenceCase:
    """One reference image and what is stored of the artefact's outputs for it."""

    name: str
    image: np.ndarray  # [H, W] uint8 at the artefact's input size
    outputs: Outputs


@dataclass
class Agreement:
    """How one run's outputs on one reference image compare with the stored ones."""

    name: str
    reference_keypoints: int
    matched_keypoints: int
    descriptor_distances: np.ndarray  # L2 between unit descriptors, one per compared keypoint or cell
    score_max_diff: float
    heatmap_max_diff: float | None = None  # dense artefacts


def network_input(image: np.ndarray, scale: float) -> np.ndarray:
    """A uint8 [H, W] image as the runtime feeds it (`FeatureExtractor`): [1, 1, H, W] float32 times ``scale``."""
    return (image.astype(np.float32) * np.float32(scale))[None, None]


def onnx_runner(session: Any) -> Runner:
    """A `Runner` on an onnxruntime session (every output, by name)."""
    names = [output.name for output in session.get_outputs()]
    input_name = session.get_inputs()[0].name

    def run(tensor: np.ndarray) -> Outputs:
        return dict(zip(names, session.run(names, {input_name: tensor})))

    return run


def stored_outputs(outputs: Outputs, mode: str) -> Outputs:
    """What the reference file keeps of one image's outputs (see the module doc)."""
    if mode == "keypoints":
        valid = int(np.asarray(outputs["num_valid"]).reshape(-1)[0])
        return {"keypoints": np.asarray(outputs["keypoints"][:valid], np.float32),
                "scores": np.asarray(outputs["scores"][:valid], np.float32),
                "descriptors": np.asarray(outputs["descriptors"][:min(valid, DESCRIPTOR_ROWS)], np.float16)}
    return {"heatmap": np.asarray(outputs["heatmap"][0, 0], np.float16),
            "descriptors_coarse": np.asarray(outputs["descriptors_coarse"][0, :, ::COARSE_STRIDE, ::COARSE_STRIDE], np.float16)}


def reference_cases(run: Runner, images: List[Tuple[str, np.ndarray]], scale: float, mode: str) -> List[ReferenceCase]:
    """Run ``images`` (name, uint8 at the input size) through ``run`` and keep what `stored_outputs` keeps."""
    return [ReferenceCase(name, image, stored_outputs(run(network_input(image, scale)), mode)) for name, image in images]


def write_references(directory: Path, cases: List[ReferenceCase], provider: str) -> Dict[str, Any]:
    """Write ``reference.npz`` into ``directory``; return the manifest's ``reference`` entry (with its sha256)."""
    arrays = {}
    for index, case in enumerate(cases):
        arrays[f"{index}.image"] = case.image
        arrays.update({f"{index}.{key}": value for key, value in case.outputs.items()})
    path = Path(directory) / REFERENCE_NAME
    with open(path, "wb") as handle:  # a file object: np.savez would otherwise append .npz to any other name
        np.savez_compressed(handle, **arrays)
    return {"file": REFERENCE_NAME, "sha256": sha256_file(path), "images": [case.name for case in cases],
            "outputs_from": provider, "descriptor_rows": DESCRIPTOR_ROWS, "coarse_stride": COARSE_STRIDE}


def load_references(directory: Path, manifest: Dict[str, Any]) -> List[ReferenceCase]:
    """The reference cases of an artefact whose manifest `verify_artefact` has checked.

    Raises:
        ArtefactError: no reference entry (an artefact exported before 0.2.0), a missing file, a checksum that does
            not match, or a file that does not hold what the entry names.
    """
    entry = manifest.get("reference")
    if not isinstance(entry, dict) or not isinstance(entry.get("images"), list):
        raise ArtefactError(f"{directory} ships no reference outputs (written by edgefeat "
                            f"{manifest.get('toolkit_version', '?')}; they came with 0.2.0): re-export it to verify it")
    path = Path(directory) / str(entry.get("file", REFERENCE_NAME))
    if not path.is_file():
        raise ArtefactError(f"{directory}: {path.name} is missing (the manifest lists reference outputs)")
    if sha256_file(path) != entry.get("sha256"):
        raise ArtefactError(f"{path} fails its manifest checksum: the reference outputs were changed after export")
    keys = ("keypoints", "scores", "descriptors") if manifest.get("mode") == "keypoints" else ("heatmap", "descriptors_coarse")
    try:
        with np.load(path, allow_pickle=False) as data:
            return [ReferenceCase(str(name), data[f"{index}.image"], {key: data[f"{index}.{key}"] for key in keys})
                    for index, name in enumerate(entry["images"])]
    except (KeyError, ValueError, OSError) as exc:
        raise ArtefactError(f"{path} does not hold the reference outputs its manifest lists ({exc})") from None


def _nearest(reference: np.ndarray, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """For each reference keypoint, the index of the nearest of ``points`` and its distance (inf if none)."""
    if len(points) == 0:
        return np.zeros(len(reference), int), np.full(len(reference), np.inf)
    distances = np.linalg.norm(reference[:, None, :] - points[None, :, :], axis=2)
    nearest = distances.argmin(axis=1)
    return nearest, distances[np.arange(len(reference)), nearest]


def compare_keypoints(case: ReferenceCase, outputs: Outputs) -> Agreement:
    """Reference keypoints found again within `MATCH_RADIUS_PX`, and the descriptor distance at those found."""
    valid = int(np.asarray(outputs["num_valid"]).reshape(-1)[0])
    points = np.asarray(outputs["keypoints"][:valid], np.float32)
    reference = case.outputs["keypoints"]
    nearest, distance = _nearest(reference, points)
    found = distance <= MATCH_RADIUS_PX
    rows = np.flatnonzero(found[: len(case.outputs["descriptors"])])
    stored = case.outputs["descriptors"][rows].astype(np.float32)
    descriptors = np.asarray(outputs["descriptors"], np.float32)[nearest[rows]]
    scores = np.asarray(outputs["scores"], np.float32)[nearest[found]]
    score_diff = float(np.abs(case.outputs["scores"][found] - scores).max()) if found.any() else 0.0
    return Agreement(case.name, len(reference), int(found.sum()), np.linalg.norm(stored - descriptors, axis=1), score_diff)


def compare_dense(case: ReferenceCase, outputs: Outputs) -> Agreement:
    """Heatmap difference and per-cell descriptor distance of a dense artefact's outputs."""
    heatmap = case.outputs["heatmap"].astype(np.float32)
    stored = case.outputs["descriptors_coarse"].astype(np.float32)
    sampled = np.asarray(outputs["descriptors_coarse"], np.float32)[0, :, ::COARSE_STRIDE, ::COARSE_STRIDE]
    distances = np.linalg.norm((stored - sampled).reshape(stored.shape[0], -1), axis=0)
    difference = float(np.abs(np.asarray(outputs["heatmap"], np.float32)[0, 0] - heatmap).max())
    return Agreement(case.name, 0, 0, distances, 0.0, heatmap_max_diff=difference)
