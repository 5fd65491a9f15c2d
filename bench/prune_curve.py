"""Accuracy against latency of pruned versions of a shipped model: the pruning curve.

For each ratio, `toolkit prune` (DepGraph channel pruning + its distillation fine-tune from the unpruned
model) on this CPU; then every model, the unpruned one included, is exported for x86-cpu (keypoint graph,
240x320 by default), timed in one interleaved onnxruntime run (1 thread), and evaluated with `toolkit eval`
(500 keypoints, 3 px) on HPatches v_dogman and lowlight_pairs. Writes curve.json, curve.md and curve.png.

    python bench/prune_curve.py --checkpoint default-relu --ratios 0.25,0.5,0.75 --steps 400 -o runs/prune-curve

Pruned checkpoints and artefacts already in the output folder are reused, so a run can be resumed.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_speed import session, time_interleaved  # noqa: E402

DATASETS = {  # label -> (eval kind, folder under --data, extra arguments)
    "hpatches": ("hpatches", "hpatches_v_dogman", []),
    "lowlight raw": ("pairs", "lowlight_pairs", []),
    "lowlight minmax": ("pairs", "lowlight_pairs", ["--normalise", "minmax"]),
}


def _toolkit(*args: str) -> None:
    result = subprocess.run([sys.executable, "-m", "toolkit", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"toolkit {' '.join(args[:2])} failed: {result.stderr.strip()[-600:]}")


def prune_all(checkpoint: str, ratios: list[float], steps: int, folder: Path) -> dict[str, str]:
    """``label -> checkpoint`` for the unpruned model and one pruned model per ratio."""
    models = {"unpruned": checkpoint}
    for ratio in ratios:
        label = f"pruned {round(ratio * 100)} %"
        out = folder / f"pruned{round(ratio * 100)}.safetensors"
        if not out.is_file():
            print(f"pruning {ratio:.0%} and fine-tuning {steps} steps ...", flush=True)
            _toolkit("prune", "--checkpoint", checkpoint, "--ratio", str(ratio), "--steps", str(steps),
                     "--no-eval", "-o", str(out))
        models[label] = str(out)
    return models


def export_all(models: dict[str, str], size: str, folder: Path) -> dict[str, Path]:
    paths = {}
    for index, (label, checkpoint) in enumerate(models.items()):
        out = folder / f"artefact{index}"
        if not (out / "manifest.json").is_file():
            _toolkit("export", "--target", "x86-cpu", "--checkpoint", checkpoint, "--input-size", size, "-o", str(out))
        paths[label] = out
    return paths


def evaluate_all(models: dict[str, str], data: Path, folder: Path) -> dict[str, dict[str, dict]]:
    """``dataset -> label -> summary['all']`` from one `toolkit eval` run per dataset."""
    results: dict[str, dict[str, dict]] = {}
    for name, (kind, sub, extra) in DATASETS.items():
        out = folder / f"eval-{name.replace(' ', '-')}"
        if not (out / "results.json").is_file():
            specs = [f"m{i}={path}" for i, path in enumerate(models.values())]
            _toolkit("eval", kind, "--data", str(data / sub), "--max-keypoints", "500", *extra,
                     "--model", *specs, "-o", str(out))
        rows = json.loads((out / "results.json").read_text())["models"]
        results[name] = {label: row["summary"]["all"] for label, row in zip(models, rows)}
    return results


def plot(curve: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for axis, metric in zip(axes, ("matching_score", "nn_map")):
        for name in DATASETS:
            xs = [row["latency_ms"] for row in curve]
            ys = [row["metrics"][name][metric] for row in curve]
            axis.plot(xs, ys, "o-", label=name)
            for x, y, row in zip(xs, ys, curve):
                axis.annotate(row["label"].replace("pruned ", ""), (x, y), fontsize=7, xytext=(3, 3),
                              textcoords="offset points")
        axis.set_xlabel("latency, ms (onnxruntime, 1 thread, keypoint graph)")
        axis.set_ylabel(metric.replace("_", " "))
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Pruning the shipped model: accuracy against latency")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default="default-relu")
    parser.add_argument("--ratios", default="0.25,0.5,0.75")
    parser.add_argument("--steps", type=int, default=400, help="distillation steps per pruned model")
    parser.add_argument("--size", default="240x320")
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("-o", "--output", type=Path, default=Path("runs/prune-curve"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    height, width = (int(v) for v in args.size.split("x"))

    models = prune_all(args.checkpoint, [float(r) for r in args.ratios.split(",")], args.steps, args.output)
    artefacts = export_all(models, args.size, args.output)
    sessions = {label: session(path / "model.onnx", 1) for label, path in artefacts.items()}
    image = np.random.default_rng(0).random((1, 1, height, width), dtype=np.float32)
    timings = time_interleaved(sessions, image, args.rounds)
    metrics = evaluate_all(models, args.data, args.output)

    curve = []
    for label, path in artefacts.items():
        manifest = json.loads((path / "manifest.json").read_text())
        curve.append({"label": label, "checkpoint": models[label], "parameters": manifest["model"]["parameters"],
                      "widths": manifest["model"]["config"]["widths"],
                      "latency_ms": statistics.median(timings[label]),
                      "metrics": {name: metrics[name][label] for name in DATASETS}})
    base = curve[0]["latency_ms"]
    lines = [f"{args.size}, onnxruntime 1 thread, {args.rounds} interleaved rounds; `toolkit eval` 500 keypoints, 3 px; "
             f"prune fine-tune {args.steps} steps", "",
             "| model | widths | params | latency ms | speed-up | " + " | ".join(
                 f"{name} M.score / NN mAP" for name in DATASETS) + " |",
             "|---|---|---|---|---|" + "---|" * len(DATASETS)]
    for row in curve:
        cells = " | ".join(f"{row['metrics'][n]['matching_score']:.3f} / {row['metrics'][n]['nn_map']:.3f}" for n in DATASETS)
        lines.append(f"| {row['label']} | {row['widths']} | {row['parameters']:,} | {row['latency_ms']:.2f} | "
                     f"{base / row['latency_ms']:.2f}x | {cells} |")
    (args.output / "curve.json").write_text(json.dumps(curve, indent=2) + "\n")
    (args.output / "curve.md").write_text("\n".join(lines) + "\n")
    plot(curve, args.output / "curve.png")
    print("\n".join(lines))
    print(f"wrote {args.output}/curve.json, curve.md, curve.png")


if __name__ == "__main__":
    main()
