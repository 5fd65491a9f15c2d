"""`toolkit quantise`: an FP32 artefact to an INT8 (x86-cpu) or FP16 artefact with its own manifest."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from toolkit.compression.quantise import QuantiseOptions, quantise_artefact

EXAMPLES = """examples:
  toolkit quantise --mode int8 -o out/cpu-int8                      # the shipped featurenet-relu artefact
  toolkit quantise --artefact out/cpu --mode int8 -o out/cpu-int8
  toolkit quantise --artefact out/cpu --mode int8 --calibration ../shared/data/train_images --calibration-count 64 \\
      --keep-sensitive 3 -o out/cpu-int8-k3
  toolkit quantise --artefact out/tx2-fp32 --mode fp16 -o out/tx2-fp16

int8 (x86-cpu only; the TX2 has no fast INT8 and is refused): onnxruntime static quantisation, QDQ of the
convs and the descriptor projection, per-channel int8 weights, uint8 activations calibrated (99.99th
percentile) on real images; the keypoint-logit convs, the cell-contrast convs and the one-channel stem
stay float. A sensitivity pass reports each conv's isolated INT8 error; --keep-sensitive N keeps the N
worst in float. ELU does not quantise in onnxruntime: export a ReLU checkpoint (activation relu) for the
fast INT8 path. fp16: weights and arithmetic in FP16, inputs/outputs FP32, checked against the profile.
The new manifest records precision, calibration set and count, and parity and latency against FP32.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "quantise",
        help="quantise an FP32 artefact to INT8 (x86-cpu) or FP16, with parity against FP32",
        description="Quantise an exported FP32 artefact to INT8 (onnxruntime static QDQ, x86-cpu) or FP16 and "
        "write a new artefact with its own manifest (calibration, per-layer sensitivity, parity, latency).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--artefact", type=Path, default=None, metavar="DIR",
                        help="FP32 artefact directory (from toolkit export); default: the shipped featurenet-relu "
                        "x86-cpu artefact")
    parser.add_argument("--mode", required=True, choices=["int8", "fp16"], help="int8 (x86-cpu) or fp16")
    parser.add_argument("--calibration", type=Path, metavar="DIR", help="calibration images (default: the 4 images shipped in export/parity_images)")
    parser.add_argument("--calibration-count", type=int, default=32, metavar="N", help="images used for calibration (default 32)")
    parser.add_argument("--keep-sensitive", type=int, nargs="?", const=3, default=0, metavar="N",
                        help="keep the N most sensitive convs in FP32 (N defaults to 3 when the flag is given alone)")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT", help="directory for the quantised artefact")
    parser.add_argument("--force", action="store_true",
                        help="replace a quantised artefact written here before (never any other folder)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from vo_runtime.artefact import default_artefact

    options = QuantiseOptions(
        artefact=args.artefact if args.artefact is not None else default_artefact(), mode=args.mode, output=args.output, calibration=args.calibration,
        calibration_count=args.calibration_count, keep_sensitive=args.keep_sensitive, force=args.force,
    )
    directory = quantise_artefact(options)
    manifest = json.loads((directory / "manifest.json").read_text())
    q = manifest["quantisation"]
    parity, latency = q["parity_vs_fp32"], q["latency_ms_1thread"]
    if "sensitivity" in q:
        print("per-layer INT8 sensitivity (isolated relative error, worst first):")
        floats = set(q["float_nodes"]["head_outputs"] + q["float_nodes"]["sensitive"])
        for item in q["sensitivity"]:
            print(f"  {item['relative_error']:.4f}  {item['kind']:9}  {item['node']}{'  [kept fp32]' if item['node'] in floats else ''}")
    print(f"wrote {directory}: {args.mode}, {parity['keypoints_unchanged']:.2%} keypoints unchanged vs FP32, descriptor cosine "
          f"{parity['descriptor_cosine']:.4f}; latency {latency['fp32']:.1f} -> {latency[args.mode]:.1f} ms (1 thread)")
    return 0
