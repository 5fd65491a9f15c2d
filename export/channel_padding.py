"""Zero channels that let onnxruntime keep a pooled tensor in its blocked layout (`pad_pooled_channels`).

onnxruntime's CPU provider runs convolutions in a blocked layout (NCHWc: 16 channels a block with AVX-512, 8 with
AVX2). A max-pool between two convolutions runs blocked only when its channel count is a multiple of the block;
otherwise the tensor is converted back to plain NCHW for the pool and blocked again after it. The slim network's
second stage (24 channels at 240x376 for a 480x752 input) paid ~1.1 ms of 21.5 for that on an AVX-512 core
(docs/vo_euroc.md, "Channels padded for the CPU's blocks").

Padding such a chain changes no output value: the producing convolution gets zero filters with zero bias (its
new channels are 0), ReLU and max-pool keep 0 at 0, the depthwise convolutions in between get zero filters, and
the consuming convolution gets zero weights for the new input channels, which add exact zeros to its sums.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import numpy_helper

from export.onnx_export import node_attribute

# Ops that map a zero channel to a zero channel, one input, one output.
ZERO_PRESERVING = ("Relu", "MaxPool")


@dataclass
class PaddedChain:
    """One padded chain: the producing convolution, its channels before and after, and the consuming one."""

    producer: str
    channels: int
    padded: int
    consumer: str

    def to_dict(self) -> dict:
        return {"producer": self.producer, "channels": self.channels, "padded": self.padded, "consumer": self.consumer}


class _Graph:
    """Lookups over one graph: consumers of each tensor, initializers and how many nodes read each."""

    def __init__(self, graph: onnx.GraphProto) -> None:
        self.graph = graph
        self.initializers = {tensor.name: tensor for tensor in graph.initializer}
        self.consumers: dict[str, list[onnx.NodeProto]] = {}
        for node in graph.node:
            for name in node.input:
                self.consumers.setdefault(name, []).append(node)
        self.outputs = {value.name for value in graph.output}

    def weight(self, node: onnx.NodeProto, position: int) -> np.ndarray | None:
        """A node's input ``position`` as an array when it is an initializer no other node reads, else None."""
        if len(node.input) <= position or not node.input[position]:
            return None
        name = node.input[position]
        if name not in self.initializers or len(self.consumers.get(name, [])) != 1:
            return None
        return numpy_helper.to_array(self.initializers[name])

    def set_weight(self, node: onnx.NodeProto, position: int, values: np.ndarray) -> None:
        name = node.input[position]
        self.initializers[name].CopyFrom(numpy_helper.from_array(values, name))

    def paddable_bias(self, node: onnx.NodeProto) -> bool:
        """Whether a convolution has no bias or one no other node reads (it can grow with the filters)."""
        return len(node.input) <= 2 or not node.input[2] or self.weight(node, 2) is not None

    def only_consumer(self, tensor: str) -> onnx.NodeProto | None:
        readers = self.consumers.get(tensor, [])
        return readers[0] if len(readers) == 1 and tensor not in self.outputs else None


def _chain(graph: _Graph, producer: onnx.NodeProto, channels: int):
    """The nodes from ``producer``'s output to the plain convolution that consumes it, when every tensor on the
    way has one reader and every node keeps zero channels at zero: (middle nodes, consumer), else None."""
    middle, tensor = [], producer.output[0]
    while True:
        node = graph.only_consumer(tensor)
        if node is None:
            return None
        if node.op_type == "Conv":
            weight = graph.weight(node, 1)
            if weight is None:
                return None
            group = node_attribute(node, "group", 1)
            if group == channels and weight.shape[:2] == (channels, 1):  # depthwise: its filters pad too
                if not graph.paddable_bias(node):
                    return None
                middle.append(node)
                tensor = node.output[0]
                continue
            if group == 1 and weight.shape[1] == channels:
                return middle, node
            return None
        if node.op_type not in ZERO_PRESERVING or len([o for o in node.output if o]) != 1:
            return None
        middle.append(node)
        tensor = node.output[0]


def _pad_rows(values: np.ndarray, extra: int, axis: int = 0) -> np.ndarray:
    shape = list(values.shape)
    shape[axis] = extra
    return np.concatenate([values, np.zeros(shape, values.dtype)], axis=axis)


def _set_channels(graph: onnx.GraphProto, tensors: set[str], channels: int) -> None:
    """Shape annotations of the padded tensors follow their new channel count."""
    for value in graph.value_info:
        if value.name in tensors and value.type.tensor_type.shape.dim[1:2]:
            value.type.tensor_type.shape.dim[1].dim_value = channels


def pad_pooled_channels(model: onnx.ModelProto, multiple: int) -> tuple[onnx.ModelProto, list[PaddedChain]]:
    """A copy of ``model`` with every chain convolution -> (ReLU, max-pool, depthwise convolution)* -> convolution
    that holds a max-pool and whose width is not a multiple of ``multiple`` padded to one with zero channels (see
    the module docstring); the chains padded. ``multiple`` <= 1 pads nothing."""
    padded_model = onnx.ModelProto()
    padded_model.CopyFrom(model)
    if multiple <= 1:
        return padded_model, []
    graph = _Graph(padded_model.graph)
    chains = []
    for producer in list(padded_model.graph.node):
        weight = graph.weight(producer, 1) if producer.op_type == "Conv" else None
        if weight is None or node_attribute(producer, "group", 1) != 1 or weight.shape[0] % multiple == 0:
            continue
        channels = weight.shape[0]
        found = _chain(graph, producer, channels) if graph.paddable_bias(producer) else None
        if found is None or not any(node.op_type == "MaxPool" for node in found[0]):
            continue
        middle, consumer = found
        extra = -channels % multiple
        depthwise = [node for node in middle if node.op_type == "Conv"]
        for node in [producer] + depthwise:  # zero filters, zero biases
            for position in (1, 2):
                values = graph.weight(node, position)
                if values is not None:
                    graph.set_weight(node, position, _pad_rows(values, extra))
        for attribute in (attribute for node in depthwise for attribute in node.attribute):
            if attribute.name == "group":
                attribute.i = channels + extra
        graph.set_weight(consumer, 1, _pad_rows(graph.weight(consumer, 1), extra, axis=1))
        _set_channels(padded_model.graph, {producer.output[0]} | {node.output[0] for node in middle}, channels + extra)
        chains.append(PaddedChain(producer.name, channels, channels + extra, consumer.name))
    return padded_model, chains
