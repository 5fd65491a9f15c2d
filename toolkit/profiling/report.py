"""Rendering a profile report: terminal table, markdown, JSON and a PNG chart, written atomically."""
from __future__ import annotations

import json
from contextlib import AbstractContextManager
from pathlib import Path

from toolkit.atomic import OutputClaim, OutputKind, claim_output_dir

TOP_LAYERS = 12
HOST_TARGET = "x86-cpu"  # the target whose prediction is checked against this host's measurement


def _mb(value: float) -> str:
    return f"{value / 1e6:.2f}"


def summary_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """One row per model: counts, size, measured on the host, predicted on every hardware model."""
    labels = [hw["label"] for hw in report["hardware"]]
    header = ["model", "params (M)", "GMACs", "GFLOPs", "ONNX count vs fvcore", "model.onnx (MB)",
              "host ORT median / p90 (ms)", "host torch eager (ms)", *[f"pred. {label} (ms)" for label in labels]]
    host_labels = [label for label in labels if label.startswith(HOST_TARGET)]
    header += [f"pred. / measured ({label})" for label in host_labels]
    rows = []
    for model in report["models"]:
        measured = model["measured_on_host"]
        ort = measured.get("onnxruntime")
        eager = measured.get("torch-eager")
        deltas = ", ".join(f"{t}: {d['onnx_vs_fvcore']:+.2%}" for t, d in model["targets"].items())
        sizes = ", ".join(f"{t}: {_mb(d['artefact_bytes'])}" for t, d in model["targets"].items())
        predicted = []
        for label in labels:
            values = [d["predictions"][label]["total_ms"] for d in model["targets"].values() if label in d["predictions"]]
            predicted.append(f"{values[0]:.2f}" if values else "-")
        rows.append([
            model["name"], f"{model['parameters'] / 1e6:.3f}", f"{model['macs'] / 1e9:.3f}", f"{model['flops'] / 1e9:.3f}",
            deltas, sizes, f"{ort['median_ms']:.2f} / {ort['p90_ms']:.2f}" if ort else "-",
            f"{eager['median_ms']:.2f}" if eager else "-", *predicted,
            *(f"{model['targets'][HOST_TARGET]['predictions'][label]['total_ms'] / ort['median_ms']:.2f}" if ort else "-"
              for label in host_labels),
        ])
    return header, rows


def ratio_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    comparison = report.get("comparison") or {}
    names = [name for name in comparison if name != "reference"]
    if not names:
        return [], []
    keys = list(comparison[names[0]])
    header = [f"{comparison['reference']} / model", *keys]
    return header, [[name, *(f"{comparison[name][k]:.2f}x" for k in keys)] for name in names]


