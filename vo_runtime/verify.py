"""``python -m vo_runtime verify ARTEFACT`` (and ``toolkit verify``): does this runtime reproduce the parity run?

The artefact's reference inputs go through the chosen execution provider (onnxruntime: cpu, cuda, tensorrt) or a
TensorRT engine file (``--engine``, run by trtexec), and the outputs are compared with the stored references
(`vo_runtime.references`): the share of reference keypoints found again within a pixel, and the distance between
their descriptors. Past a tolerance the command fails with one ``error:`` line (exit 2).
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np

from vo_runtime.artefact import verify_artefact
from vo_runtime.clitools import command_parser, run_guarded
from vo_runtime.cpu_blocks import graph_for_this_cpu
from vo_runtime.errors import VORuntimeError
from vo_runtime.references import (
    MATCH_RADIUS_PX, Agreement, Runner, compare_dense, compare_keypoints, load_references, network_input, onnx_runner,
)

DESCRIPTION = ("Run an artefact's reference inputs (shipped from its parity run) through an execution provider or a "
               "TensorRT engine and compare keypoints and descriptors with the stored outputs.")
EPILOG = """\
examples:
  {prog} out/cpu                                    # onnxruntime's CPU provider (the default: auto)
  {prog} out/tx2 --providers tensorrt               # on a Jetson: onnxruntime's TensorRT provider (FP16)
  {prog} out/tx2 --engine out/tx2/model_fp16.engine # the engine trtexec built from the artefact README
  {prog} out/cpu-int8 --providers cpu --json

