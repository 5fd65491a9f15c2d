"""Per-layer INT8 sensitivity of an ONNX graph, each Conv measured in isolation.

For every Conv, its real FP32 inputs (from running the graph on calibration images) go through the conv
twice: once in FP32, once with the input fake-quantised as onnxruntime's MinMax calibration would
(uint8, asymmetric, range over the images, zero included) and the weights per output channel (int8,
symmetric). The relative L2 error of the output is the layer's sensitivity; upstream errors are excluded,
so the ranking says which layers to keep in float (depthwise convs are the usual offenders).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import onnx
import torch
import torch.nn.functional as F
from onnx import numpy_helper

from toolkit.compression.report import ort_session


@dataclass
class LayerSensitivity:
    node: str
    kind: str  # "depthwise", "pointwise" or "conv"
    relative_error: float

    def to_dict(self) -> dict:
        return asdict(self)


def conv_nodes(model: onnx.ModelProto) -> list[onnx.NodeProto]:
    """Conv nodes whose weight is an initializer (the ones static quantisation can touch)."""
    weights = {init.name for init in model.graph.initializer}
    return [node for node in model.graph.node if node.op_type == "Conv" and node.input[1] in weights]


def fixed_kernel_convs(model: onnx.ModelProto) -> list[str]:
    """Names of the convs inside `models.featurenet.CellContrast` and `WindowStatistics`: fixed kernels on raw
    pixel differences and their squares, where uint8 steps would erase a dark cell's contrast. They stay in float."""
    scopes = ("/cell_contrast/", "/window_statistics/")
    return [node.name for node in model.graph.node if node.op_type == "Conv" and any(s in node.name for s in scopes)]


def single_channel_convs(model: onnx.ModelProto) -> list[str]:
    """Names of dense convs reading one input channel (the stem on the gray image). onnxruntime's
    QLinearConv is slow there: 2.0 ms against 0.3 ms in float for the 1 -> 16 stem at 240x320, more than
    every other conv gains together. They stay in float."""
    weights = {init.name: init for init in model.graph.initializer}
    found = []
    for node in conv_nodes(model):
        group = next((int(a.i) for a in node.attribute if a.name == "group"), 1)
        if group == 1 and weights[node.input[1]].dims[1] == 1:
            found.append(node.name)
    return found


def head_output_convs(model: onnx.ModelProto) -> list[str]:
    """Names of the convs that end a head, which stay in float: those whose output reaches a Softmax before
    any other learned layer (the 1x1 convs making the 65 keypoint logits, which a softmax turns into scores
    compared against a threshold), and those with no learned layer (Conv, DeformConv, Gemm, MatMul with
    weights) downstream at all (a dense graph's descriptor conv, whose output is normalised). The
    descriptor head's last conv in a keypoint graph runs as a Gemm at the keypoints and is quantised."""
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    weights = {init.name for init in model.graph.initializer}

    def learned(node: onnx.NodeProto) -> bool:
        return node.op_type in ("Conv", "DeformConv", "Gemm") or (node.op_type == "MatMul" and node.input[1] in weights)

    ends = []
    for conv in conv_nodes(model):
        stack, seen, feeds_learned, reaches_softmax = list(conv.output), set(), False, False
        while stack:
            for node in consumers.get(stack.pop(), []):
                if learned(node):
                    feeds_learned = True
                elif id(node) not in seen:
                    seen.add(id(node))
                    reaches_softmax |= node.op_type == "Softmax"
                    stack.extend(node.output)
        if reaches_softmax or not feeds_learned:
            ends.append(conv.name)
    return ends


def _attributes(node: onnx.NodeProto) -> dict:
    values = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
    pads = list(values.get("pads", [0, 0, 0, 0]))
    return {"stride": tuple(values.get("strides", [1, 1])), "dilation": tuple(values.get("dilations", [1, 1])),
            "groups": int(values.get("group", 1)), "pads": pads}


def _fake_quant_activation(x: torch.Tensor) -> torch.Tensor:
    low, high = min(float(x.min()), 0.0), max(float(x.max()), 0.0)
    scale = (high - low) / 255.0 or 1.0
    zero = round(-low / scale)
    return (torch.clamp(torch.round(x / scale) + zero, 0, 255) - zero) * scale


def _fake_quant_weight(w: torch.Tensor) -> torch.Tensor:
    scale = w.abs().amax(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12) / 127.0
    return torch.clamp(torch.round(w / scale), -127, 127) * scale


def _conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, attrs: dict) -> torch.Tensor:
    top, left, bottom, right = attrs["pads"]
    x = F.pad(x, (left, right, top, bottom))
    return F.conv2d(x, weight, bias, attrs["stride"], 0, attrs["dilation"], attrs["groups"])


def layer_sensitivity(model: onnx.ModelProto, images: np.ndarray) -> list[LayerSensitivity]:
    """Sensitivity of every quantisable Conv on ``images`` [N, 1, H, W], worst first."""
    convs = conv_nodes(model)
    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    known = {value.name for value in probe.graph.output} | {value.name for value in probe.graph.input}
    wanted = list(dict.fromkeys(node.input[0] for node in convs))
    for name in wanted:
        if name not in known:
            probe.graph.output.append(onnx.ValueInfoProto(name=name))
    session = ort_session(probe)
    input_name = session.get_inputs()[0].name
    computed = [name for name in wanted if name != input_name]
    gathered: dict[str, list[np.ndarray]] = {name: [] for name in wanted}
    for image in images:
        feed = {input_name: image[None]}
        if input_name in gathered:
            gathered[input_name].append(image[None])
        for name, value in zip(computed, session.run(computed, feed) if computed else []):
            gathered[name].append(value)
    initializers = {init.name: init for init in model.graph.initializer}
    results = []
    with torch.no_grad():
        for node in convs:
            x = torch.from_numpy(np.concatenate(gathered[node.input[0]])).float()
            weight = torch.from_numpy(numpy_helper.to_array(initializers[node.input[1]]).astype(np.float32))
            bias = None
            if len(node.input) > 2 and node.input[2] in initializers:
                bias = torch.from_numpy(numpy_helper.to_array(initializers[node.input[2]]).astype(np.float32))
            attrs = _attributes(node)
            exact = _conv(x, weight, bias, attrs)
            quantised = _conv(_fake_quant_activation(x), _fake_quant_weight(weight), bias, attrs)
            error = float((quantised - exact).norm() / exact.norm().clamp_min(1e-12))
            kind = "depthwise" if attrs["groups"] > 1 else ("pointwise" if weight.shape[2:] == (1, 1) else "conv")
            results.append(LayerSensitivity(node.name, kind, error))
    return sorted(results, key=lambda item: item.relative_error, reverse=True)
