"""Putting a graph's nodes in topological order after a transformation that adds nodes.

The ONNX spec requires every node to follow the producers of its inputs, and TensorRT's parser and other
strict consumers read nodes in file order. onnxruntime sorts for itself, so an out-of-order graph still runs
there: onnxruntime's float16 converter appends the input Casts after their consumers, and nothing but
onnx.checker would notice.
"""
from __future__ import annotations

import heapq

import onnx

from export.errors import ExportError


def _subgraphs(node: onnx.NodeProto) -> list[onnx.GraphProto]:
    """The bodies of an If / Loop / Scan node (empty for every other node)."""
    graphs: list[onnx.GraphProto] = []
    for attribute in node.attribute:
        if attribute.type == onnx.AttributeProto.GRAPH:
            graphs.append(attribute.g)
        elif attribute.type == onnx.AttributeProto.GRAPHS:
            graphs.extend(attribute.graphs)
    return graphs


def _names_read(node: onnx.NodeProto) -> set[str]:
    """The node's inputs plus every name its subgraphs read: a body may use outer tensors by name."""
    names = {name for name in node.input if name}
    for graph in _subgraphs(node):
        for inner in graph.node:
            names |= _names_read(inner)
    return names


def sort_topologically(graph: onnx.GraphProto) -> None:
    """Reorder ``graph.node`` (and its subgraphs') in place so that each node follows its inputs' producers.

    Kahn's algorithm taking the ready node that came first in the old order, so a sorted graph is left
    exactly as it was and a nearly sorted one moves as little as possible. `ExportError` on a cycle.
    """
    nodes = list(graph.node)
    producer = {name: index for index, node in enumerate(nodes) for name in node.output if name}
    # Names no node produces (graph inputs, initializers, outer-scope tensors) are there from the start.
    inputs_from = [{producer[name] for name in _names_read(node) if name in producer} for node in nodes]
    consumers: list[list[int]] = [[] for _ in nodes]
    for index, sources in enumerate(inputs_from):
        for source in sources:
            consumers[source].append(index)
    waiting = [len(sources) for sources in inputs_from]
    ready = [index for index, count in enumerate(waiting) if count == 0]
    heapq.heapify(ready)
    order: list[int] = []
    while ready:
        index = heapq.heappop(ready)
        order.append(index)
        for consumer in consumers[index]:
            waiting[consumer] -= 1
            if waiting[consumer] == 0:
                heapq.heappush(ready, consumer)
    if len(order) < len(nodes):
        stuck = next(node for index, node in enumerate(nodes) if waiting[index])
        raise ExportError(f"the graph has a cycle through node {stuck.name or stuck.op_type}: it cannot be ordered")
    for node in nodes:
        for subgraph in _subgraphs(node):
            sort_topologically(subgraph)
    if order == sorted(order):
        return
    ordered = [onnx.NodeProto() for _ in order]
    for copy, index in zip(ordered, order):  # copied first: clearing the field detaches the old messages
        copy.CopyFrom(nodes[index])
    graph.ClearField("node")
    graph.node.extend(ordered)


def topologically_sorted(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with its nodes sorted (`sort_topologically`); the same object, for chaining."""
    sort_topologically(model.graph)
    return model
