"""Choose FeatureNet's widths and block order by onnxruntime latency, against SuperPoint in the same run.

MACs do not make speed on a CPU: depthwise convs and ELU are memory-bound. This script exports each
candidate's dense graph (heads only; the keypoint post-processing is the same for all), then times all
candidates interleaved round by round, so machine noise hits them alike, and prints medians and the
speed-up over the SuperPoint architecture measured in the same run.

    python bench/bench_backbone.py                      # 240x320, 1 thread
    python bench/bench_backbone.py --size 480x640 --threads 2
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import onnxruntime as ort
import torch
from torch.utils.flop_counter import FlopCounterMode

from export.graphs import DENSE_OUTPUTS, DenseGraph
from export.onnx_export import export_onnx
from models.deform import set_deform_strategy
from models.featurenet import FeatureNet, FeatureNetConfig
from models.superpoint import SuperPointNet

CANDIDATES: dict[str, tuple[FeatureNetConfig, str]] = {
    "default (elu, native deform)": (FeatureNetConfig(), "native"),
    "default, portable deform": (FeatureNetConfig(), "torch"),
    "relu variant": (FeatureNetConfig(activation="relu"), "native"),
    "no deformable conv": (FeatureNetConfig(deformable=False), "native"),
    "+1 full-res block": (FeatureNetConfig(blocks=[1, 1, 2, 2]), "native"),
    "wider (24/48/96/128)": (FeatureNetConfig(widths=[24, 48, 96, 128]), "native"),
    "thin heads (96)": (FeatureNetConfig(head_channels=96), "native"),
    "deformable at H/4 instead": (FeatureNetConfig(deform_scale=2), "native"),
}


def count_macs(model: torch.nn.Module, height: int, width: int) -> float:
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        model(torch.rand(1, 1, height, width))
    return counter.get_total_flops() / 2


def build_session(model: torch.nn.Module, strategy: str, height: int, width: int, threads: int):
    set_deform_strategy(model, strategy)
    opset = 19 if strategy == "native" else 13
    exported = export_onnx(DenseGraph(model).eval(), torch.zeros(1, 1, height, width), opset, DENSE_OUTPUTS)
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    return ort.InferenceSession(exported.model.SerializeToString(), options, providers=["CPUExecutionProvider"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="240x320")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=30)
    args = parser.parse_args()
    height, width = (int(v) for v in args.size.split("x"))
    torch.manual_seed(0)
    torch.set_num_threads(1)

    rows = {"SuperPoint architecture": (SuperPointNet().eval(), "torch")}
    rows.update({name: (FeatureNet(cfg).eval(), strategy) for name, (cfg, strategy) in CANDIDATES.items()})
    sessions, stats = {}, {}
    for name, (model, strategy) in rows.items():
        stats[name] = (sum(p.numel() for p in model.parameters()), count_macs(model, height, width))
        sessions[name] = build_session(model, strategy, height, width, args.threads)
    image = np.random.default_rng(0).random((1, 1, height, width), dtype=np.float32)
    timings: dict[str, list[float]] = {name: [] for name in sessions}
    for session in sessions.values():
        for _ in range(3):
            session.run(None, {"image": image})
    for _ in range(args.rounds):
        for name, session in sessions.items():
            start = time.perf_counter()
            session.run(None, {"image": image})
            timings[name].append((time.perf_counter() - start) * 1e3)

    reference = statistics.median(timings["SuperPoint architecture"])
    print(f"onnxruntime {ort.__version__}, {height}x{width}, {args.threads} thread(s), {args.rounds} interleaved rounds")
    print(f"{'model':32s} {'params':>9s} {'GMACs':>7s} {'median ms':>10s} {'p90 ms':>8s} {'speed-up vs SP':>15s}")
    for name, values in timings.items():
        params, macs = stats[name]
        median = statistics.median(values)
        p90 = float(np.percentile(values, 90))
        print(f"{name:32s} {params / 1e6:8.3f}M {macs / 1e9:7.3f} {median:10.2f} {p90:8.2f} {reference / median:14.2f}x")


if __name__ == "__main__":
    main()
