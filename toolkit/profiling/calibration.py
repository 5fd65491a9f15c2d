"""`toolkit profile --calibrate`: fit the host profile's roofline figures from measurements on this host.

1. Peak compute (a large MatMul) and memory bandwidth (a large elementwise Add) in onnxruntime.
   Also the bandwidth of each cache level (L2, L3 from sysfs): small activations never reach DRAM.
2. Micro-layers (one op kind each, at sizes the networks use) and whole networks, all timed interleaved.
3. A weighted non-negative least-squares fit of 1 / efficiency per kind and a per-layer overhead
   (`roofline.design_row` makes the model linear), rows weighted by 1 / measured time so every row counts
   by its relative error, with a weak pull towards the profile's prior figures for kinds the data hardly
   constrains.
4. Leave-one-out: each network is predicted by a fit made without it; that error is what is reported.
"""
from __future__ import annotations

import os
import platform
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper
from scipy.optimize import nnls
from torch import nn

from export.onnx_export import trace_to_onnx
from models.deform import DeformableConv, set_deform_strategy
from models.featurenet import ELU, set_elu_form
from toolkit.profiling.counts import KINDS, LayerCost, onnx_layer_costs
from toolkit.profiling.latency import ort_runner, ort_session, summarise, time_interleaved
from toolkit.profiling.roofline import HardwareModel, design_row
from vo_runtime.progress import progress_bar

FEATURES = (*KINDS, "layers", "run")
MIN_INVERSE_EFFICIENCY = 0.01
PRIOR_WEIGHT = 0.05
CHAIN = 3  # a prior row counts as 5 % of one measured row: it only decides what the data leaves open
# A network's row counts as three micro-layers': the fit exists to predict networks (leave-one-out on this host's
# measurements: featurenet-relu -15 % -> -5 %, featurenet -21 % -> -16 % under load, no worse where it was good).
NETWORK_WEIGHT = 3.0
LOO_LIMIT = 0.25  # a leave-one-out error past this is reported with the terms the fit could not predict


@dataclass
class Measured:
    """One timed graph: its name, layers, and median latency (s)."""

    name: str
    layers: list[LayerCost]
    seconds: float
    is_network: bool = False


@dataclass
class FitResult:
    inverse_efficiency: dict[str, float]  # 1 / efficiency per kind
    overhead_s: float  # per running layer
    run_overhead_s: float = 0.0  # once per inference call (session.run, input/output handling)

    def predict(self, row: dict[str, float]) -> float:
        fixed = row["layers"] * self.overhead_s + row.get("run", 0.0) * self.run_overhead_s
        return sum(row[k] * self.inverse_efficiency[k] for k in KINDS) + fixed

    def efficiency(self) -> dict[str, float]:
        return {k: 1.0 / v for k, v in self.inverse_efficiency.items()}


@dataclass
class CalibrationResult:
    peak_gflops_fp32: float
    memory_bandwidth_gbs: float
    efficiency: dict[str, float]
    overhead_us: float
    run_overhead_us: float
    threads: int
    leave_one_out: list[dict] = field(default_factory=list)  # per network: measured, predicted, error
    micro_layers: list[dict] = field(default_factory=list)
    host: str = ""
    created: str = ""
    cache_levels: list[dict] = field(default_factory=list)

    def to_json_dict(self) -> dict:
        data = asdict(self)
        data["peak_gflops_fp16"] = self.peak_gflops_fp32  # onnxruntime's CPU provider has no faster FP16 path
        data["sources"] = [f"measured by `toolkit profile --calibrate` on {self.host} at {self.threads} thread(s), {self.created}"]
        return data


def fit_factors(rows: list[dict[str, float]], seconds: list[float], prior: FitResult, prior_weight: float = PRIOR_WEIGHT,
                weights: list[float] | None = None) -> FitResult:
    """Weighted NNLS for 1/efficiency per kind and the overheads: seconds ~ sum_k row[k] c_k + layers o + run r.

    Args:
        rows: `design_row` dicts, one per measured graph.
        seconds: measured median seconds, same order.
        prior: figures to fall back on where the rows say nothing.
        weights: how much each row's relative error counts (default 1 each).
    """
    scale = {feature: max(max((row[feature] for row in rows), default=0.0), 1e-12) for feature in FEATURES}
    matrix, target = [], []
    for row, measured, weight in zip(rows, seconds, weights or [1.0] * len(rows)):
        matrix.append([weight * row[f] / scale[f] / measured for f in FEATURES])  # relative error per row
        target.append(weight)
    prior_values = [*(prior.inverse_efficiency[k] for k in KINDS), prior.overhead_s, prior.run_overhead_s]
    for index, feature in enumerate(FEATURES):
        # Residual prior_weight * (value / prior - 1): relative, so the pull is the same for every feature.
        # The unknown is value * scale, hence the scale in the denominator.
        unit = [0.0] * len(FEATURES)
        unit[index] = prior_weight / (prior_values[index] * scale[feature]) if prior_values[index] > 0 else prior_weight
        matrix.append(unit)
        target.append(prior_weight if prior_values[index] > 0 else 0.0)
    solution, _ = nnls(np.asarray(matrix), np.asarray(target))
    values = {f: float(solution[i] / scale[f]) for i, f in enumerate(FEATURES)}
    # NNLS may zero a factor the data cannot see; cap the efficiency at 100x the DRAM roofline instead.
    return FitResult({k: max(values[k], MIN_INVERSE_EFFICIENCY) for k in KINDS}, values["layers"], values["run"])