def format_table(header: list[str], rows: list[list[str]]) -> str:
    """A plain fixed-width text table."""
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows)]
    lines = ["  ".join(str(cell).ljust(w) for cell, w in zip(line, widths)) for line in [header, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def terminal_text(report: dict) -> str:
    height, width = report["input_size"]
    parts = [f"profile at {height}x{width}, host measurements with {report['threads']} thread(s); {report['flops_convention']}",
             format_table(*summary_rows(report))]
    header, rows = ratio_rows(report)
    if rows:
        parts += ["", format_table(header, rows)]
    parts += ["", "figures: " + "; ".join(f"{hw['label']} from {hw['figures_from']}" for hw in report["hardware"])]
    return "\n".join(parts)


def layer_table(target_data: dict, label: str, limit: int | None = None) -> tuple[list[str], list[list[str]]]:
    """Per-layer rows of one model on one hardware model, slowest first."""
    rows = [r for r in target_data["layers"] if label in r["predicted"]]
    rows.sort(key=lambda r: -r["predicted"][label]["time_ms"])
    header = ["layer", "op", "kind", "MACs (M)", "activations (MB, fp32)", "traffic (MB)", "pred. (ms)", "bound"]
    body = [[r["name"], r["op"], r["kind"], f"{r['macs'] / 1e6:.2f}", _mb(r["activation_bytes_fp32"]),
             _mb(r["predicted"][label]["traffic_bytes"]), f"{r['predicted'][label]['time_ms']:.3f}", r["predicted"][label]["bound"]]
            for r in rows[:limit]]
    return header, body


def markdown_text(report: dict) -> str:
    height, width = report["input_size"]
    parts = [f"# EdgeFeat profile at {height}x{width}", "",
             f"- {report['flops_convention']}.", f"- Weights: {report['weights_note']}.",
             f"- Host measurements: onnxruntime and torch eager, {report['threads']} thread(s), warm-up then median and p90.",
             "", "## Summary", "", markdown_table(*summary_rows(report))]
    header, rows = ratio_rows(report)
    if rows:
        parts += ["", "## Comparison (reference / model; > 1 means the model is smaller or faster)", "", markdown_table(header, rows)]
    parts += ["", "## Hardware figures", ""]
    for hw in report["hardware"]:
        eff = ", ".join(f"{k} {v:.3g}" for k, v in hw["efficiency"].items())
        parts.append(f"- **{hw['label']}**: {hw['peak_gflops']:.1f} GFLOP/s, {hw['bandwidth_gbs']:.1f} GB/s, "
                     f"overhead {hw['overhead_us']:.1f} us/layer, efficiency {eff}; from `{hw['figures_from']}`"
                     + (f" ({'; '.join(hw['sources'])})" if hw["sources"] else ""))
    for model in report["models"]:
        parts += ["", f"## {model['name']}", "", f"Origin: {model['origin']}.", ""]
        parts += [markdown_table(["module (fvcore, own ops)", "MACs (M)", "params"],
                                 [[m["name"], f"{m['macs'] / 1e6:.2f}", str(m["parameters"])] for m in model["modules"]]), ""]
        for target, data in model["targets"].items():
            for label in data["predictions"]:
                parts += [f"### {label}: per-layer prediction ({data['graph']}, opset {data['opset']})", "",
                          markdown_table(*layer_table(data, label)), ""]
    return "\n".join(parts) + "\n"


def plot_layers(report: dict, path: Path) -> None:
    """Horizontal bars of the slowest layers per model and hardware model, coloured by bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(m, t, label) for m in report["models"] for t, d in m["targets"].items() for label in d["predictions"]]
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 3.2 * len(panels)), squeeze=False)
    colours = {"compute": "tab:red", "memory": "tab:blue", "fused": "tab:gray"}
    for axis, (model, target, label) in zip(axes[:, 0], panels):
        data = model["targets"][target]
        _, rows = layer_table(data, label, TOP_LAYERS)
        names = [r[0][-38:] for r in rows][::-1]
        times = [float(r[6]) for r in rows][::-1]
        axis.barh(names, times, color=[colours[r[7]] for r in rows][::-1])
        total = data["predictions"][label]["total_ms"]
        axis.set_title(f"{model['name']} on {label}: {total:.2f} ms predicted (red compute-, blue memory-bound)", fontsize=9)
        axis.set_xlabel("predicted ms")
        axis.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# What --force may replace: a report this command wrote before, as its listing records (vo_runtime.outputs).
PROFILE_REPORT = OutputKind("profile-report", "a profile report written by toolkit profile")


def claim_report_dir(output: Path, force: bool, inputs: list[Path]) -> AbstractContextManager[OutputClaim]:
    """Hold ``output`` for a report: absent, empty, or (with ``force``) an earlier profile report."""
    return claim_output_dir(output, PROFILE_REPORT, force, inputs)


def write_outputs(report: dict, claim: OutputClaim) -> None:
    """Write profile.json, profile.md and profile.png via a staging directory swapped in by ``claim``."""
    with claim.writing() as staging:
        (staging / "profile.json").write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")  # strict JSON
        (staging / "profile.md").write_text(markdown_text(report))
        plot_layers(report, staging / "profile.png")
