"""What pruning and quantisation buy and cost, measured in one run on this CPU.

Builds the stand-in reference network (random weights, BatchNorm statistics estimated on real images:
there are no trained weights yet, so accuracy is drift from the FP32 model's own outputs, never a
detector-quality claim) in its ELU and ReLU variants, exports each as an x86-cpu FP32 artefact, and derives
INT8 (ELU, ReLU), FP16 (ELU) and pruned 30 % / 50 % (ELU, distilled) artefacts with the toolkit's own code.
All seven run in onnxruntime, timed round-robin on one real image so load swings hit them alike; drift is
measured on held-out images (HPatches v_dogman, LOL low/high), never the calibration or distillation set.

    python bench/bench_compression.py                          # 240x320, 1 thread
    python bench/bench_compression.py --threads 2 --steps 300 --json out/compression.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from export.artefact import ExportOptions, export_artefact  # noqa: E402
from toolkit.sizes import parse_size  # noqa: E402
from export.parity import shared_data_dir  # noqa: E402
from models.checkpoint import save_checkpoint  # noqa: E402
from models.featurenet import FeatureNetConfig  # noqa: E402
from toolkit.compression.distill import DistillConfig, distill  # noqa: E402
from toolkit.compression.images import load_images  # noqa: E402
from toolkit.compression.prune import count_macs, count_parameters, prune_channels, rebuild  # noqa: E402
from toolkit.compression.proxy import calibrated_random_featurenet  # noqa: E402
from toolkit.compression.quantise import QuantiseOptions, quantise_artefact  # noqa: E402
from toolkit.compression.report import interleaved_median_ms, ort_drift, ort_session  # noqa: E402


def quiet(_message: str) -> None:
    pass


def export(checkpoint: Path, out: Path, size: tuple[int, int]) -> Path:
    return export_artefact(ExportOptions(target="x86-cpu", output=out, checkpoint=checkpoint, input_size=size,
                                         precision="fp32", force=True), log=quiet)


def evaluation_metrics(artefacts: dict[str, Path], data: Path, size: tuple[int, int]) -> dict[str, dict]:
    """Repeatability / matching score / homography accuracy of every artefact with the evaluation package
    (empty when it does not import), on the real pairs beside the repository."""
    try:
        from toolkit.evaluation.datasets import read_hpatches, read_registered_pairs
        from toolkit.evaluation.detectors import DetectorConfig, artefact_detector
        from toolkit.evaluation.runner import EvalConfig, ImageCache, evaluate_model, summarise
    except ImportError as exc:
        print(f"evaluation package not importable ({exc}); drift figures only")
        return {}
    pairs = read_hpatches(data / "hpatches_v_dogman") + read_registered_pairs(data / "lowlight_pairs")
    config = EvalConfig(size=size)
    images = ImageCache(config.size, config.normalise)
    results = {}
    for name, directory in artefacts.items():
        result = evaluate_model(artefact_detector(directory, DetectorConfig(), name), pairs, config, images)
        results[name] = summarise([metrics for _group, metrics in result.pairs.values()])
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="240x320", help="artefact input size (default 240x320)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per artefact (default 30)")
    parser.add_argument("--steps", type=int, default=150, help="distillation steps per pruned model (default 150)")
    parser.add_argument("--distill-size", default="120x160", help="distillation crop size (default 120x160)")
    parser.add_argument("--lr", type=float, default=1e-3, help="distillation learning rate (default 1e-3)")
    parser.add_argument("--calibration-count", type=int, default=32, help="INT8 calibration images (default 32)")
    parser.add_argument("--workdir", type=Path, help="keep the artefacts here (default: a temporary folder)")
    parser.add_argument("--json", type=Path, help="also write the results as JSON")
    args = parser.parse_args()
    torch.set_num_threads(max(1, args.threads))
    size, distill_size = parse_size(args.size), parse_size(args.distill_size)
    data = shared_data_dir()
    if data is None:
        sys.exit("error: ../shared/data not found")
    train = data / "train_images"
    held_out = np.concatenate([load_images(data / "hpatches_v_dogman", 6, size)[0],
                               load_images(data / "lowlight_pairs", 6, size)[0]])
    bn_images = load_images(train / "coco128", 16, size)[0]
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench-compression-"))
    work.mkdir(parents=True, exist_ok=True)
    tick = time.perf_counter()

    artefacts: dict[str, Path] = {}
    references: dict[str, str] = {}
    nets = {}
    for activation in ("elu", "relu"):
        net = calibrated_random_featurenet(FeatureNetConfig(activation=activation), bn_images, seed=0)
        nets[activation] = net
        checkpoint = save_checkpoint(net, work / f"{activation}.safetensors")
        artefacts[f"FP32 ({activation.upper()})"] = export(checkpoint, work / f"fp32-{activation}", size)
        print(f"[{time.perf_counter() - tick:5.0f} s] exported FP32 {activation}", flush=True)
        quantised = quantise_artefact(QuantiseOptions(artefacts[f"FP32 ({activation.upper()})"], "int8", work / f"int8-{activation}",
                                                      calibration=train, calibration_count=args.calibration_count,
                                                      force=True, timing_repeats=3), log=quiet)
        artefacts[f"INT8 ({activation.upper()})"] = quantised
        references[f"INT8 ({activation.upper()})"] = f"FP32 ({activation.upper()})"
        print(f"[{time.perf_counter() - tick:5.0f} s] quantised INT8 {activation}", flush=True)
    artefacts["FP16 (ELU)"] = quantise_artefact(QuantiseOptions(artefacts["FP32 (ELU)"], "fp16", work / "fp16-elu",
                                                                force=True, timing_repeats=3), log=quiet)
    references["FP16 (ELU)"] = "FP32 (ELU)"

    sizes = {"FP32 (ELU)": (count_parameters(nets["elu"]), count_macs(nets["elu"], size))}
    distillation = {}
    for ratio in (0.3, 0.5):
        name = f"pruned {round(ratio * 100)} % (ELU)"
        student = prune_channels(nets["elu"], ratio)
        result = distill(student, nets["elu"], train, DistillConfig(steps=args.steps, batch=4, lr=args.lr,
                                                                    size=distill_size, images=128), progress=False)
        student = rebuild(student)
        sizes[name] = (count_parameters(student), count_macs(student, size))
        distillation[name] = {"steps": result.steps, "loss_first": result.first_loss, "loss_last": result.last_loss,
                              "widths": student.config.widths, "head_channels": student.config.head_channels}
        checkpoint = save_checkpoint(student, work / f"pruned{round(ratio * 100)}.safetensors")
        artefacts[name] = export(checkpoint, work / f"pruned{round(ratio * 100)}", size)
        references[name] = "FP32 (ELU)"
        print(f"[{time.perf_counter() - tick:5.0f} s] pruned {ratio:.0%}, distilled {args.steps} steps "
              f"(loss {result.first_loss:.3f} -> {result.last_loss:.3f}), exported", flush=True)

    sessions = {name: ort_session(str(path / "model.onnx"), args.threads) for name, path in artefacts.items()}
    feed = {"image": held_out[:1]}
    latency = interleaved_median_ms({name: (lambda s=s: s.run(None, feed)) for name, s in sessions.items()},
                                    repeats=args.repeats, warmup=3)
    drift = {name: ort_drift(sessions[ref], sessions[name], held_out).to_dict() for name, ref in references.items()}

    print(f"\nlatency, onnxruntime {args.threads} thread(s), {size[0]}x{size[1]} keypoint graph, median of {args.repeats} "
          f"(round-robin, one run)")
    print(f"{'artefact':24}{'ms':>9}{'vs FP32 same act.':>19}{'params':>10}{'MMACs':>9}")
    for name, ms in latency.items():
        base = references.get(name, name)
        params, macs = sizes.get(name, (None, None))
        extra = f"{params:>10,}{macs / 1e6:>9.0f}" if params else ""
        print(f"{name:24}{ms:9.1f}{latency[base] / ms:18.2f}x{extra}")
    ratios = {
        "INT8 vs FP32 (ELU)": latency["FP32 (ELU)"] / latency["INT8 (ELU)"],
        "INT8 vs FP32 (ReLU)": latency["FP32 (RELU)"] / latency["INT8 (RELU)"],
        "FP16 vs FP32 (ELU)": latency["FP32 (ELU)"] / latency["FP16 (ELU)"],
        "pruned 30 % vs unpruned": latency["FP32 (ELU)"] / latency["pruned 30 % (ELU)"],
        "pruned 50 % vs unpruned": latency["FP32 (ELU)"] / latency["pruned 50 % (ELU)"],
    }
    print("\nspeed-ups (higher is faster): " + ", ".join(f"{k} {v:.2f}x" for k, v in ratios.items()))
    print(f"\ndrift from the FP32 model of the same activation on {len(held_out)} held-out images "
          f"(stand-in network: random weights, image-calibrated BatchNorm; NOT detector accuracy)")
    print(f"{'artefact':24}{'kp unchanged':>14}{'desc cosine':>13}{'score max diff':>16}")
    for name, figures in drift.items():
        print(f"{name:24}{figures['keypoints_unchanged']:14.1%}{figures['descriptor_cosine']:13.4f}{figures['scores_max_abs']:16.2e}")
    metrics = evaluation_metrics(artefacts, data, size)
    if metrics:
        print("\nevaluation metrics (toolkit.evaluation, HPatches v_dogman + LOL low->high pairs at "
              f"{size[0]}x{size[1]}; stand-in network, so compare rows, do not read them as quality)")
        print(f"{'artefact':24}{'repeatability':>15}{'matching score':>16}{'homography 3px':>16}")
        for name, summary in metrics.items():
            print(f"{name:24}{summary['repeatability']:15.3f}{summary['matching_score']:16.3f}{summary['homography_3px']:16.3f}")
    results = {"size": list(size), "threads": args.threads, "repeats": args.repeats, "latency_ms": latency,
               "speedups": ratios, "drift": drift, "evaluation": metrics, "sizes": sizes, "distillation": distillation,
               "calibration_count": args.calibration_count, "seconds": time.perf_counter() - tick}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    print(f"\n[{time.perf_counter() - tick:5.0f} s] artefacts in {work}")


if __name__ == "__main__":
    main()