# ---------------------------------------------------------------- host peak figures


def _single_node_model(op: str, inputs: list[tuple[str, list[int]]], output_shape: list[int], initializer=None) -> onnx.ModelProto:
    graph = helper.make_graph(
        [helper.make_node(op, [name for name, _ in inputs], ["out"])],
        op,
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, shape) for name, shape in inputs if initializer is None or name != initializer.name],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, output_shape)],
        initializer=[initializer] if initializer is not None else [],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def measure_peak_gflops(threads: int, size: int = 768, repeats: int = 10) -> float:
    """FP32 GFLOP/s of a size^3 MatMul in onnxruntime (the best a dense kernel gets on this host)."""
    weights = helper.make_tensor("b", TensorProto.FLOAT, [size, size], np.random.default_rng(0).random(size * size, dtype=np.float32))
    model = _single_node_model("MatMul", [("a", [size, size]), ("b", [size, size])], [size, size], weights)
    samples = time_interleaved({"matmul": ort_runner(ort_session(model, threads))}, repeats, warmup=2)["matmul"]
    return 2.0 * size**3 / (min(samples) * 1e-3) / 1e9


def _add_model(elements: int) -> onnx.ModelProto:
    one = helper.make_tensor("one", TensorProto.FLOAT, [1], [1.0])
    return _single_node_model("Add", [("x", [elements]), ("one", [1])], [elements], one)


def measure_bandwidth_gbs(threads: int, traffic_bytes: int = 1 << 27, repeats: int = 10) -> float:
    """GB/s of an elementwise Add that reads and writes ``traffic_bytes`` in all (default 128 MB: DRAM).

    The time of a 1024-element Add (the per-call overhead) is subtracted, which matters for cache-sized runs.
    """
    elements = max(traffic_bytes // 8, 1 << 14)
    runners = {"add": ort_runner(ort_session(_add_model(elements), threads)),
               "tiny": ort_runner(ort_session(_add_model(1024), threads))}
    samples = time_interleaved(runners, repeats, warmup=2)
    seconds = max(min(samples["add"]) - min(samples["tiny"]), 0.05 * min(samples["add"])) * 1e-3
    return 2 * 4 * elements / seconds / 1e9


def cache_sizes() -> list[int]:
    """Capacities (bytes) of the data caches above L1 that core 0 sees (L2, L3), from sysfs; [] if unknown."""
    sizes = []
    for index in sorted(Path("/sys/devices/system/cpu/cpu0/cache").glob("index*")):
        try:
            level = int((index / "level").read_text())
            kind = (index / "type").read_text().strip()
            text = (index / "size").read_text().strip().upper()
        except (OSError, ValueError):
            continue
        if level < 2 or kind == "Instruction":
            continue
        factor = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1], 1)
        sizes.append(int(text.rstrip("KMG")) * factor)
    return sorted(sizes)


