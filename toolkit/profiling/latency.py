"""Measured latency on this host: onnxruntime on the exported graph, PyTorch eager for reference.

Every measurement warms up first (first runs allocate buffers and pick kernels), then times repeated
runs and keeps the median and the 90th percentile: on a shared machine the mean is dragged by outliers.
Several candidates are timed interleaved, round by round, so machine noise hits them alike.
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

from vo_runtime.progress import progress_bar


@dataclass
class LatencyStats:
    """Wall-clock latency of one forward pass, in milliseconds."""

    engine: str
    threads: int
    median_ms: float
    p90_ms: float
    repeats: int
    warmup: int

    def to_dict(self) -> dict:
        return asdict(self)


def ort_session(model: onnx.ModelProto | bytes, threads: int) -> ort.InferenceSession:
    """A CPU session with ``threads`` intra-op threads and full graph optimisation (Conv+ReLU fusion etc.)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    payload = model if isinstance(model, bytes) else model.SerializeToString()
    return ort.InferenceSession(payload, options, providers=["CPUExecutionProvider"])


def ort_runner(session: ort.InferenceSession) -> Callable[[], object]:
    """A no-argument callable running ``session`` on a fixed random input of its declared shape."""
    feeds = {}
    rng = np.random.default_rng(0)
    for tensor in session.get_inputs():
        shape = [int(d) for d in tensor.shape]
        feeds[tensor.name] = rng.random(shape, dtype=np.float32)
    return lambda: session.run(None, feeds)


def torch_runner(module: nn.Module, image: torch.Tensor) -> Callable[[], object]:
    """A no-argument callable running ``module`` eagerly on ``image`` without autograd."""
    def run() -> object:
        with torch.inference_mode():
            return module(image)
    return run


def time_interleaved(
    runners: dict[str, Callable[[], object]], repeats: int, warmup: int = 3
) -> dict[str, list[float]]:
    """Warm every runner up, then time ``repeats`` rounds, each running every runner once (ms)."""
    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    for run in runners.values():
        for _ in range(warmup):
            run()
    timings: dict[str, list[float]] = {name: [] for name in runners}
    for _ in progress_bar(range(repeats), desc=f"timing {len(runners)} graph(s)", unit="round", leave=False):
        for name, run in runners.items():
            start = time.perf_counter()
            run()
            timings[name].append((time.perf_counter() - start) * 1e3)
    return timings


def summarise(samples_ms: list[float], engine: str, threads: int, warmup: int) -> LatencyStats:
    """Median and p90 of one runner's samples."""
    return LatencyStats(
        engine=engine,
        threads=threads,
        median_ms=float(statistics.median(samples_ms)),
        p90_ms=float(np.percentile(samples_ms, 90)),
        repeats=len(samples_ms),
        warmup=warmup,
    )

