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


def head_output_convs(model: onnx.ModelProto) -> list[str]:
    """Names of Conv nodes with no Conv/DeformConv downstream: the 1x1 convs making the 65 logits and the
    descriptors. Their outputs are compared against thresholds and normalised, so they stay in float."""
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    terminal = []
    for conv in conv_nodes(model):
        stack, seen, feeds_conv = list(conv.output), set(), False
        while stack and not feeds_conv:
            name = stack.pop()
            for node in consumers.get(name, []):
                if node.op_type in ("Conv", "DeformConv"):
                    feeds_conv = True
                    break
                if id(node) not in seen:
                    seen.add(id(node))
                    stack.extend(node.output)
        if not feeds_conv:
            terminal.append(conv.name)
    return terminal


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
