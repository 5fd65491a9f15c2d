"""Predicted latency: a per-layer roofline with one efficiency factor per op kind.

For layer i of kind k with F_i FLOPs (2 x MACs) and B_i bytes of traffic (activations in and out plus
weights, at the precision's element size), on hardware with peak P FLOP/s and bandwidth W B/s:

    ideal_i = max(F_i / P, B_i / W)           # the roofline: the larger of compute and memory time wins

where W is the bandwidth of the smallest cache level holding B_i (DRAM when none does; the x86 host's
L2/L3 speeds are measured by the calibration, the TX2 profile lists none).
    t_i     = ideal_i / efficiency_k + overhead   (plus one run overhead per inference)
    bound_i = "compute" if F_i / P > B_i / W else "memory"

Activations the runtime fuses into the preceding conv (ReLU in onnxruntime, any activation in TensorRT)
cost nothing. The model is linear in 1 / efficiency_k and in the overhead, which is what lets
`calibration` fit those figures by least squares from measured timings.
"""
from __future__ import annotations

import math

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from profiles import TargetProfile
from toolkit.errors import ToolkitError
from toolkit.profiling.counts import KINDS, LayerCost

BYTES_PER_ELEMENT = {"fp32": 4, "fp16": 2, "int8": 1}
# The [hardware] fields a profile needs for a prediction; peak figures are checked per precision/mode.
REQUIRED_HARDWARE_FIELDS = ("memory_bandwidth_gbs", "overhead_us", "fused_activations", "efficiency")


@dataclass
class HardwareModel:
    """What the roofline needs about one target at one precision (and power mode, for the TX2)."""

    target: str
    precision: str
    power_mode: str
    peak_gflops: float
    bandwidth_gbs: float
    efficiency: dict[str, float]
    overhead_us: float
    fused_activations: tuple[str, ...]
    figures_from: str  # which file the figures came from (profile TOML or calibration JSON)
    sources: list[str] = field(default_factory=list)
    # (capacity bytes, GB/s) of the caches, smallest first: a layer whose traffic fits in one streams at its speed.
    cache_levels: list[tuple[int, float]] = field(default_factory=list)
    run_overhead_us: float = 0.0  # once per inference (optional field): call and I/O handling

    def bandwidth_for(self, traffic_bytes: int) -> float:
        """GB/s for a layer moving ``traffic_bytes``: the first cache level that holds it, else DRAM."""
        for capacity, bandwidth in self.cache_levels:
            if traffic_bytes <= capacity:
                return bandwidth
        return self.bandwidth_gbs

    @property
    def label(self) -> str:
        mode = f" {self.power_mode.upper()}" if self.power_mode else ""
        return f"{self.target}{mode} {self.precision}"

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class LayerPrediction:
    name: str
    op_type: str
    kind: str
    flops: int
    traffic_bytes: int
    compute_ms: float  # F / P, before efficiency
    memory_ms: float  # B / W, before efficiency
    time_ms: float  # predicted, after efficiency and overhead
    bound: str  # "compute", "memory" or "fused"

    def to_dict(self) -> dict:
        return asdict(self)


def _field(hardware: dict[str, Any], name: str, source: str) -> Any:
    if name not in hardware:
        raise ToolkitError(f"profile {source} is missing the field 'hardware.{name}'")
    return hardware[name]


def _figure(hardware: dict[str, Any], name: str, source: str, zero: bool = False, table: str = "hardware") -> float:
    """A hardware figure: a finite number above zero (or at least zero, for overheads); a peak of 0, "fast"
    or NaN would divide by zero, crash or end as NaN in the report."""
    if name not in hardware:
        raise ToolkitError(f"profile {source} is missing the field '{table}.{name}'")
    value = hardware[name]
    number = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not number or not (value >= 0 if zero else value > 0):
        raise ToolkitError(f"profile {source}: {table}.{name} must be a {'non-negative' if zero else 'positive'} "
                           f"finite number, got {value!r}")
    return float(value)


