"""Tiny ONNX graphs that return fixed outputs, for artefacts whose graph breaks its manifest's promise (issue 29):
a num_valid outside the rows, descriptors of another width, [K, 3] or NaN keypoints, a missing output."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from vo_runtime.artefact import ARTEFACT_FORMAT, MANIFEST_NAME, MODEL_NAME, sha256_file

OPSET = 17


def constant_keypoint_graph(height: int, width: int, outputs: dict[str, np.ndarray]) -> onnx.ModelProto:
    """A graph on an [1, 1, height, width] image whose outputs are the given constants (name -> array)."""
    nodes = [helper.make_node("Constant", [], [name], value=numpy_helper.from_array(value, f"{name}_value"))
             for name, value in outputs.items()]
    types = {np.dtype(np.float32): TensorProto.FLOAT, np.dtype(np.int32): TensorProto.INT32,
             np.dtype(np.int64): TensorProto.INT64}
    graph = helper.make_graph(
        nodes, "constant_keypoints",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, height, width])],
        [helper.make_tensor_value_info(name, types[value.dtype], list(value.shape)) for name, value in outputs.items()])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])


def keypoint_outputs(rows: int = 16, dim: int = 8, num_valid: int = 4) -> dict[str, np.ndarray]:
    """Well-formed outputs: ``num_valid`` real rows of ``rows``, unit descriptors of ``dim``."""
    rng = np.random.default_rng(0)
    descriptors = rng.normal(size=(rows, dim)).astype(np.float32)
    return {"keypoints": rng.uniform(4, 28, (rows, 2)).astype(np.float32),
            "scores": np.linspace(0.9, 0.1, rows, dtype=np.float32),
            "descriptors": descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True),
            "num_valid": np.array([num_valid], np.int32)}


def write_graph_artefact(directory: Path, model: onnx.ModelProto, height: int, width: int, rows: int = 16,
                         dim: int | None = 8, **manifest_changes) -> Path:
    """An artefact folder around ``model`` whose manifest records its checksum (so only the graph is wrong)."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / MODEL_NAME).write_bytes(model.SerializeToString())
    outputs = {"keypoints": {"shape": [rows, 2]}, "scores": {"shape": [rows]}, "num_valid": {"shape": [1]}}
    if dim is not None:
        outputs["descriptors"] = {"shape": [rows, dim]}
    manifest = {"format": ARTEFACT_FORMAT, "mode": "keypoints", "target": "x86-cpu",
                "input": {"name": "image", "shape": [1, 1, height, width], "normalisation": {"scale": 1 / 255}},
                "outputs": outputs, "postprocess": {"max_keypoints": rows},
                "onnx": {"file": MODEL_NAME, "sha256": sha256_file(directory / MODEL_NAME)},
                "model": {"arch": "featurenet", "config": {}}}
    for dotted, value in manifest_changes.items():
        node = manifest
        *parents, last = dotted.split("__")
        for part in parents:
            node = node[part]
        if value is None:
            node.pop(last, None)
        else:
            node[last] = value
    (directory / MANIFEST_NAME).write_text(json.dumps(manifest))
    return directory