Passes when at least --min-keypoint-agreement of the reference keypoints are found again within 1 px and their
descriptors lie within --max-descriptor-distance (mean L2 between unit vectors); a dense artefact is judged by
its heatmap difference instead of keypoints. Exit codes: 0 passed, 2 failed or bad input (one error: line).
"""


@dataclass
class Tolerance:
    # The export's own floor for FP16 (manifest parity.required_identical for fp16): TensorRT runs FP16 layers.
    min_keypoint_agreement: float = 0.90
    # Unit descriptors: 0.10 is a cosine above 0.995; FP16 arithmetic moves them by ~1e-3.
    max_descriptor_distance: float = 0.10
    max_heatmap_diff: float = 0.02  # dense artefacts: keypoint probability


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("artefact", type=Path, help="artefact directory written by toolkit export or quantise")
    parser.add_argument("--providers", default="auto",
                        help="onnxruntime execution providers: auto (default: the best of tensorrt, cuda, cpu) or a "
                             "list such as tensorrt or cuda,cpu; a missing one is an error")
    parser.add_argument("--engine", type=Path, metavar="FILE",
                        help="a TensorRT engine built from this artefact's model.onnx, run with trtexec instead")
    parser.add_argument("--trtexec", metavar="PATH", help="trtexec for --engine (default: on PATH, else "
                        "/usr/src/tensorrt/bin/trtexec)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")
    defaults = Tolerance()
    parser.add_argument("--min-keypoint-agreement", type=float, default=defaults.min_keypoint_agreement, metavar="F",
                        help=f"share of reference keypoints to find within 1 px (default {defaults.min_keypoint_agreement})")
    parser.add_argument("--max-descriptor-distance", type=float, default=defaults.max_descriptor_distance, metavar="D",
                        help=f"largest mean descriptor distance (default {defaults.max_descriptor_distance})")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def _check_options(args: argparse.Namespace) -> Tolerance:
    if args.threads < 1:
        raise VORuntimeError(f"--threads must be at least 1, got {args.threads}")
    if not 0.0 <= args.min_keypoint_agreement <= 1.0:
        raise VORuntimeError(f"--min-keypoint-agreement is a share in [0, 1], got {args.min_keypoint_agreement}")
    if not 0.0 <= args.max_descriptor_distance <= 2.0:
        raise VORuntimeError(f"--max-descriptor-distance is an L2 distance of unit vectors in [0, 2], "
                             f"got {args.max_descriptor_distance}")
    if args.trtexec and not args.engine:
        raise VORuntimeError("--trtexec runs an --engine file: pass --engine FILE")
    return Tolerance(args.min_keypoint_agreement, args.max_descriptor_distance)


def _runner(args: argparse.Namespace, model: Path) -> Tuple[Runner, str]:
    """The runner the options ask for, and what it runs on ("cpu", "tensorrt,cuda,cpu", "engine model.plan")."""
    if args.engine:
        from vo_runtime.trtexec import find_trtexec, trtexec_runner

        return trtexec_runner(args.engine, find_trtexec(args.trtexec)), f"engine {args.engine.name}"
    from vo_runtime.providers import open_session, short_name

    session = open_session(model, args.threads, args.providers)
    return onnx_runner(session), ",".join(short_name(p) for p in session.get_providers())


def summarise(agreements: List[Agreement], dense: bool) -> Dict[str, Any]:
    distances = np.concatenate([a.descriptor_distances for a in agreements])
    summary: Dict[str, Any] = {
        "descriptor_distance_mean": float(distances.mean()) if distances.size else None,
        "descriptor_distance_max": float(distances.max()) if distances.size else None,
    }
    if dense:
        summary["heatmap_max_diff"] = max(a.heatmap_max_diff or 0.0 for a in agreements)
    else:
        total = sum(a.reference_keypoints for a in agreements)
        summary.update({"reference_keypoints": total, "keypoint_agreement": sum(a.matched_keypoints for a in agreements)
                        / total if total else 0.0, "score_max_diff": max(a.score_max_diff for a in agreements)})
    return summary


def failure(summary: Dict[str, Any], tolerance: Tolerance, dense: bool) -> str | None:
    """Why the run is outside the tolerance, or None when it passes."""
    if dense and summary["heatmap_max_diff"] > tolerance.max_heatmap_diff:
        return f"heatmap differs by up to {summary['heatmap_max_diff']:.3g} (at most {tolerance.max_heatmap_diff} allowed)"
    if not dense and summary["keypoint_agreement"] < tolerance.min_keypoint_agreement:
        return (f"only {summary['keypoint_agreement']:.1%} of {summary['reference_keypoints']} reference keypoints found "
                f"within {MATCH_RADIUS_PX:g} px (at least {tolerance.min_keypoint_agreement:.0%} needed)")
    mean = summary["descriptor_distance_mean"]
    if mean is None:
        return "no descriptor could be compared (no reference keypoint was found again)"
    if mean > tolerance.max_descriptor_distance:
        return f"mean descriptor distance {mean:.3f} (at most {tolerance.max_descriptor_distance} allowed)"
    return None


def _image_line(agreement: Agreement, dense: bool) -> str:
    distances = agreement.descriptor_distances
    described = (f"descriptor distance mean {distances.mean():.4f}, max {distances.max():.4f}" if distances.size
                 else "no descriptor compared")
    if dense:
        return f"  {agreement.name}: heatmap max diff {agreement.heatmap_max_diff:.2e}, {described}"
    share = agreement.matched_keypoints / agreement.reference_keypoints if agreement.reference_keypoints else 0.0
    return (f"  {agreement.name}: {agreement.matched_keypoints}/{agreement.reference_keypoints} keypoints within "
            f"{MATCH_RADIUS_PX:g} px ({share:.1%}), {described}, score max diff {agreement.score_max_diff:.2e}")


def run(args: argparse.Namespace) -> int:
    tolerance = _check_options(args)
    manifest = verify_artefact(args.artefact)
    cases = load_references(args.artefact, manifest)
    dense = manifest.get("mode") != "keypoints"
    graph = graph_for_this_cpu(manifest)  # the one FeatureExtractor runs on this CPU
    runner, runs_on = _runner(args, args.artefact / graph)
    scale = float(manifest["input"]["normalisation"]["scale"])
    compare = compare_dense if dense else compare_keypoints
    agreements = [compare(case, runner(network_input(case.image, scale))) for case in cases]
    summary = {"artefact": str(args.artefact), "graph": graph, "runs_on": runs_on,
               "written_by": manifest.get("toolkit_version"),
               **summarise(agreements, dense)}
    problem = failure(summary, tolerance, dense)
    summary["passed"] = problem is None
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"verify {args.artefact} ({graph}) on {runs_on}, against the outputs of its parity run "
              f"({manifest['reference'].get('outputs_from', '?')}, edgefeat {summary['written_by']}):")
        print("\n".join(_image_line(agreement, dense) for agreement in agreements))
    if problem:
        raise VORuntimeError(f"verify failed on {runs_on}: {problem}")
    if not args.json:
        checked = (f"heatmap diff <= {tolerance.max_heatmap_diff}" if dense else
                   f"keypoints >= {tolerance.min_keypoint_agreement:.0%} within {MATCH_RADIUS_PX:g} px")
        print(f"passed on {runs_on}: {checked}, mean descriptor distance <= {tolerance.max_descriptor_distance}")
    return 0


def build_parser(prog: str = "python -m vo_runtime verify") -> argparse.ArgumentParser:
    return command_parser(prog, DESCRIPTION, EPILOG, add_arguments, run)


def main(argv: List[str] | None = None) -> int:
    return run_guarded(build_parser(), argv, (VORuntimeError,))
