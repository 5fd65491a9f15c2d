"""Tracing a graph module to ONNX, checking it, and simplifying it; the checker every artefact writer runs.

The TorchScript exporter (``dynamo=False``) is used for every target: the dynamo exporter of torch 2.13
emits opset >= 18 whatever is asked, and the TX2 (TensorRT 8.0) reads opset <= 13.
"""
from __future__ import annotations

import io
import warnings
from collections import Counter
from dataclasses import dataclass

import onnx
import torch
from torch import nn

from export.graph_order import topologically_sorted
from export.errors import ExportError
from vo_runtime.errors import first_line


@dataclass
class OnnxExportResult:
    model: onnx.ModelProto
    nodes_before_simplify: int
    nodes_after_simplify: int
    simplifier: str


def trace_to_onnx(
    module: nn.Module, image: torch.Tensor, opset: int, output_names: tuple[str, ...]
) -> onnx.ModelProto:
    """Trace ``module`` on ``image`` [1, 1, H, W] into an in-memory ONNX model with fixed shapes."""
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # tracer warnings about Python ints in shapes: shapes are fixed by design
        torch.onnx.export(
            module,
            (image,),
            buffer,
            dynamo=False,
            opset_version=opset,
            input_names=["image"],
            output_names=list(output_names),
            do_constant_folding=True,
        )
    return onnx.load_from_string(buffer.getvalue())


def simplify(model: onnx.ModelProto) -> tuple[onnx.ModelProto, str]:
    """Constant-fold and clean the graph with onnxsim; the result is re-checked by onnxsim itself and sorted
    (folding rewrites nodes, and the order is what strict consumers read)."""
    import onnxsim

    simplified, ok = onnxsim.simplify(model)
    if not ok:
        raise ExportError("onnxsim could not validate the simplified graph against the original")
    return topologically_sorted(simplified), f"onnxsim {onnxsim.__version__}"


def full_check(model: onnx.ModelProto, what: str = "exported graph") -> None:
    """onnx.checker with shape inference (``full_check``); a failure is a toolkit bug, reported in one line."""
    try:
        onnx.checker.check_model(model, full_check=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as exc:
        raise ExportError(f"{what} fails onnx.checker: {first_line(exc)}") from None


def check_before_writing(model: onnx.ModelProto, what: str) -> dict:
    """`full_check` of the graph a writer is about to save; returns the manifest's record of it (``onnx.checker``).

    The record is how the runtime knows: the check takes ~2 ms, but it needs the onnx package, which the
    runtime does not depend on, and onnxruntime sorts nodes for itself, so it cannot tell either.
    """
    full_check(model, what)
    return {"check": "onnx.checker.check_model(full_check=True)", "passed": True, "onnx_version": onnx.__version__}


def export_onnx(
    module: nn.Module, image: torch.Tensor, opset: int, output_names: tuple[str, ...]
) -> OnnxExportResult:
    """Trace, check, simplify and check again. Returns the final model and node counts."""
    raw = trace_to_onnx(module, image, opset, output_names)
    full_check(raw)
    simplified, simplifier = simplify(raw)
    full_check(simplified)
    return OnnxExportResult(simplified, len(raw.graph.node), len(simplified.graph.node), simplifier)


def op_histogram(model: onnx.ModelProto) -> dict[str, int]:
    """Node count per op type, sorted by name."""
    return dict(sorted(Counter(node.op_type for node in model.graph.node).items()))


def model_opset(model: onnx.ModelProto) -> int:
    """The default-domain opset the model declares."""
    for entry in model.opset_import:
        if entry.domain in ("", "ai.onnx"):
            return int(entry.version)
    raise ExportError("exported model declares no default-domain opset")


def node_attribute(node: onnx.NodeProto, name: str, default):
    """The value of ``node``'s attribute ``name``, or ``default`` when the node does not set it."""
    for attribute in node.attribute:
        if attribute.name == name:
            return onnx.helper.get_attribute_value(attribute)
    return default
