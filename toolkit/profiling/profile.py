"""Assemble one profile report: counts, host measurements and roofline predictions for models x targets.

The report is a plain JSON-able dict; `report` renders it as a table, markdown and a chart.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import onnx
import torch
from torch import nn

from export.graphs import DENSE_OUTPUTS, KEYPOINT_OUTPUTS, DenseGraph, KeypointGraph
from export.onnx_export import export_onnx
from models.deform import set_deform_strategy
from models.featurenet import set_elu_form
from profiles import TargetProfile
from toolkit import __version__
from toolkit.profiling.counts import LayerCost, fvcore_count, onnx_layer_costs, parameter_count
from toolkit.profiling.latency import ort_runner, ort_session, summarise, time_interleaved, torch_runner
from toolkit.profiling.roofline import HardwareModel, predict_layers
from toolkit.profiling.sources import ModelSource
from vo_runtime.progress import progress_bar

FLOPS_CONVENTION = "FLOPs = 2 x MACs (one multiply-accumulate = two floating-point operations)"
WEIGHTS_NOTE = ("architecture names use random weights: MACs, parameters and latency do not depend on weight values; "
                "the deformable conv samples the same number of points whatever its offsets")


@dataclass
class TargetGraph:
    """One model's deployed graph for one target."""

    target: str
    model: onnx.ModelProto
    layers: list[LayerCost]
    from_artefact: bool


def graph_module(source: ModelSource, height: int, width: int, max_keypoints: int) -> nn.Module:
    """The module that is exported and timed: the network plus its fixed-K post-processing (or dense heads)."""
    if source.artefact_dense:
        return DenseGraph(source.net).eval()
    k = source.max_keypoints or max_keypoints
    return KeypointGraph(source.net, height, width, k, source.nms_radius, source.threshold, source.border).eval()


def target_graph(source: ModelSource, profile: TargetProfile, height: int, width: int) -> TargetGraph:
    """The artefact's own graph when it was exported for ``profile``, else a fresh export with its rules."""
    if source.artefact_dir is not None and source.artefact_target == profile.name:
        model = source.artefact_model()
        return TargetGraph(profile.name, model, onnx_layer_costs(model), True)
    set_deform_strategy(source.net, "native" if profile.deform_strategy == "native" else "torch")
    set_elu_form(source.net, profile.elu_form)
    module = graph_module(source, height, width, profile.default_max_keypoints)
    outputs = DENSE_OUTPUTS if source.artefact_dense else KEYPOINT_OUTPUTS
    exported = export_onnx(module, torch.zeros(1, 1, height, width), profile.max_opset, outputs).model
    return TargetGraph(profile.name, exported, onnx_layer_costs(exported), False)


def count_model(source: ModelSource, height: int, width: int, max_keypoints: int, elu_form: str = "native") -> dict:
    """Parameters and fvcore MACs (total and per module) of the network plus post-processing, with ELU
    traced in ``elu_form`` (the model's own figure is the native one: one operation per element)."""
    set_deform_strategy(source.net, "native")  # one opaque op, counted by its handler
    set_elu_form(source.net, elu_form)
    module = graph_module(source, height, width, max_keypoints)
    total, modules = fvcore_count(module, torch.zeros(1, 1, height, width))
    return {
        "parameters": parameter_count(source.net),
        "macs": total,
        "flops": 2 * total,
        "modules": [{"name": m.name.removeprefix("net."), "macs": m.macs, "parameters": m.parameters} for m in modules],
    }


def target_entry(graph: TargetGraph, fvcore_macs: int, hardware: list[HardwareModel]) -> dict:
    """Counts on the ONNX graph, per-layer predictions on every hardware model of that target."""
    onnx_macs = sum(layer.macs for layer in graph.layers)
    per_hardware = {hw.label: predict_layers(graph.layers, hw) for hw in hardware}
    rows = []
    for index, layer in enumerate(graph.layers):
        row = {"name": layer.name.removeprefix("/net/").lstrip("/"), "op": layer.op_type, "kind": layer.kind,
               "macs": layer.macs, "activation_bytes_fp32": 4 * (layer.input_elements + layer.output_elements),
               "weight_bytes_fp32": 4 * layer.weight_elements, "output_shape": layer.output_shape}
        row["predicted"] = {label: {"time_ms": p[index].time_ms, "bound": p[index].bound,
                                    "traffic_bytes": p[index].traffic_bytes} for label, p in per_hardware.items()}
        rows.append(row)
    predictions = {}
    for hw in hardware:
        layers = per_hardware[hw.label]
        total = sum(p.time_ms for p in layers) + hw.run_overhead_us * 1e-3
        compute_ms = sum(p.time_ms for p in layers if p.bound == "compute")
        predictions[hw.label] = {
            "total_ms": total,
            "compute_bound_share": compute_ms / total if total > 0 else 0.0,
            "compute_bound_layers": sum(p.bound == "compute" for p in layers),
            "memory_bound_layers": sum(p.bound == "memory" for p in layers),
            "traffic_bytes": sum(p.traffic_bytes for p in layers if p.bound != "fused"),
        }
    return {
        "graph": "artefact model.onnx" if graph.from_artefact else "exported with the target's rules",
        "opset": next((e.version for e in graph.model.opset_import if e.domain in ("", "ai.onnx")), None),
        "onnx_macs": onnx_macs,
        "onnx_vs_fvcore": onnx_macs / fvcore_macs - 1.0 if fvcore_macs else 0.0,
        "artefact_bytes": len(graph.model.SerializeToString()),
        "activation_traffic_bytes_fp32": sum(r["activation_bytes_fp32"] for r in rows),
        "predictions": predictions,
        "layers": rows,
    }