def hardware_model(
    profile: TargetProfile, precision: str | None = None, power_mode: str | None = None, calibration: dict | None = None
) -> HardwareModel:
    """Roofline figures of ``profile`` at ``precision``; a host ``calibration`` (JSON dict) overrides them.

    Raises `ToolkitError` naming a missing ``hardware.*`` field or an unavailable precision/mode.
    """
    precision = precision or profile.default_precision
    if precision not in profile.precisions:
        raise ToolkitError(f"precision {precision} is not available for {profile.name} (choose from {', '.join(profile.precisions)})")
    hardware = dict(profile.hardware)
    figures_from = profile.source
    if calibration is not None:
        keys = ("memory_bandwidth_gbs", "overhead_us", "efficiency", "cache_levels", "run_overhead_us")
        hardware.update({key: calibration[key] for key in keys if key in calibration})
        hardware.update({key: value for key, value in calibration.items() if key.startswith("peak_gflops_")})
        figures_from = str(calibration.get("path", "calibration"))
    for name in REQUIRED_HARDWARE_FIELDS:
        _field(hardware, name, profile.source)
    modes = list(hardware.get("power_modes", []))
    if modes:
        power_mode = power_mode or str(_field(hardware, "default_power_mode", profile.source))
        if power_mode not in modes:
            raise ToolkitError(f"power mode {power_mode} is not one of {profile.name}'s ({', '.join(modes)})")
        peak_key = f"peak_gflops_{precision}_{power_mode}"
    else:
        power_mode = ""
        peak_key = f"peak_gflops_{precision}"
    if not isinstance(hardware["efficiency"], dict):
        raise ToolkitError(f"profile {profile.source}: hardware.efficiency must be a table")
    efficiency = dict(hardware["efficiency"])
    for kind in KINDS:
        efficiency[kind] = _figure(efficiency, kind, profile.source, table="hardware.efficiency")
    return HardwareModel(
        target=profile.name,
        precision=precision,
        power_mode=power_mode,
        peak_gflops=_figure(hardware, peak_key, profile.source),
        bandwidth_gbs=_figure(hardware, "memory_bandwidth_gbs", profile.source),
        efficiency={kind: efficiency[kind] for kind in KINDS},
        overhead_us=_figure(hardware, "overhead_us", profile.source, zero=True),
        fused_activations=tuple(hardware["fused_activations"]),
        figures_from=figures_from,
        sources=[str(s) for s in hardware.get("sources", [])],
        cache_levels=_cache_levels(hardware.get("cache_levels", []), profile.source),
        run_overhead_us=_figure({"run_overhead_us": 0.0, **hardware}, "run_overhead_us", profile.source, zero=True),
    )


def _cache_levels(levels: list, source: str) -> list[tuple[int, float]]:
    if not isinstance(levels, list) or not all(isinstance(level, dict) for level in levels):
        raise ToolkitError(f"profile {source}: hardware.cache_levels must be a list of tables")
    table = "hardware.cache_levels[]"
    return sorted((int(_figure(level, "bytes", source, table=table)), _figure(level, "bandwidth_gbs", source, table=table))
                  for level in levels)


def is_fused(layer: LayerCost, fused_activations: tuple[str, ...]) -> bool:
    """An activation the runtime folds into the conv that feeds it (and only it)."""
    return layer.op_type in fused_activations and layer.producer_op == "Conv" and layer.input_consumers == 1


def ideal_seconds(layer: LayerCost, hardware: HardwareModel) -> tuple[float, float]:
    """(compute seconds, memory seconds) of ``layer`` at 100 % of peak and of the bandwidth it gets."""
    traffic = layer.traffic_bytes(BYTES_PER_ELEMENT[hardware.precision])
    compute = 2.0 * layer.macs / (hardware.peak_gflops * 1e9)
    memory = traffic / (hardware.bandwidth_for(traffic) * 1e9)
    return compute, memory


def predict_layers(layers: list[LayerCost], hardware: HardwareModel) -> list[LayerPrediction]:
    """Per-layer predicted time (ms) and bound on ``hardware`` (the run overhead is not in any layer)."""
    bytes_per_element = BYTES_PER_ELEMENT[hardware.precision]
    predictions = []
    for layer in layers:
        compute, memory = ideal_seconds(layer, hardware)
        if is_fused(layer, hardware.fused_activations):
            time_ms, bound = 0.0, "fused"
        else:
            time_ms = max(compute, memory) / hardware.efficiency[layer.kind] * 1e3 + hardware.overhead_us * 1e-3
            bound = "compute" if compute > memory else "memory"
        predictions.append(LayerPrediction(
            layer.name, layer.op_type, layer.kind, 2 * layer.macs, layer.traffic_bytes(bytes_per_element),
            compute * 1e3, memory * 1e3, time_ms, bound,
        ))
    return predictions


def design_row(layers: list[LayerCost], hardware: HardwareModel) -> dict[str, float]:
    """Linear features of a graph: ideal seconds summed per kind, and the count of running layers.

    predicted seconds = sum_k row[k] / efficiency_k + row["layers"] * overhead + row["run"] * run overhead
    (efficiency and overhead of ``hardware`` are not used: they are what a fit solves for).
    """
    row = {kind: 0.0 for kind in KINDS}
    row["layers"] = 0.0
    row["run"] = 1.0
    for layer in layers:
        if is_fused(layer, hardware.fused_activations):
            continue
        row[layer.kind] += max(ideal_seconds(layer, hardware))
        row["layers"] += 1.0
    return row


def load_calibration(path: Path) -> dict | None:
    """The calibration JSON at ``path`` (with its path recorded), or None when there is none."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ToolkitError(f"calibration file {path} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ToolkitError(f"calibration file {path} is not a JSON object")
    missing = [key for key in ("memory_bandwidth_gbs", "overhead_us", "efficiency", "peak_gflops_fp32") if key not in data]
    if missing:
        raise ToolkitError(f"calibration file {path} is missing the field '{missing[0]}'")
    data["path"] = str(path)
    return data
