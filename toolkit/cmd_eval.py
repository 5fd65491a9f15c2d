"""`toolkit eval`: HPatches-protocol detector/descriptor metrics for any model, and for registered pairs."""
from __future__ import annotations

import argparse
from contextlib import nullcontext

from toolkit.eval_common import (add_common_options, base_report, evaluate_models, finish_report, load_detectors,
                                 protocol_configs)
from toolkit.evaluation.datasets import ImagePair, read_hpatches, read_registered_pairs
from toolkit.evaluation.report import claim_report_dir
from toolkit.evaluation.runner import ImageCache

HPATCHES_EPILOG = """\
examples:
  toolkit eval hpatches --data ../shared/data/hpatches_v_dogman --model default --model default-relu \
      --model orb --model sift --model teacher:alike-n --max-keypoints 500 -o reports/dogman
  toolkit eval hpatches --data hpatches-sequences-release --model fp32=export/x86 --model int8=export/x86_int8
  toolkit eval hpatches --data DIR --model sift --size native --max-keypoints 500

Each sequence folder holds 1.ppm..6.ppm and H_1_k (image 1 -> k). i_ and v_ sequences are reported apart
and together. Metrics (definitions: docs/evaluation.md): repeatability and MLE at 3 px, descriptor NN mAP,
matching score, homography accuracy at corner error 1/3/5 px after RANSAC on mutual nearest neighbours.
-o DIR writes results.json, results.md and matches_<model>.png.
"""

PAIRS_EPILOG = """\
examples:
  toolkit eval pairs --data ../shared/data/lowlight_pairs --model orb --model sift -o reports/lowlight
  toolkit eval pairs --data DIR --first day --second night --model export/x86 --size native

Layout: FIRST/<n>.png and SECOND/<n>.png show the same view; HOMOGRAPHIES/<n>.txt (3x3, FIRST -> SECOND)
is optional and the identity when absent (pixel-registered pairs such as LOL low/normal light).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "eval", help="evaluate models with the HPatches protocol or on registered image pairs",
        description="Evaluate keypoint models (checkpoints, exported artefacts, SuperPoint, ORB, SIFT) through "
                    "one code path, with SuperPoint's detector and descriptor metrics.",
        epilog="examples:\n  toolkit eval hpatches --data ../shared/data/hpatches_v_dogman --model orb sift\n"
               "  toolkit eval pairs --data ../shared/data/lowlight_pairs --model orb -o reports/lowlight\n"
               "  toolkit eval synth --images ../shared/data/tum_fr2_desk_snippet --model default sift -o reports/tum",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="eval_command", metavar="<dataset>")
    sub.required = True
    hpatches = sub.add_parser("hpatches", help="HPatches-layout sequences (1.ppm..6.ppm, H_1_k)",
                              description="Evaluate models on HPatches-layout sequence folders.",
                              epilog=HPATCHES_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_options(hpatches)
    hpatches.set_defaults(func=run)
    pairs = sub.add_parser("pairs", help="registered pairs (low/<n>.png vs high/<n>.png, optional H)",
                           description="Evaluate models on registered image pairs with an optional homography.",
                           epilog=PAIRS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_options(pairs)
    pairs.add_argument("--first", default="low", help="folder of the first images (default low)")
    pairs.add_argument("--second", default="high", help="folder of the second images (default high)")
    pairs.add_argument("--homographies", default="homographies",
                       help="folder of optional <n>.txt homographies first -> second (default homographies)")
    pairs.set_defaults(func=run)
    from toolkit.cmd_eval_synth import register_synth  # it builds on this module's helpers

    register_synth(sub)


def _read_pairs(args: argparse.Namespace) -> list[ImagePair]:
    if args.eval_command == "hpatches":
        return read_hpatches(args.data)
    return read_registered_pairs(args.data, args.first, args.second, args.homographies)


def run(args: argparse.Namespace) -> int:
    config, detector_config = protocol_configs(args)
    with claim_report_dir(args.output) if args.output is not None else nullcontext() as claim:
        pairs = _read_pairs(args)
        detectors = load_detectors(args.model, detector_config)
        report, examples = evaluate_models(detectors, pairs, ImageCache(config.size, config.normalise), config,
                                           base_report(args, str(args.data.resolve()), config))
        finish_report(report, examples, claim, args.output)
    return 0