def measure_all(graphs: dict[str, onnx.ModelProto], sources: dict[str, ModelSource], height: int, width: int,
                threads: int, repeats: int, warmup: int, eager: bool) -> dict[str, dict]:
    """onnxruntime on every model's host graph (and torch eager), all interleaved in one run."""
    runners = {}
    for name, model in graphs.items():
        runners[(name, "onnxruntime")] = ort_runner(ort_session(model, threads))
        if eager:
            set_deform_strategy(sources[name].net, "torch")
            module = graph_module(sources[name], height, width, 1024)
            runners[(name, "torch-eager")] = torch_runner(module, torch.rand(1, 1, height, width))
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        samples = time_interleaved(runners, repeats, warmup)
    finally:
        torch.set_num_threads(previous)
    measured: dict[str, dict] = {name: {} for name in graphs}
    for (name, engine), values in samples.items():
        measured[name][engine] = summarise(values, engine, threads, warmup).to_dict()
    return measured


def build_report(sources: list[ModelSource], profiles: list[TargetProfile], hardware: dict[str, list[HardwareModel]],
                 size: tuple[int, int], threads: int, repeats: int, warmup: int = 3, eager: bool = True,
                 host_profile: str = "x86-cpu") -> dict:
    """Counts, predictions for every target, host measurements on the host profile's graph, and ratios."""
    height, width = size
    models = []
    host_graphs: dict[str, onnx.ModelProto] = {}
    for source in progress_bar(sources, desc="counting and exporting", unit="model", leave=False):
        counts = count_model(source, height, width, profiles[0].default_max_keypoints)
        entry = {"name": source.name, "origin": source.origin, **counts, "targets": {}}
        for profile in profiles:
            # fvcore counts the graph the target runs: onnxruntime's ELU is four elementwise ops, not one.
            macs = counts["macs"] if profile.elu_form == "native" else count_model(
                source, height, width, profiles[0].default_max_keypoints, profile.elu_form)["macs"]
            graph = target_graph(source, profile, height, width)
            entry["targets"][profile.name] = target_entry(graph, macs, hardware[profile.name])
            if profile.name == host_profile:
                host_graphs[source.name] = graph.model
        models.append(entry)
    if not host_graphs:  # measure on the host graph even when only other targets are predicted
        for source in sources:
            host_graphs[source.name] = target_graph(source, _host(profiles, host_profile), height, width).model
    measured = measure_all(host_graphs, {s.name: s for s in sources}, height, width, threads, repeats, warmup, eager)
    for entry in models:
        entry["measured_on_host"] = measured[entry["name"]]
    return {
        "toolkit_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "input_size": [height, width],
        "threads": threads,
        "flops_convention": FLOPS_CONVENTION,
        "weights_note": WEIGHTS_NOTE,
        "hardware": [hw.to_dict() | {"label": hw.label} for hws in hardware.values() for hw in hws],
        "models": models,
        "comparison": comparison(models),
    }


def _host(profiles: list[TargetProfile], name: str) -> TargetProfile:
    from profiles import load_profile

    return next((p for p in profiles if p.name == name), None) or load_profile(name)


def comparison(models: list[dict], reference_arch: str = "superpoint") -> dict:
    """Reference / model ratios (MACs, parameters, size, measured and predicted latency): > 1 means smaller or faster."""
    reference = next((m for m in models if m["name"] == reference_arch), None) or next(
        (m for m in models if m["name"].endswith(f"({reference_arch})")), None)
    if reference is None:
        return {}
    ratios = {"reference": reference["name"]}
    for model in models:
        if model is reference:
            continue
        row = {"macs": reference["macs"] / model["macs"], "parameters": reference["parameters"] / model["parameters"]}
        measured = model["measured_on_host"]
        for engine, stats in measured.items():
            row[f"measured {engine}"] = reference["measured_on_host"][engine]["median_ms"] / stats["median_ms"]
        for target, data in model["targets"].items():
            for label, prediction in data["predictions"].items():
                row[f"predicted {label}"] = reference["targets"][target]["predictions"][label]["total_ms"] / prediction["total_ms"]
        ratios[model["name"]] = row
    return ratios
