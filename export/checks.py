"""Checking an exported graph against a `TargetProfile`, naming the first thing the target cannot run."""
from __future__ import annotations

import numpy as np
import onnx

from export.onnx_export import model_opset
from profiles import TargetProfile
from export.errors import ExportError

GATHER_OPS = ("Gather", "GatherElements")


def _constant_names(model: onnx.ModelProto) -> set[str]:
    names = {init.name for init in model.graph.initializer}
    names.update(out for node in model.graph.node if node.op_type == "Constant" for out in node.output)
    return names


def check_against_profile(model: onnx.ModelProto, profile: TargetProfile) -> None:
    """Raise `ExportError` naming the offending op, opset or shape; return None when the graph fits."""
    opset = model_opset(model)
    if opset > profile.max_opset:
        raise ExportError(f"graph uses opset {opset}; target {profile.name} reads opset <= {profile.max_opset}")
    for value in model.graph.input:
        dims = value.type.tensor_type.shape.dim
        if any(not dim.HasField("dim_value") or dim.dim_value <= 0 for dim in dims):
            raise ExportError(f"input {value.name!r} has a dynamic dimension; target {profile.name} needs fixed shapes")
    constants = _constant_names(model)
    for node in model.graph.node:
        label = f"{node.op_type} (node {node.name or '?'})"
        if node.domain not in ("", "ai.onnx"):
            raise ExportError(f"op {node.domain}::{node.op_type} is not a standard ONNX op; target {profile.name} cannot run it")
        if profile.allowed_ops and node.op_type not in profile.allowed_ops:
            raise ExportError(f"op {label} is not supported by target {profile.name} ({profile.runtime})")
        if node.op_type == "TopK" and node.input[1] not in constants:
            raise ExportError(f"op {label} has a data-dependent K; target {profile.name} needs a constant K")
        if node.op_type == "Pad":
            mode = next((a.s.decode() for a in node.attribute if a.name == "mode"), "constant")
            if mode != "constant" or (len(node.input) > 1 and node.input[1] not in constants):
                raise ExportError(f"op {label} is not a constant-mode Pad with constant pads")


def gather_index_names(model: onnx.ModelProto) -> list[str]:
    """Names of the tensors that feed Gather/GatherElements as indices and are computed at run time."""
    constants = _constant_names(model)
    return [node.input[1] for node in model.graph.node if node.op_type in GATHER_OPS and node.input[1] not in constants]


def min_gather_index(model: onnx.ModelProto, images: list[np.ndarray]) -> int | None:
    """Smallest Gather index seen when running ``model`` on ``images`` ([1,1,H,W] float32), or None if no gathers.

    TensorRT 8.0 reads negative Gather indices wrongly (onnxruntime wraps them), so the portable
    graph keeps them non-negative by construction; this proves it on real inputs.
    """
    import onnxruntime as ort

    names = gather_index_names(model)
    if not names:
        return None
    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    known = {value.name for value in probe.graph.output}
    for name in names:
        if name not in known:
            probe.graph.output.append(onnx.ValueInfoProto(name=name))
    session = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    lowest = None
    for image in images:
        for values in session.run(names, {session.get_inputs()[0].name: image}):
            current = int(np.min(values)) if np.size(values) else 0
            lowest = current if lowest is None else min(lowest, current)
    return lowest


def require_non_negative_gathers(model: onnx.ModelProto, images: list[np.ndarray], profile: TargetProfile) -> int | None:
    """For targets that constrain Gather indices, fail when any observed index is negative."""
    lowest = min_gather_index(model, images)
    constrained = any(op in profile.op_constraints for op in GATHER_OPS)
    if constrained and lowest is not None and lowest < 0:
        raise ExportError(f"a Gather index reached {lowest} on the parity images; target {profile.name} needs indices >= 0")
    return lowest
