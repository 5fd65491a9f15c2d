"""The options and steps every `toolkit eval` command shares: protocol options, models, the report."""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any, Callable

from toolkit import __version__
from toolkit.atomic import OutputClaim
from toolkit.errors import ToolkitError
from toolkit.evaluation.datasets import ImagePair, parse_size
from toolkit.evaluation.detectors import Detector, DetectorConfig, load_detector
from toolkit.evaluation.report import format_terminal_table, write_report
from toolkit.evaluation.runner import (EvalConfig, ImageCache, ModelResult, PairExample, evaluate_model,
                                       group_summaries, pair_records)

MODEL_HELP = ("model to evaluate, repeatable: default / default-relu (the shipped weights), orb, sift, an artefact "
              "directory, a checkpoint (.safetensors/.pth), superpoint:PATH, teacher:alike-n (the teacher's own "
              "keypoints and descriptors), xfeat (the light learned peer; bench extra); prefix LABEL= to name "
              "the row (default: default orb sift)")

def add_common_options(parser: argparse.ArgumentParser, data: bool = True) -> None:
    """The options every `toolkit eval` dataset shares (``--data`` where the data is a folder to read)."""
    if data:
        parser.add_argument("--data", required=True, type=Path, help="dataset directory")
    parser.add_argument("--model", action="extend", nargs="+", default=None, metavar="M", help=MODEL_HELP)
    parser.add_argument("--size", default="240x320", help="HxW to resize every image to, or native (default 240x320)")
    parser.add_argument("--max-keypoints", type=int, default=1000, help="keypoint budget per image (default 1000)")
    parser.add_argument("--nms", type=int, default=4, help="NMS radius in px for networks run in Python (default 4)")
    parser.add_argument("--score-window", type=int, default=1, metavar="PX",
                        help="odd window whose keypoint probability mass ranks a heatmap peak, for 65-way networks "
                        "run in Python (default 1: the peak itself, as export)")
    parser.add_argument("--refine", default="", metavar="METHOD",
                        help="how a heatmap peak becomes a sub-pixel keypoint, for 65-way networks run in Python: "
                        "centroid[:W], quadratic or softargmax[:W[:T]] (default: the one the checkpoint names)")
    parser.add_argument("--threshold", type=float, default=3.0,
                        help="correctness distance in px for repeatability, mAP and matching score (default 3)")
    parser.add_argument("--normalise", choices=("none", "minmax"), default="none",
                        help="per-image contrast stretch before detection, for all models alike (default none)")
    parser.add_argument("-o", "--output", type=Path, default=None, help="report directory to write (optional)")


def _unique_labels(labels: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    unique = []
    for label in labels:
        seen[label] = seen.get(label, 0) + 1
        unique.append(label if seen[label] == 1 else f"{label}#{seen[label]}")
    return unique


def protocol_configs(args: argparse.Namespace) -> tuple[EvalConfig, DetectorConfig]:
    """The checked protocol options; `ToolkitError` for a bad value."""
    if args.max_keypoints < 1:
        raise ToolkitError("--max-keypoints must be at least 1")
    if args.nms < 0 or not (math.isfinite(args.threshold) and args.threshold > 0):  # NaN compares False
        raise ToolkitError(f"--nms must be >= 0 and --threshold a positive number of pixels, got {args.nms} and "
                           f"{args.threshold}")
    from models.keypoints import is_score_window, parse_refinement

    if not is_score_window(args.score_window):
        raise ToolkitError(f"--score-window must be an odd number of pixels >= 1, got {args.score_window}")
    if args.refine:
        try:
            parse_refinement(args.refine)
        except ValueError as exc:
            raise ToolkitError(f"--refine: {exc}") from None
    config = EvalConfig(size=parse_size(args.size), correct_threshold=args.threshold, normalise=args.normalise)
    detector_config = DetectorConfig(max_keypoints=args.max_keypoints, nms_radius=args.nms,
                                     score_window=args.score_window, refinement=args.refine)
    return config, detector_config


def load_detectors(specs: list[str] | None, detector_config: DetectorConfig) -> list[Detector]:
    """Every ``--model`` (default: default orb sift), labels made unique. Loaded before the first pair, so a
    bad spec fails in a second rather than after a long run."""
    detectors = [load_detector(spec, detector_config) for spec in (specs or ["default", "orb", "sift"])]
    for detector, label in zip(detectors, _unique_labels([d.label for d in detectors])):
        detector.label = label
    return detectors


def base_report(args: argparse.Namespace, data: str | list[str], config: EvalConfig) -> dict[str, Any]:
    """The report's header: command, data, version and protocol; ``models`` is filled by `evaluate_models`."""
    return {
        "command": args.eval_command,
        "data": data,
        "toolkit_version": __version__,
        "protocol": {"size": list(config.size) if config.size else None, "max_keypoints": args.max_keypoints,
                     "nms_radius": args.nms, "score_window": args.score_window, "refinement": args.refine or "the model's",
                     "correct_threshold": config.correct_threshold,
                     "ransac_threshold": config.ransac_threshold, "normalise": config.normalise,
                     "homography_epsilons_px": [1, 3, 5],
                     "matcher": "mutual nearest neighbour (L2 for float, Hamming for binary descriptors)"},
        "models": [],
    }


def evaluate_models(detectors: list[Detector], pairs: list[ImagePair], images: ImageCache, config: EvalConfig,
                    report: dict[str, Any],
                    summarise_result: Callable[[ModelResult], dict[str, Any]] = group_summaries,
                    ) -> tuple[dict[str, Any], dict[str, list[PairExample]]]:
    """Every model on every pair: ``report`` with its models filled in, and the example pairs by label.
    ``summarise_result`` makes a model's per-group summaries (`group_summaries`, plus intervals for synth)."""
    examples = {}
    for detector in detectors:
        result = evaluate_model(detector, pairs, config, images)
        report["models"].append({"label": result.label, "kind": result.kind, "settings": result.settings,
                                 "summary": summarise_result(result), "pairs": pair_records(result)})
        if result.examples:
            examples[result.label] = result.examples
    return report, examples


def finish_report(report: dict[str, Any], examples: dict[str, list[PairExample]], claim: OutputClaim | None,
                  output: Path | None) -> None:
    """The table printed and, with ``claim``, the report written there."""
    print(format_terminal_table(report))
    if claim is not None:
        write_report(claim, report, examples)
        print(f"wrote {output}: results.json, results.md and the match plots")
