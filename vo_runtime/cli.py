"""The ``vo`` command: run the monocular VO over a sequence, write the trajectory, evaluate it if asked.

Shared by ``toolkit vo`` and ``python -m vo_runtime`` (for apps without the toolkit).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from vo_runtime.artefact import default_artefact
from vo_runtime.datasets import CAMERA_PRESETS, open_sequence
from vo_runtime.errors import VORuntimeError
from vo_runtime.features import FeatureExtractor, OrbExtractor
from vo_runtime.odometry import VisualOdometry
from vo_runtime.sequence import read_frames
from vo_runtime.trajectory import write_trajectory

DESCRIPTION = ("Run the monocular VO on a sequence (KITTI odometry or TUM RGB-D layout, or a folder of "
               "images) with an exported artefact or OpenCV ORB features; write the trajectory and, given "
               "ground truth, ATE/RPE after Sim(3) alignment and a plot.")

EPILOG = """\
examples:
  {prog} --artefact out/cpu --images ../shared/data/kitti_odom07_f000000-000159 --gt auto -o runs/k07
  {prog} --features orb --images ../shared/data/tum_fr2_desk_snippet --gt auto -o runs/tum_orb
  {prog} --features orb --images ../shared/data/kitti_odom06_f000000-000050 --lowlight 2,3,0.3 --gt auto