def measure_cache_levels(threads: int, repeats: int = 20) -> list[dict]:
    """Bandwidth of an Add whose traffic fills half of each cache level (the other half is left to others)."""
    return [{"bytes": size, "bandwidth_gbs": measure_bandwidth_gbs(threads, size // 2, repeats)} for size in cache_sizes()]


# ---------------------------------------------------------------- micro-layers


# The host runs onnxruntime, whose graphs trace ELU as max(x, exp(min(x, 0)) - 1) (`TargetProfile.elu_form`):
# the micro-layers time that form, not the Elu op the networks never contain.
HOST_ELU_FORM = "max_exp"
TINY_OPS = 16  # the overhead micro-layer: this many elementwise layers on a tensor too small to cost anything


class _ScaleShift(nn.Module):
    """x * 0.5 + 0.25: two elementwise layers (Mul, Add), as the networks' arithmetic between convs."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * 0.5 + 0.25


class _Softmax(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.softmax(x, dim=1)


class _Normalize(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.normalize(x, p=2.0, dim=1)


class _PixelShuffle(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.pixel_shuffle(x, 8)


class _MatMul(nn.Module):
    def __init__(self, k: int, n: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(k, n) * 0.05)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.matmul(x, self.weight)


def _chain(make, count: int = CHAIN) -> nn.Module:
    """``count`` shape-preserving copies in a row: layout changes at the graph's ends are paid once, as in a network."""
    return nn.Sequential(*(make() for _ in range(count)))


def _elu() -> nn.Module:
    return set_elu_form(ELU(), HOST_ELU_FORM)


def micro_layers(height: int, width: int) -> dict[str, tuple[nn.Module, list[int]]]:
    """One module per op kind, at the widths and scales FeatureNet and SuperPoint use for an HxW input."""
    h2, w2, h4, w4, h8, w8 = height // 2, width // 2, height // 4, width // 4, height // 8, width // 8
    deform = DeformableConv(128, 128)
    nn.init.normal_(deform.offset_pw.weight, std=0.01)  # non-zero offsets, as in a trained layer
    set_deform_strategy(deform, "native")
    return {
        "conv3x3 1->16 @H": (nn.Conv2d(1, 16, 3, padding=1), [1, 1, height, width]),
        "conv3x3 64->64 @H/2 x3": (_chain(lambda: nn.Conv2d(64, 64, 3, padding=1)), [1, 64, h2, w2]),
        "conv3x3 128->128 @H/8 x3": (_chain(lambda: nn.Conv2d(128, 128, 3, padding=1)), [1, 128, h8, w8]),
        "depthwise 32 @H/2 x3": (_chain(lambda: nn.Conv2d(32, 32, 3, padding=1, groups=32)), [1, 32, h2, w2]),
        "depthwise 64 @H/4 x3": (_chain(lambda: nn.Conv2d(64, 64, 3, padding=1, groups=64)), [1, 64, h4, w4]),
        "pointwise 64->64 @H/4 x3": (_chain(lambda: nn.Conv2d(64, 64, 1)), [1, 64, h4, w4]),
        "pointwise 128->256 @H/8": (nn.Conv2d(128, 256, 1), [1, 128, h8, w8]),
        "deform 128 @H/8": (deform, [1, 128, h8, w8]),
        # Between convs, as in the networks: onnxruntime's blocked (NCHWc) conv layout has to be converted
        # back and forth around an ELU, which costs more than the ELU itself.
        "(pointwise + elu) 16 @H x3": (_chain(lambda: nn.Sequential(nn.Conv2d(16, 16, 1), _elu())), [1, 16, height, width]),
        "(pointwise + elu) 64 @H/4 x3": (_chain(lambda: nn.Sequential(nn.Conv2d(64, 64, 1), _elu())), [1, 64, h4, w4]),
        # Without these two the data left the elementwise efficiency and the per-layer overhead to the
        # networks alone, and a network left out of the fit took them with it (leave-one-out +26 %, -25 %).
        "elementwise 32 @H/2 x3": (_chain(_ScaleShift), [1, 32, h2, w2]),
        f"{2 * TINY_OPS} tiny elementwise (overhead)": (_chain(_ScaleShift, TINY_OPS), [1, 8, 4, 4]),
        "maxpool 64 @H": (nn.MaxPool2d(2, 2), [1, 64, height, width]),
        "maxpool9 nms @H": (nn.MaxPool2d(9, 1, 4), [1, 1, height, width]),
        "softmax 65 @H/8": (_Softmax(), [1, 65, h8, w8]),
        "pixel-shuffle 64 @H/8": (_PixelShuffle(), [1, 64, h8, w8]),
        "l2-normalise 256 @H/8": (_Normalize(), [1, 256, h8, w8]),
        "matmul 128x256 @H/8": (_MatMul(128, 256), [1, h8 * w8, 128]),
    }


def export_micro_layers(height: int, width: int) -> dict[str, onnx.ModelProto]:
    """Every micro-layer as an ONNX graph (opset 19, onnxruntime's DeformConv)."""
    torch.manual_seed(0)
    graphs = {}
    for name, (module, shape) in progress_bar(micro_layers(height, width).items(), desc="micro-layers", unit="layer", leave=False):
        graphs[name] = trace_to_onnx(module.eval(), torch.rand(shape), 19, ("out",))
    return graphs


def measure_graphs(graphs: dict[str, onnx.ModelProto], networks: set[str], threads: int, repeats: int, warmup: int) -> list[Measured]:
    """Time all graphs interleaved (machine noise hits micro-layers and networks alike); medians."""
    runners = {name: ort_runner(ort_session(model, threads)) for name, model in graphs.items()}
    samples = time_interleaved(runners, repeats, warmup)
    return [Measured(name, onnx_layer_costs(model), summarise(samples[name], "onnxruntime", threads, warmup).median_ms * 1e-3,
                     name in networks) for name, model in graphs.items()]


def term_ms(fit: FitResult, row: dict[str, float]) -> dict[str, float]:
    """What each term of the model contributes to a graph's predicted time (ms): every kind, and the overheads."""
    terms = {kind: row[kind] * fit.inverse_efficiency[kind] * 1e3 for kind in KINDS}
    terms["overhead"] = (row["layers"] * fit.overhead_s + row.get("run", 0.0) * fit.run_overhead_s) * 1e3
    return terms


def unpredicted_terms(full: FitResult, without: FitResult, row: dict[str, float], most: int = 2) -> list[str]:
    """The terms of a left-out graph that the fit without it got most wrong against the fit with it."""
    with_it, left_out = term_ms(full, row), term_ms(without, row)
    moved = sorted(with_it, key=lambda term: -abs(left_out[term] - with_it[term]))[:most]
    return [f"{term} {with_it[term]:.2f} -> {left_out[term]:.2f} ms" for term in moved
            if abs(left_out[term] - with_it[term]) >= 0.01]


def leave_one_out(measured: list[Measured], hardware: HardwareModel, prior: FitResult) -> tuple[FitResult, list[dict]]:
    """Fit on everything; and for each network, fit without it and predict it."""
    rows = [design_row(m.layers, hardware) for m in measured]
    seconds = [m.seconds for m in measured]
    weights = [NETWORK_WEIGHT if m.is_network else 1.0 for m in measured]
    full = fit_factors(rows, seconds, prior, weights=weights)
    errors = []
    for index, item in enumerate(measured):
        if not item.is_network:
            continue
        keep = [i for i in range(len(measured)) if i != index]
        fit = fit_factors([rows[i] for i in keep], [seconds[i] for i in keep], prior, weights=[weights[i] for i in keep])
        predicted = fit.predict(rows[index])
        error = predicted / item.seconds - 1.0
        errors.append({"network": item.name, "measured_ms": item.seconds * 1e3, "predicted_ms": predicted * 1e3,
                       "relative_error": error, "in_sample_predicted_ms": full.predict(rows[index]) * 1e3,
                       "unpredicted_terms": unpredicted_terms(full, fit, rows[index]) if abs(error) > LOO_LIMIT else []})
    return full, errors


def leave_one_out_note(entry: dict) -> str | None:
    """A plain line for a network the fit could not predict within `LOO_LIMIT` (None when it could)."""
    if abs(entry["relative_error"]) <= LOO_LIMIT:
        return None
    in_sample = entry["in_sample_predicted_ms"] / entry["measured_ms"] - 1.0
    terms = "; ".join(entry["unpredicted_terms"]) or "no single term"
    reason = (f"even fitted on it the model is {in_sample:+.0%} off, so no term describes that share (often load "
              "from other processes while measuring: rerun on a quiet host)" if abs(in_sample) > LOO_LIMIT else
              "the other graphs do not pin down these terms of it")
    return (f"note: {entry['network']} is predicted {entry['relative_error']:+.0%} off from the other graphs "
            f"(limit {LOO_LIMIT:.0%}): the terms it cannot predict are {terms} (with it -> without it); {reason}")


def host_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu} ({platform.system()}, {os.cpu_count()} logical CPUs)"


def calibrate(networks: dict[str, onnx.ModelProto], height: int, width: int, threads: int, repeats: int, warmup: int,
              prior: HardwareModel) -> CalibrationResult:
    """Measure peaks, cache and DRAM bandwidth, micro-layers and ``networks``; fit; leave-one-out errors."""
    measured_hw = replace(prior, peak_gflops=measure_peak_gflops(threads), bandwidth_gbs=measure_bandwidth_gbs(threads),
                          cache_levels=[(level["bytes"], level["bandwidth_gbs"]) for level in measure_cache_levels(threads)])
    graphs = {**export_micro_layers(height, width), **networks}
    measured = measure_graphs(graphs, set(networks), threads, repeats, warmup)
    start = FitResult({k: 1.0 / prior.efficiency[k] for k in KINDS}, prior.overhead_us * 1e-6, prior.run_overhead_us * 1e-6)
    fit, errors = leave_one_out(measured, measured_hw, start)
    micro_rows = [{"layer": m.name, "measured_ms": m.seconds * 1e3, "predicted_ms": fit.predict(design_row(m.layers, measured_hw)) * 1e3}
                  for m in measured if not m.is_network]
    return CalibrationResult(
        peak_gflops_fp32=measured_hw.peak_gflops, memory_bandwidth_gbs=measured_hw.bandwidth_gbs,
        efficiency={k: round(v, 4) for k, v in fit.efficiency().items()}, overhead_us=fit.overhead_s * 1e6,
        run_overhead_us=fit.run_overhead_s * 1e6,
        threads=threads, leave_one_out=errors, micro_layers=micro_rows, host=host_description(),
        created=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        cache_levels=[{"bytes": b, "bandwidth_gbs": g} for b, g in measured_hw.cache_levels],
    )
