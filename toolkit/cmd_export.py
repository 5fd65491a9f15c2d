"""`toolkit export`: a checkpoint to a verified artefact directory for one target."""
from __future__ import annotations

import argparse
from pathlib import Path

from export.artefact import ExportOptions, export_artefact
from toolkit.sizes import parse_size

EXAMPLES = """examples:
  toolkit export --target tx2 -o out/tx2                                     # the shipped default model
  toolkit export --target x86-cpu --checkpoint default-relu -o out/cpu-relu   # the shipped ReLU model
  toolkit export --target tx2 --checkpoint runs/a/best.safetensors -o out/tx2
  toolkit export --target x86-cpu --checkpoint runs/a/best.safetensors --input-size 480x640 -o out/cpu
  toolkit export --target tx2 --checkpoint C --precision fp32 --max-keypoints 512 -o out/tx2-fp32 --force
  toolkit export --target x86-cpu --checkpoint C --dense -o out/cpu-dense     # raw heads, no NMS/top-K

The artefact holds model.onnx, manifest.json (checksums, shapes, parity figures) and a README with the
on-device step (for tx2: the trtexec command that builds the FP16 TensorRT engine on the Jetson).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export",
        help="export a checkpoint to a verified ONNX artefact for tx2 or x86-cpu",
        description="Export a checkpoint to ONNX for a target profile, check the graph against the profile, "
        "simplify it, and verify parity with PyTorch on real images before writing anything.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--target", required=True, help="target profile: tx2, x86-cpu, or a path to a profile TOML")
    parser.add_argument("--checkpoint", type=Path, help="checkpoint (.safetensors, or a Magic Leap superpoint_v1.pth); default: the shipped "
                        "featurenet-elu weights (`default-relu` names the shipped ReLU model)")
    parser.add_argument("--input-size", metavar="HxW", help="fixed input size (default: the profile's)")
    parser.add_argument("--precision", choices=["fp32", "fp16"], help="default: the profile's (tx2: fp16, x86-cpu: fp32)")
    parser.add_argument("--max-keypoints", type=int, metavar="K", help="fixed number of output rows (default: the profile's)")
    parser.add_argument("--nms-radius", type=int, default=4, help="max-pool NMS radius in pixels (default 4)")
    parser.add_argument("--score-window", type=int, default=1, metavar="PX",
                        help="odd window whose keypoint probability mass ranks a heatmap peak (default 1: the peak "
                        "itself, best for VO; 3 at 240x320 / 5 at 480x640 matched more points on HPatches)")
    parser.add_argument("--refine", default="", metavar="METHOD",
                        help="how a heatmap peak becomes a sub-pixel keypoint: centroid[:W], quadratic or "
                        "softargmax[:W[:T]] (default: the one the checkpoint was trained for; centroid = 3x3)")
    parser.add_argument("--threshold", type=float, default=0.005, help="detection threshold on the keypoint probability")
    parser.add_argument("--border", type=int, default=4, help="pixels removed at the image border (default 4)")
    parser.add_argument("--dense", action="store_true", help="output the raw heads instead of keypoints")
    parser.add_argument("--parity-images", type=Path, metavar="DIR", help="images for the parity run (default: the 4 images shipped in export/parity_images)")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="DIR", help="artefact directory to write")
    parser.add_argument("--force", action="store_true",
                        help="replace an artefact exported here before (never any other folder)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = ExportOptions(
        target=args.target, output=args.output, checkpoint=args.checkpoint, input_size=parse_size(args.input_size, "--input-size") if args.input_size else None,
        precision=args.precision, max_keypoints=args.max_keypoints, nms_radius=args.nms_radius, score_window=args.score_window,
        refinement=args.refine,
        threshold=args.threshold, border=args.border, dense=args.dense, force=args.force,
        parity_images=args.parity_images,
    )
    directory = export_artefact(options)
    import json

    manifest = json.loads((directory / "manifest.json").read_text())
    parity = manifest["parity"]
    print(
        f"wrote {directory}: {manifest['onnx']['nodes_before_simplify']} -> {manifest['onnx']['nodes_after_simplify']} nodes, "
        f"opset {manifest['onnx']['opset']}, {parity['keypoints_identical']:.2%} keypoints identical, "
        f"heatmap max diff {parity['heatmap_max_abs_diff']:.1e}"
    )
    return 0
