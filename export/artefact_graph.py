"""Loading an artefact's graph for the toolkit's own use (quantise, profile): checksum, then the graph itself.

A checksum proves the file is the exported one; a garbage or truncated model.onnx whose checksum was
recorded (or re-recorded by hand) passes it, and then failed deep inside onnx or onnxruntime. Here the graph
is loaded and checked once, and its input and outputs compared with the manifest, so a bad artefact is one
`ArtefactError` naming it before any work.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import onnx

from vo_runtime.artefact import verify_artefact
from vo_runtime.errors import ArtefactError, first_line
from vo_runtime.graph_contract import KEYPOINT_OUTPUTS

DENSE_OUTPUT_NAMES = ("heatmap", "descriptors_coarse")


def _static_shape(value_info: onnx.ValueInfoProto) -> list[int | str]:
    dims = value_info.type.tensor_type.shape.dim
    return [dim.dim_value if dim.HasField("dim_value") else dim.dim_param for dim in dims]


def _check_against_manifest(model: onnx.ModelProto, manifest: dict[str, Any], path: Path) -> None:
    inputs = list(model.graph.input)
    if len(inputs) != 1:
        raise ArtefactError(f"{path}: the graph takes {len(inputs)} inputs, the manifest one image")
    shape = _static_shape(inputs[0])
    if shape != manifest["input"]["shape"]:
        raise ArtefactError(f"{path}: the graph's input is {shape}, the manifest says {manifest['input']['shape']}")
    wanted = DENSE_OUTPUT_NAMES if manifest.get("mode") == "dense" else KEYPOINT_OUTPUTS
    missing = [name for name in wanted if name not in {output.name for output in model.graph.output}]
    if missing:
        raise ArtefactError(f"{path}: the graph has no {', '.join(missing)} output that its manifest promises")


def load_artefact_graph(directory: str | Path) -> tuple[dict[str, Any], onnx.ModelProto]:
    """The verified manifest and the checked graph of an artefact directory; `ArtefactError` when either fails."""
    directory = Path(directory)
    manifest = verify_artefact(directory)
    path = directory / manifest["onnx"]["file"]
    try:
        model = onnx.load(str(path))
        onnx.checker.check_model(model)
    except Exception as exc:  # onnx raises DecodeError, ValidationError, OSError... for a bad file
        raise ArtefactError(f"{path} matches its checksum but is no valid ONNX graph ({first_line(exc)}): re-export "
                            "the artefact") from None
    _check_against_manifest(model, manifest, path)
    return manifest, model
