"""FP16 ONNX graphs for onnxruntime (`export --precision fp16`, `quantise --mode fp16`)."""
from __future__ import annotations

import onnx

from export.graph_order import topologically_sorted


def to_fp16(model: onnx.ModelProto) -> onnx.ModelProto:
    """Every float tensor in FP16, inputs and outputs kept FP32 (Cast at the edges).

    The keypoint post-processing converts too: its gather indices are int32 arithmetic on values exact in
    FP16 (`models/keypoints.py`, `models/deform.py`), so a flat pixel index never passes through half
    precision, whose 65,504 maximum a 240x320 image already exceeds. Shipped ReLU weights: 99.1 % of
    keypoints unchanged against FP32 on the parity images. The converter appends the input Casts after
    their consumers, so the result is sorted again.
    """
    from onnxruntime.transformers.float16 import convert_float_to_float16

    return topologically_sorted(convert_float_to_float16(model, keep_io_types=True))
