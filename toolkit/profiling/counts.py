"""Counting work: parameters, MACs (FLOPs = 2 x MACs) and activation memory traffic, two independent ways.

1. fvcore on the PyTorch module, with handlers for every op it skips or ignores (the deformable conv,
   ELU and the other activations, pooling/NMS, softmax, normalisation, the descriptor sampling arithmetic).
2. A walk over the exported ONNX graph with inferred shapes, which is also the per-layer list the roofline
   uses (it is what the runtime executes, after BatchNorm folding and simplification).

Both use the same cost conventions, so their totals agree within 1 % (checked in tests):
- Conv / MatMul / Gemm: multiply-accumulates of the dense product (bias ignored, as fvcore does).
- Deformable 3x3 conv: its convolution plus 4 MACs per sampled value (bilinear weighted sum of four
  corners) plus 1 per sampled value for the DCNv2 mask.
- Elementwise ops (activations, arithmetic, comparisons, clipping): 1 per output element.
- Softmax: 3 per element (exp, sum, divide). Max-pool (also the NMS): k*k per output element.
- Reductions (sum, L2 norm, top-k): 1 per input element.
- BatchNorm: 0 when it directly follows a conv (folded into the conv at export), else 1 per element.
- Data movement (reshape, transpose, gather, pixel shuffle, slice, concat, expand, cast): 0 MACs, but
  its bytes count as memory traffic.
fvcore's own number is named "flops" but it is MACs; this module never calls MACs FLOPs.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import onnx
import torch
from fvcore.nn import FlopCountAnalysis
from fvcore.nn.jit_handles import get_shape
from torch import nn

from export.onnx_export import node_attribute

DEFORM_TAPS = 9

# ONNX op type -> kind used by the roofline's efficiency factors.
# Transcendental activations run far below the memory roofline on CPUs (ELU: one exp per element).
ACTIVATION_OPS = {"Elu", "Sigmoid", "Tanh", "Exp", "Log", "Sqrt", "Pow", "Erf", "Softmax"}
ELEMENTWISE_OPS = {
    "Relu", "LeakyRelu", "Add", "Sub", "Mul", "Div", "Clip", "Floor", "Ceil", "Equal", "Greater", "Less",
    "GreaterOrEqual", "LessOrEqual", "Neg", "Abs", "Where", "Max", "Min", "Not", "And", "Or", "Round",
    "BatchNormalization",
} | ACTIVATION_OPS
REDUCE_OPS = {"ReduceSum", "ReduceL2", "ReduceMean", "ReduceMax", "TopK"}
POOL_OPS = {"MaxPool", "AveragePool", "GlobalAveragePool"}
DATA_OPS = {"Gather", "GatherElements", "Transpose", "DepthToSpace", "SpaceToDepth", "Concat", "Slice", "Pad",
            "Expand", "Tile", "Split", "Cast"}
PARTIAL_READ_OPS = {"Gather", "GatherElements", "Slice"}
# Pure metadata in onnxruntime and TensorRT: no bytes move, no kernel runs.
FREE_OPS = {"Reshape", "Squeeze", "Unsqueeze", "Flatten", "Shape", "Identity", "Constant", "ConstantOfShape",
            "Range", "Size"}
KINDS = ("conv", "depthwise", "pointwise", "deform", "matmul", "activation", "elementwise", "reduce", "pool", "data")


@dataclass
class LayerCost:
    """One ONNX node that runs a kernel. Element counts are per image (batch 1)."""

    name: str
    op_type: str
    kind: str
    macs: int
    input_elements: int  # activations read (initializers excluded)
    output_elements: int  # activations written
    weight_elements: int  # initializers read
    output_shape: list[int] = field(default_factory=list)
    producer_op: str = ""  # op type that produced the first activation input
    input_consumers: int = 0  # nodes reading that input: an activation fuses into its conv only if it is the sole one

    def traffic_bytes(self, bytes_per_element: int) -> int:
        return (self.input_elements + self.output_elements + self.weight_elements) * bytes_per_element


@dataclass
class ModuleCount:
    """MACs of one module of the PyTorch model, its own ops only (children excluded)."""

    name: str
    macs: int
    parameters: int


def deform_macs(in_channels: int, out_channels: int, locations: int, modulated: bool,
                kernel_in_channels: int | None = None) -> int:
    """MACs of a 3x3 deformable conv on ``locations`` output pixels (conv + bilinear sampling + mask).

    ``kernel_in_channels`` is the kernel's input width (``in_channels`` for a dense kernel, 1 for a
    depthwise one): each output channel weighs that many sampled channels per tap."""
    sampled = in_channels * DEFORM_TAPS * locations
    per_output = (in_channels if kernel_in_channels is None else kernel_in_channels) * DEFORM_TAPS * locations
    return out_channels * per_output + 4 * sampled + (sampled if modulated else 0)


# ---------------------------------------------------------------- fvcore handlers (jit values in, MACs out)


def _numel(value) -> int:
    shape = get_shape(value)
    return int(math.prod(shape)) if shape is not None else 0


def _per_output(cost: int):
    def handle(inputs, outputs) -> int:
        return cost * _numel(outputs[0])
    return handle


def _per_input(inputs, outputs) -> int:
    return _numel(inputs[0])


def _zero(inputs, outputs) -> int:
    return 0


def _int_list(value) -> list[int]:
    """A traced int list argument: a constant, or a ListConstruct of constants."""
    constant = value.toIValue()
    if constant is not None:
        return [int(v) for v in constant]
    return [int(item.toIValue()) for item in value.node().inputs()]


def _max_pool(inputs, outputs) -> int:
    kernel = _int_list(inputs[1])
    return _numel(outputs[0]) * int(math.prod(kernel if len(kernel) == 2 else kernel * 2))


def _batch_norm(inputs, outputs) -> int:
    # A BatchNorm fed by a conv is folded into that conv's weights by the ONNX export (eval mode).
    if inputs[0].node().kind() == "aten::_convolution":
        return 0
    return _numel(outputs[0])


def _deform(inputs, outputs) -> int:
    x_shape, weight_shape, out_shape = get_shape(inputs[0]), get_shape(inputs[2]), get_shape(outputs[0])
    modulated = inputs[4].type().kind() != "NoneType"
    return x_shape[0] * deform_macs(x_shape[1], weight_shape[0], out_shape[2] * out_shape[3], modulated, weight_shape[1])


ELEMENTWISE_ATEN = [
    "elu", "elu_", "relu", "relu_", "sigmoid", "sigmoid_", "add", "add_", "sub", "sub_", "rsub", "mul", "mul_",
    "div", "div_", "clamp", "clamp_", "clamp_min", "clamp_max", "floor", "eq", "gt", "lt", "ge", "le", "exp",
    "sqrt", "neg", "abs", "where", "leaky_relu", "tanh", "maximum", "minimum",
]


def fvcore_handles() -> dict:
    """Handlers for the ops fvcore skips or ignores, in the conventions of this module."""
    handles = {f"aten::{name}": _per_output(1) for name in ELEMENTWISE_ATEN}
    handles.update({
        "aten::softmax": _per_output(3),
        "aten::max_pool2d": _max_pool,
        "aten::batch_norm": _batch_norm,
        "aten::linalg_vector_norm": _per_input,
        "aten::norm": _per_input,
        "aten::sum": _per_input,
        "aten::topk": _per_input,
        "aten::pixel_shuffle": _zero,
        "aten::expand_as": _zero,
        "aten::index_select": _zero,
        "edgefeat::deform_conv2d": _deform,
    })
    return handles


def fvcore_count(module: nn.Module, image: torch.Tensor) -> tuple[int, list[ModuleCount]]:
    """Total MACs and per-module self MACs of ``module`` on ``image`` [1, 1, H, W].

    The deformable conv must be in the ``native`` strategy (one opaque op with a handler); the ``torch``
    strategy would be counted as its gather arithmetic instead.
    """
    analysis = FlopCountAnalysis(module, (image,)).set_op_handle(**fvcore_handles())
    analysis.unsupported_ops_warnings(False).uncalled_modules_warnings(False).tracer_warnings("none")
    with torch.no_grad():
        by_module = analysis.by_module()
        total = int(analysis.total())
    modules = dict(module.named_modules())
    rows = []
    for name, macs in by_module.items():
        if name not in modules:
            continue
        children = sum(by_module.get(f"{name}.{child}" if name else child, 0) for child, _ in modules[name].named_children())
        own = int(macs - children)
        if own > 0:
            # Own parameters, plus those of children the forward uses directly (the deformable kernel).
            idle = [child for key, child in modules[name].named_children() if by_module.get(f"{name}.{key}" if name else key, 0) == 0]
            params = sum(p.numel() for p in modules[name].parameters(recurse=False))
            params += sum(p.numel() for child in idle for p in child.parameters())
            rows.append(ModuleCount(name or "(top level)", own, int(params)))
    return total, rows


def parameter_count(module: nn.Module) -> int:
    return int(sum(p.numel() for p in module.parameters()))


# ---------------------------------------------------------------- ONNX graph walk


def _tensor_shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    inferred = onnx.shape_inference.infer_shapes(model, data_prop=True)
    shapes: dict[str, list[int]] = {}
    graph = inferred.graph
    for info in list(graph.input) + list(graph.output) + list(graph.value_info):
        dims = info.type.tensor_type.shape.dim
        if all(d.HasField("dim_value") for d in dims):
            shapes[info.name] = [int(d.dim_value) for d in dims]
    for init in graph.initializer:
        shapes[init.name] = list(init.dims)
    return shapes


def op_kind(node: onnx.NodeProto, weight_shape: list[int] | None) -> str:
    """Roofline kind of a node: one of `KINDS`."""
    op = node.op_type
    if op == "Conv":
        group = int(node_attribute(node, "group", 1))
        if weight_shape and group > 1 and weight_shape[1] == 1:
            return "depthwise"
        if weight_shape and weight_shape[2:] == [1, 1]:
            return "pointwise"
        return "conv"
    if op == "DeformConv":
        return "deform"
    if op in ("MatMul", "Gemm"):
        return "matmul"
    if op in ACTIVATION_OPS:
        return "activation"
    if op in ELEMENTWISE_OPS:
        return "elementwise"
    if op in REDUCE_OPS:
        return "reduce"
    if op in POOL_OPS:
        return "pool"
    return "data"


def _node_macs(node: onnx.NodeProto, shapes: dict[str, list[int]], out_elements: int, in_elements: int) -> int:
    op = node.op_type
    if op == "Conv":
        weight = shapes[node.input[1]]
        return out_elements * int(math.prod(weight[1:]))
    if op == "DeformConv":
        x, weight, out = shapes[node.input[0]], shapes[node.input[1]], shapes[node.output[0]]
        modulated = len(node.input) > 4 and node.input[4] != ""
        return x[0] * deform_macs(x[1], weight[0], out[2] * out[3], modulated, weight[1])
    if op == "MatMul":
        return out_elements * shapes[node.input[0]][-1]
    if op == "Gemm":
        a = shapes[node.input[0]]
        return out_elements * (a[0] if node_attribute(node, "transA", 0) else a[-1])
    if op == "Softmax":
        return 3 * out_elements
    if op == "MaxPool":
        return out_elements * int(math.prod(node_attribute(node, "kernel_shape", [1])))
    if op in ("ReduceSum", "ReduceL2", "ReduceMean", "ReduceMax", "TopK"):
        return in_elements
    if op in ELEMENTWISE_OPS:
        return out_elements
    return 0


def onnx_layer_costs(model: onnx.ModelProto) -> list[LayerCost]:
    """Every kernel-running node of ``model`` (fixed shapes) with its MACs and element traffic."""
    shapes = _tensor_shapes(model)
    constants = {init.name for init in model.graph.initializer}
    constants.update(out for node in model.graph.node if node.op_type == "Constant" for out in node.output)
    consumers: Counter[str] = Counter(name for node in model.graph.node for name in node.input)
    producers = {out: node.op_type for node in model.graph.node for out in node.output}
    layers = []
    for node in model.graph.node:
        if node.op_type in FREE_OPS:
            continue
        activation_inputs = [name for name in node.input if name and name not in constants]
        sizes = [int(math.prod(shapes.get(name, [0]))) for name in activation_inputs]
        out_elements = sum(int(math.prod(shapes.get(name, [0]))) for name in node.output if name)
        if node.op_type in PARTIAL_READ_OPS and sizes:
            # Gathers and slices read only the elements they output (plus their indices), not the whole table.
            sizes[0] = min(sizes[0], out_elements)
        in_elements = sum(sizes)
        weight_elements = sum(int(math.prod(shapes.get(name, [0]))) for name in node.input if name in constants)
        weight_shape = shapes.get(node.input[1]) if len(node.input) > 1 else None
        first_in = activation_inputs[0] if activation_inputs else ""
        layers.append(LayerCost(
            name=node.name or node.output[0],
            op_type=node.op_type,
            kind=op_kind(node, weight_shape),
            macs=int(_node_macs(node, shapes, out_elements, in_elements)),
            input_elements=in_elements,
            output_elements=out_elements,
            weight_elements=weight_elements,
            output_shape=shapes.get(node.output[0], []),
            producer_op=producers.get(first_in, ""),
            input_consumers=consumers[first_in],
        ))
    return layers

