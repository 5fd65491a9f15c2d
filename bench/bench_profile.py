"""FeatureNet vs the SuperPoint architecture in onnxruntime: latency ratio at 240x320 and 480x640, FP32 and INT8.

Every graph is the deployed x86-cpu keypoint graph (network + NMS + top-K + descriptor sampling, native
DeformConv, opset 19), with random weights (latency does not depend on weight values). All graphs of one
resolution are timed interleaved, round by round, in one run, so machine noise hits them alike; the
script prints medians and the SuperPoint / FeatureNet ratio (> 1: FeatureNet is faster).

INT8 is onnxruntime static QDQ on the Conv nodes only (per-channel S8 weights, U8 activations, MinMax
calibration on a few real images from ../shared/data/train_images), the two head output convs in float:
`toolkit.compression.quantise.quantise_int8` (issue 7) when it is importable, else the same recipe here.

    python bench/bench_profile.py                  # 1 thread, 20 rounds
    python bench/bench_profile.py --threads 2 --rounds 40
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from export.parity import prepare_image  # noqa: E402
from profiles import load_profile  # noqa: E402
from toolkit.profiling.latency import ort_runner, ort_session, time_interleaved  # noqa: E402
from toolkit.profiling.profile import target_graph  # noqa: E402
from toolkit.profiling.sources import resolve_model  # noqa: E402

SIZES = ((240, 320), (480, 640))
MODELS = ("featurenet", "featurenet-relu", "superpoint")
CALIBRATION_IMAGES = 8
TRAIN_IMAGES = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "train_images"


def calibration_images(height: int, width: int, count: int = CALIBRATION_IMAGES) -> np.ndarray:
    """``count`` real photos, evenly spread over the sorted folder, prepared like runtime frames: [N, 1, H, W]."""
    paths = sorted(p for p in TRAIN_IMAGES.rglob("*.jpg"))
    picks = [paths[i] for i in np.linspace(0, len(paths) - 1, count).round().astype(int)]
    return np.concatenate([prepare_image(path, height, width) for path in picks])


def _head_output_convs(model: onnx.ModelProto) -> list[str]:
    """Conv nodes whose output reaches no other Conv/DeformConv (the 65-logit and descriptor 1x1 convs)."""
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    terminal = []
    for conv in (n for n in model.graph.node if n.op_type == "Conv"):
        stack, seen, feeds_conv = list(conv.output), set(), False
        while stack and not feeds_conv:
            name = stack.pop()
            for node in consumers.get(name, []):
                feeds_conv |= node.op_type in ("Conv", "DeformConv")
                stack.extend(out for out in node.output if out not in seen)
                seen.update(node.output)
        if not feeds_conv:
            terminal.append(conv.name)
    return terminal


def quantise(model: onnx.ModelProto, images: np.ndarray) -> tuple[onnx.ModelProto, str]:
    """INT8 QDQ of ``model`` and which implementation did it."""
    try:
        from toolkit.compression.quantise import quantise_int8
        from toolkit.compression.sensitivity import head_output_convs
    except ImportError:
        return _quantise_here(model, images), "onnxruntime.quantization static QDQ in this script"
    return quantise_int8(model, images, head_output_convs(model)), "toolkit.compression.quantise.quantise_int8 (issue 7)"


def _quantise_here(model: onnx.ModelProto, images: np.ndarray) -> onnx.ModelProto:
    import tempfile

    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    class Reader:
        def __init__(self) -> None:
            self.feeds = iter([{model.graph.input[0].name: image[None]} for image in images])

        def get_next(self):
            return next(self.feeds, None)

    with tempfile.TemporaryDirectory() as work:
        source, target = Path(work) / "fp32.onnx", Path(work) / "int8.onnx"
        onnx.save(model, str(source))
        quantize_static(str(source), str(target), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, op_types_to_quantize=["Conv"],
                        nodes_to_exclude=_head_output_convs(model), calibrate_method=CalibrationMethod.MinMax)
        return onnx.load(str(target))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--no-int8", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    profile = load_profile("x86-cpu")
    print(f"onnxruntime {ort.__version__}, {args.threads} thread(s), {args.rounds} interleaved rounds per size, "
          "x86-cpu keypoint graphs, random weights")
    for height, width in SIZES:
        graphs = {}
        images = None if args.no_int8 else calibration_images(height, width)
        for name in MODELS:
            fp32 = target_graph(resolve_model(name, None), profile, height, width).model
            graphs[(name, "fp32")] = fp32
            if images is not None:
                graphs[(name, "int8")], how = quantise(fp32, images)
        runners = {key: ort_runner(ort_session(model, args.threads)) for key, model in graphs.items()}
        samples = time_interleaved(runners, args.rounds)
        median = {key: statistics.median(values) for key, values in samples.items()}
        print(f"\n{height}x{width}")
        print(f"{'model':18s} {'precision':9s} {'median ms':>10s} {'SuperPoint / model':>19s}")
        for (name, precision), value in median.items():
            print(f"{name:18s} {precision:9s} {value:10.2f} {median[('superpoint', precision)] / value:18.2f}x")
        for precision in ("fp32", "int8"):
            if ("featurenet", precision) in median:
                ratio = median[("featurenet", precision)] / median[("superpoint", precision)]
                print(f"latency ratio FeatureNet / SuperPoint, {precision}: {ratio:.3f}")
        if images is not None:
            print(f"INT8 by {how}")


if __name__ == "__main__":
    main()