--images takes a KITTI sequence folder (image_0/, calib.txt, times.txt, poses.txt), a TUM folder
(rgb/, groundtruth.txt; camera preset tum-fr2 when the name says fr2) or any folder of images plus --calib.
--gt auto uses the sequence's own poses.txt / groundtruth.txt. -o DIR writes trajectory_tum.txt,
trajectory_kitti.txt, frames.json (state and counts per frame), summary.json and, with ground truth,
trajectory.png. --lowlight GAMMA,SIGMA[,GAIN] darkens every frame (I' = 255 GAIN (I/255)^GAMMA, GAIN default 1) and
adds Gaussian noise of SIGMA grey levels (seeded per frame), to test the same sequence in low light. Exit codes: 0 done,
2 bad input.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--features", choices=("artefact", "orb"), default="artefact",
                        help="keypoints from the artefact (default) or from OpenCV ORB, for comparison")
    parser.add_argument("--artefact", type=Path,
                        help="artefact directory written by `toolkit export` (default: the shipped featurenet-relu x86-cpu "
                        "artefact, 240x320)")
    parser.add_argument("--images", required=True, type=Path, help="sequence folder or folder of images")
    parser.add_argument("--calib", help=f"KITTI calib.txt, JSON intrinsics, or a preset ({', '.join(CAMERA_PRESETS)})")
    parser.add_argument("--camera", type=int, default=0, help="KITTI camera index: image_N/ and PN (default 0)")
    parser.add_argument("--gt", help="ground truth (KITTI poses.txt or TUM groundtruth.txt), or auto")
    parser.add_argument("-o", "--output", type=Path, help="output directory (replaced as a whole)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")
    parser.add_argument("--max-keypoints", type=int, default=2000, help="ORB features per frame (default 2000)")
    parser.add_argument("--max-frames", type=int, help="stop after this many frames")
    parser.add_argument("--lowlight", help="GAMMA,SIGMA[,GAIN]: darken and add noise to every frame")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def darken(image: np.ndarray, gamma: float, sigma: float, gain: float, seed: int) -> np.ndarray:
    """Gamma darkening and gain, plus Gaussian sensor noise; uint8 in and out (same shape)."""
    scaled = 255.0 * gain * (image.astype(np.float32) / 255.0) ** gamma
    noisy = scaled + np.random.default_rng(seed).normal(0.0, sigma, size=image.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def _parse_lowlight(text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
        if len(values) not in (2, 3):
            raise ValueError
    except ValueError:
        raise VORuntimeError(f"--lowlight takes GAMMA,SIGMA[,GAIN] (e.g. 2,3,0.3), got {text!r}") from None
    gamma, sigma, gain = values if len(values) == 3 else (*values, 1.0)
    if gamma <= 0 or sigma < 0 or not 0 < gain <= 1:
        raise VORuntimeError("--lowlight needs GAMMA > 0, SIGMA >= 0 and 0 < GAIN <= 1")
    return gamma, sigma, gain


def _progress(items: Iterator, total: int, enabled: bool) -> Iterator:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, total=total, desc="vo", unit="frame", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    lowlight = _parse_lowlight(args.lowlight)
    if args.features == "artefact" and args.artefact is None:
        args.artefact = default_artefact()
    if args.output is not None and args.output.exists() and not args.output.is_dir():
        raise VORuntimeError(f"--output {args.output} exists and is not a directory")
    sequence = open_sequence(args.images, args.calib, args.camera)
    groundtruth = sequence.groundtruth if args.gt == "auto" else (Path(args.gt) if args.gt else None)
    if args.gt == "auto" and groundtruth is None:
        raise VORuntimeError(f"--gt auto: {args.images} has no poses.txt or groundtruth.txt")
    if groundtruth is not None and not groundtruth.is_file():
        raise VORuntimeError(f"ground truth not found: {groundtruth}")
    frames = sequence.frames[: args.max_frames]
    extractor = (OrbExtractor(args.max_keypoints) if args.features == "orb"
                 else FeatureExtractor(args.artefact, threads=args.threads))
    vo = VisualOdometry(extractor, sequence.camera)
    images = read_frames(frames)
    for index, image in enumerate(_progress(images, len(frames), not args.no_progress)):
        if lowlight is not None:
            image = darken(image, *lowlight, seed=index)
        vo.track(image, sequence.timestamps[index])
    states = [r.status for r in vo.results]
    summary: dict[str, Any] = {
        "features": args.features if args.features == "orb" else str(args.artefact),
        "sequence": str(args.images), "layout": sequence.layout, "lowlight": args.lowlight,
        "frames": len(vo.results), "states": {s: states.count(s) for s in dict.fromkeys(states)},
        "median_extract_ms": round(float(np.median([r.extract_ms for r in vo.results])), 2),
        "median_track_ms": round(float(np.median([r.track_ms for r in vo.results])), 2),
        "median_inliers": float(np.median([r.num_inliers for r in vo.results])),
    }
    report = None
    if groundtruth is not None:
        from vo_runtime.evaluate import evaluate

        try:
            report = evaluate(vo.results, groundtruth, "tum" if sequence.layout == "tum" else "kitti",
                              sequence.timestamps)
            summary.update({k: v for k, v in report.items() if not k.startswith("_")})
        except VORuntimeError as exc:  # e.g. never initialised: keep the trajectory, say why there is no ATE
            summary["ate_rmse_m"] = None
            summary["evaluation_error"] = str(exc)
    if args.output is not None:
        _write_outputs(args.output, vo.results, summary, report)
    print(json.dumps(summary) if args.json else " ".join(f"{k}={v}" for k, v in summary.items()))
    return 0


def _write_outputs(output: Path, results: list, summary: dict[str, Any], report: dict[str, Any] | None) -> None:
    """Write everything into a staging directory beside ``output``, then swap it in."""
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.tmp-", dir=output.parent))
    try:
        write_trajectory(staging / "trajectory_tum.txt", results, "tum")
        write_trajectory(staging / "trajectory_kitti.txt", results, "kitti")
        frames = [{"index": r.index, "timestamp": r.timestamp, "state": r.status, "features": r.num_features,
                   "matches": r.num_matches, "inliers": r.num_inliers, "landmarks": r.num_landmarks, "keyframe": r.keyframe,
                   "extract_ms": round(r.extract_ms, 3), "track_ms": round(r.track_ms, 3)} for r in results]
        (staging / "frames.json").write_text(json.dumps(frames, indent=1))
        (staging / "summary.json").write_text(json.dumps(summary, indent=2))
        if report is not None:
            from vo_runtime.evaluate import plot_trajectory

            plot_trajectory(staging / "trajectory.png", report, f"{summary['sequence']} ({summary['features']})")
        os.chmod(staging, 0o755)
        if output.exists():
            shutil.rmtree(output)
        os.rename(staging, output)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def build_parser(prog: str = "python -m vo_runtime") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=DESCRIPTION, epilog=EPILOG.format(prog=prog),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except VORuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
