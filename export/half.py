"""FP16 ONNX graphs for onnxruntime: the network in half precision, keypoint post-processing in FP32."""
from __future__ import annotations

import onnx


def keypoint_postprocessing_nodes(model: onnx.ModelProto) -> list[str]:
    """Names of the nodes downstream of every TopK: the keypoint coordinates, the flat indices of sub-pixel
    refinement and descriptor sampling. They must stay FP32: a flat pixel index (up to 76,799 at 240x320)
    overflows half precision (max 65,504), and integers above 2,048 are no longer exact in it."""
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    blocked: dict[str, None] = {}
    frontier = [node for node in model.graph.node if node.op_type == "TopK"]
    while frontier:
        node = frontier.pop()
        if node.name in blocked:
            continue
        blocked[node.name] = None
        for output in node.output:
            frontier.extend(consumers.get(output, []))
    return list(blocked)


def to_fp16(model: onnx.ModelProto) -> onnx.ModelProto:
    """FP16 weights and activations for the network; keypoint post-processing stays FP32."""
    from onnxruntime.transformers.float16 import DEFAULT_OP_BLOCK_LIST, convert_float_to_float16

    for index, node in enumerate(model.graph.node):  # blocking works by node name
        node.name = node.name or f"{node.op_type}_{index}"
    blocked = keypoint_postprocessing_nodes(model)
    converted = convert_float_to_float16(model, keep_io_types=True, op_block_list=list(DEFAULT_OP_BLOCK_LIST),
                                         node_block_list=blocked)
    _drop_half_round_trips(converted, set(blocked))
    return converted


def _drop_half_round_trips(model: onnx.ModelProto, fp32_nodes: set[str]) -> None:
    """The converter still routes values between two FP32 (blocked) nodes through a Cast to FP16 and back,
    which loses the very integers blocking was for. Read the FP32 value directly instead; the dead casts go."""
    producer = {output: node for node in model.graph.node for output in node.output}
    for node in model.graph.node:
        if node.op_type != "Cast" or onnx.helper.get_attribute_value(node.attribute[0]) != onnx.TensorProto.FLOAT:
            continue
        half = producer.get(node.input[0])
        if half is None or half.op_type != "Cast" or producer.get(half.input[0]) is None:
            continue
        if producer[half.input[0]].name in fp32_nodes:
            node.input[0] = half.input[0]  # a float -> float Cast: an identity
    used = {name for node in model.graph.node for name in node.input} | {o.name for o in model.graph.output}
    dead = [node for node in model.graph.node if node.op_type == "Cast" and not any(o in used for o in node.output)]
    for node in dead:
        model.graph.node.remove(node)
