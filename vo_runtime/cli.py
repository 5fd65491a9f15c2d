"""The ``vo`` command: run the monocular VO over a sequence, write the trajectory, evaluate it if asked.

Shared by ``toolkit vo`` and ``python -m vo_runtime`` (for apps without the toolkit).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
from threadpoolctl import threadpool_limits

from vo_runtime.artefact import ASPECT_TOLERANCE, default_artefact
from vo_runtime.clitools import command_parser, run_guarded
from vo_runtime.config_overrides import config_from_overrides
from vo_runtime.datasets import CAMERA_PRESETS, Sequence, frame_size, open_sequence
from vo_runtime.errors import FrameError, VORuntimeError
from vo_runtime.features import FeatureExtractor, OrbExtractor, to_gray_u8
from vo_runtime.lowlight import Darkening, parse_lowlight
from vo_runtime.machine import check_thread_count
from vo_runtime.odometry import SKIPPED, VisualOdometry, VOConfig, VOResult
from vo_runtime.outputs import OutputClaim, OutputKind, claim_output
from vo_runtime.pipeline import StreamFrame
from vo_runtime.sequence import read_frame
from vo_runtime.trajectory import write_trajectory

# What --force may replace: a directory this command wrote, as its listing records (vo_runtime.outputs).
VO_RUN = OutputKind("vo-run", "a VO run written by the vo command")
MAX_ORB_KEYPOINTS = 100_000
MAX_EXTRACT_AHEAD = 16  # frames held decoded in memory ahead of the tracking

DESCRIPTION = ("Run the monocular VO on a sequence (KITTI odometry, TUM RGB-D or EuRoC MAV layout, or a folder of "
               "images) with an exported artefact or OpenCV ORB features; write the trajectory and, given "
               "ground truth, ATE/RPE after Sim(3) alignment and a plot.")

EPILOG = """\
examples:
  {prog} --artefact out/cpu --images ../shared/data/kitti_odom07_f000000-000159 --gt auto -o runs/k07
  {prog} --features orb --images ../shared/data/tum_fr2_desk_snippet --gt auto -o runs/tum_orb
  {prog} --features orb --images ../shared/data/kitti_odom06_f000000-000050 --lowlight 2,3,0.3 --gt auto

--images takes a KITTI sequence folder (image_0/, calib.txt, times.txt, poses.txt), a TUM folder
(rgb/, groundtruth.txt; camera preset tum-fr2 when the name says fr2), a EuRoC MAV folder (mav0/ or the
folder holding it: camN/data.csv, camN/sensor.yaml, --camera N) or any folder of images plus --calib.
--gt auto uses the sequence's own poses.txt / groundtruth.txt (EuRoC: the body's ground truth composed with
the camera's T_BS, frames matched by timestamp within 5 ms). -o DIR writes trajectory_tum.txt,
trajectory_kitti.txt, frames.json (state and counts per frame), summary.json and, with ground truth,
trajectory.png; an existing DIR is replaced only with --force and only if it is an earlier vo run.
A frame that cannot be read, or whose size differs from the calibration's (or the first frame's), is
skipped: its pose is held, frames.json says why, and the summary counts it. --lowlight tests the same
sequence in the dark (seeded per frame): GAMMA,SIGMA[,GAIN] darkens every frame (I' = 255 GAIN (I/255)^GAMMA,
GAIN default 1) and adds Gaussian noise of SIGMA grey levels; the preset dark is 2,3,0.3; the preset onboard
is a light riding on the camera (a bright spot fixed in the image, dim ambient, vignetting, Poisson-Gaussian
noise after darkening, motion blur; vo_runtime/lowlight.py). --viz (with -o) adds viz.mp4 and viz/*.png overlays.
--set FIELD=VALUE changes one VOConfig knob for this run (vo_runtime/config.py; e.g. init_wanted_landmarks=100,
a richer first map for a drone in the dark: docs/vo_takeoff.md); summary.json records what was set.
{prog} verify ARTEFACT checks an artefact (or a TensorRT engine) against its stored reference outputs.
Exit codes: 0 done, 2 bad input.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--features", choices=("artefact", "orb"), default="artefact",
                        help="keypoints from the artefact (default) or from OpenCV ORB, for comparison")
    parser.add_argument("--artefact", type=Path,
                        help="artefact directory written by `toolkit export` (default: the shipped featurenet-relu x86-cpu "
                        "artefact for the camera's aspect: 240x320 for 4:3 and any other, 480x752 for 752x480-like "
                        "cameras such as EuRoC's)")
    parser.add_argument("--images", required=True, type=Path, help="sequence folder or folder of images")
    parser.add_argument("--calib", help=f"KITTI calib.txt, JSON intrinsics, or a preset ({', '.join(CAMERA_PRESETS)})")
    parser.add_argument("--camera", type=int, default=0, help="camera index: KITTI image_N/ and PN, EuRoC camN/ (default 0)")
    parser.add_argument("--gt", help="ground truth (KITTI poses.txt, TUM groundtruth.txt, EuRoC data.csv), or auto")
    parser.add_argument("-o", "--output", type=Path, help="output directory (written as a whole)")
    parser.add_argument("--force", action="store_true", help="replace an earlier vo run in the output directory")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")
    parser.add_argument("--mapping-thread", action="store_true",
                        help="run each keyframe's mapping on a second thread, overlapping the next extraction "
                             "(same poses; faster with a free core)")
    parser.add_argument("--extract-ahead", type=int, default=2,
                        help="frames the network runs ahead of the tracking, on a second thread (default 2; same "
                             "poses, ~1.4x the frames per second on two cores; 0: one after the other)")
    parser.add_argument("--blas-threads", type=int, default=1,
                        help="numpy's BLAS threads for the geometry (default 1: its matrices are small, and BLAS "
                             "threads spinning against the network or another process cost more than they give)")
    parser.add_argument("--providers", default="auto",
                        help="onnxruntime execution providers: auto (default: the best available of tensorrt, cuda, "
                        "cpu) or a list such as cuda,cpu; a missing one is an error")
    parser.add_argument("--max-keypoints", type=int, default=2000, help="ORB features per frame (default 2000)")
    parser.add_argument("--max-frames", type=int, help="stop after this many frames")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="change a VOConfig knob (VALUE as JSON; mapping.FIELD for the mapping's), e.g. "
                             "init_wanted_landmarks=100; repeatable")
    parser.add_argument("--lowlight", help="dark, onboard, or GAMMA,SIGMA[,GAIN]: darken every frame (see below)")
    parser.add_argument("--viz", action="store_true",
                        help="with -o: viz.mp4 and viz/*.png, each frame (contrast-stretched) with its keypoints, the "
                             "landmarks it tracked and its state (a PNG every 10th frame and every frame not tracked)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def _check_options(args: argparse.Namespace) -> None:
    """Refuse out-of-range numbers before anything is read or written."""
    check_thread_count(args.threads, "--threads")  # 1 to the cores there are
    if args.viz and args.output is None:
        raise VORuntimeError("--viz writes its pictures into the run folder: give -o DIR")
    check_thread_count(args.blas_threads, "--blas-threads")
    least = VOConfig().min_features  # fewer features per frame can never be tracked
    if not least <= args.max_keypoints <= MAX_ORB_KEYPOINTS:
        raise VORuntimeError(f"--max-keypoints must be between {least} (the VO needs {least} features a frame) "
                             f"and {MAX_ORB_KEYPOINTS}, got {args.max_keypoints}")
    if not 0 <= args.extract_ahead <= MAX_EXTRACT_AHEAD:
        raise VORuntimeError(f"--extract-ahead must be between 0 and {MAX_EXTRACT_AHEAD}, got {args.extract_ahead}")
    if args.max_frames is not None and args.max_frames < 1:
        raise VORuntimeError(f"--max-frames must be at least 1, got {args.max_frames}")
    if args.camera < 0:
        raise VORuntimeError(f"--camera must be >= 0, got {args.camera}")
    args.vo_config, args.config_overrides = config_from_overrides(args.set, mapping_thread=args.mapping_thread)


def _progress(items: Iterator, total: int, enabled: bool) -> Iterator:
    """tqdm's bar on a terminal; in a log, CI or a pipe a line every 10 s with the rate and an ETA (progress.py)."""
    from vo_runtime.progress import progress_bar

    return progress_bar(items, total=total, desc="vo", unit="frame", enabled=enabled)


def _load_groundtruth(args: argparse.Namespace, sequence: Sequence) -> Any:
    """The ground-truth trajectory asked for, read before the run so a bad file fails at once; None if none."""
    if args.gt is None:
        return None
    path = sequence.groundtruth if args.gt == "auto" else Path(args.gt)
    if path is None:
        raise VORuntimeError(f"--gt auto: {args.images} has no poses.txt, groundtruth.txt or "
                             "mav0/state_groundtruth_estimate0/data.csv")
    from vo_runtime.evaluate import require_evaluation_packages, sequence_groundtruth

    require_evaluation_packages()
    return sequence_groundtruth(sequence, path)


def _frame_loader(path: Path, lowlight: Darkening | None, index: int) -> Callable[[], np.ndarray]:
    """Read (and darken) one frame file; run on the extraction thread. A bad file raises `FrameError`, so the
    frame is skipped and flagged, never fatal (a frame of another size too: `MonoVO.stream`)."""
    def load() -> np.ndarray:
        image = read_frame(path)
        return image if lowlight is None else lowlight(to_gray_u8(image), seed=index)

    return load


def run(args: argparse.Namespace) -> int:
    _check_options(args)
    # Held from the first check to the final swap; never inside the artefact (vo_runtime.outputs).
    with claim_output(args.output, VO_RUN, args.force, [args.artefact]) if args.output is not None else nullcontext() as claim:
        return _run(args, claim)


def _run(args: argparse.Namespace, claim: OutputClaim | None) -> int:
    from vo_runtime.providers import parse_providers

    providers = parse_providers(args.providers)
    lowlight = parse_lowlight(args.lowlight)
    sequence = open_sequence(args.images, args.calib, args.camera)
    groundtruth = _load_groundtruth(args, sequence)
    frames = sequence.frames[: args.max_frames]
    height, width = frame_size(sequence.camera, frames)
    if args.features == "artefact" and args.artefact is None:
        args.artefact = default_artefact(width, height)  # the shipped artefact for this camera's aspect
    extractor = (OrbExtractor(args.max_keypoints) if args.features == "orb"
                 else FeatureExtractor(args.artefact, threads=args.threads, providers=providers))
    _warn_on_squeezed_frames(extractor, height, width)
    vo = VisualOdometry(extractor, sequence.camera, args.vo_config)
    with threadpool_limits(limits=args.blas_threads, user_api="blas"):
        stream = (StreamFrame(_frame_loader(path, lowlight, index), sequence.timestamps[index], path.name)
                  for index, path in enumerate(frames))
        observations = []  # per frame, for --viz: keypoints and the landmark each matched (float32 / int32)
        for _ in _progress(vo.stream(stream, args.extract_ahead, skip_wrong_size=True), len(frames),
                           not args.no_progress):
            if args.viz:
                observations.append(_compact(vo.observations))
        vo.finish()
    used = [r for r in vo.results if r.status != SKIPPED]
    skipped = [r for r in vo.results if r.status == SKIPPED]
    if not used:
        raise VORuntimeError(f"none of the {len(frames)} frames could be used ({skipped[0].problem})")
    states = [r.status for r in vo.results]
    dropped = [r for r in vo.results if r.map_dropped]  # broken maps noticed and thrown away
    summary: dict[str, Any] = {
        "features": args.features if args.features == "orb" else str(args.artefact),
        "providers": ",".join(extractor.providers),
        "sequence": str(args.images), "layout": sequence.layout, "lowlight": args.lowlight,
        "config": args.config_overrides,
        "frames": len(vo.results), "states": {s: states.count(s) for s in dict.fromkeys(states)},
        "skipped_frames": len(skipped),
        "maps_dropped": len(dropped),
        "maps_merged": sum(r.merged_scale is not None for r in vo.results),
        "median_extract_ms": round(float(np.median([r.extract_ms for r in used])), 2),
        "median_track_ms": round(float(np.median([r.track_ms for r in used])), 2),
        "median_inliers": float(np.median([r.num_inliers for r in used])),
    }
    report = None
    if groundtruth is not None:
        from vo_runtime.evaluate import evaluate

        try:
            report = evaluate(vo.results, groundtruth, sequence.layout, sequence.timestamps)
            summary.update({k: v for k, v in report.items() if not k.startswith("_")})
        except VORuntimeError as exc:  # e.g. never initialised: keep the trajectory, say why there is no ATE
            summary["ate_rmse_m"] = None
            summary["evaluation_error"] = str(exc)
    if claim is not None:
        viz = (observations, lowlight) if args.viz else None
        _write_outputs(claim, vo.results, frames, summary, report, viz)
    print(json.dumps(summary) if args.json else " ".join(f"{k}={v}" for k, v in summary.items()))
    if skipped:
        print(f"warning: skipped {len(skipped)} of {len(frames)} frames (pose held), first: {skipped[0].problem}",
              file=sys.stderr)
    if dropped:
        print(f"warning: the VO dropped {len(dropped)} broken map(s) and built new ones, first at frame "
              f"{dropped[0].index}: {dropped[0].problem}", file=sys.stderr)
    if claim is not None:  # the line that says where it wrote (stderr under --json, whose stdout is the JSON alone)
        written = sorted(p.name for p in args.output.iterdir() if not p.name.startswith("."))
        print(f"wrote {args.output}: {', '.join(written)}", file=sys.stderr if args.json else sys.stdout)
    return 0




def _warn_on_squeezed_frames(extractor: Any, height: int | None, width: int | None) -> None:
    """One warning line when the artefact's input aspect differs from the camera's, naming the export for it."""
    if not hasattr(extractor, "aspect_distortion"):
        return
    if not (height and width) or extractor.aspect_distortion(height, width) <= ASPECT_TOLERANCE:
        return
    pixels = extractor.height * extractor.width
    suggestion = f"{8 * round(math.sqrt(pixels * height / width) / 8)}x{8 * round(math.sqrt(pixels * width / height) / 8)}"
    # Patch alignment recovers most of the precision (KITTI: a 152x504 export tracked no better than the
    # squeezed 240x320 one with it, docs/vo.md), so this informs rather than prescribes.
    print(f"warning: {width}x{height} frames are resized to the artefact's {extractor.width}x{extractor.height}, "
          f"another aspect, which costs detection precision; patch alignment on the full frames recovers most "
          f"of it; an artefact for this camera's aspect is toolkit export --input-size {suggestion} "
          f"(as many pixels)", file=sys.stderr)


def _frame_record(result: VOResult, path: Path) -> dict[str, Any]:
    record = {"index": result.index, "file": path.name, "timestamp": result.timestamp, "state": result.status,
              "features": result.num_features, "matches": result.num_matches, "inliers": result.num_inliers,
              "landmarks": result.num_landmarks, "keyframe": result.keyframe, "tracked_by": result.tracked_by,
              "extract_ms": round(result.extract_ms, 3), "track_ms": round(result.track_ms, 3),
              "match_ms": round(result.match_ms, 3), "pose_ms": round(result.pose_ms, 3),
              "mapping_ms": round(result.mapping_ms, 3)}
    if result.problem is not None:
        record["problem"] = result.problem
    if result.map_dropped:
        record["map_dropped"] = True
    if result.merged_scale is not None:
        record["merged_scale"] = round(result.merged_scale, 4)
    return record


def _compact(observations: Any) -> Any:
    if observations is None:
        return None
    keypoints, landmark = observations
    return keypoints.astype(np.float32), None if landmark is None else landmark.astype(np.int32)


def _write_viz(folder: Path, results: list[VOResult], frames: list[Path], observations: list, lowlight: Any) -> None:
    """The --viz overlays: each frame read (and darkened) again, as the VO saw it."""
    from vo_runtime.viz import VizWriter, draw_frame

    writer = VizWriter(folder)
    try:
        for index, (result, path, seen) in enumerate(zip(results, frames, observations)):
            try:
                gray = to_gray_u8(_frame_loader(path, lowlight, index)())
            except FrameError:
                continue  # an unreadable frame was skipped; frames.json says why
            keypoints, landmark = seen if seen is not None else (None, None)
            writer.add(draw_frame(gray, result, keypoints, landmark), result)
    finally:
        writer.close()


def _write_outputs(claim: OutputClaim, results: list[VOResult], frames: list[Path], summary: dict[str, Any],
                   report: dict[str, Any] | None, viz: tuple | None = None) -> None:
    """Write everything into a staging directory beside the claimed output, then swap it in (if unchanged)."""
    with claim.writing() as staging:
        write_trajectory(staging / "trajectory_tum.txt", results, "tum")
        write_trajectory(staging / "trajectory_kitti.txt", results, "kitti")
        records = [_frame_record(result, path) for result, path in zip(results, frames)]
        (staging / "frames.json").write_text(json.dumps(records, indent=1))
        (staging / "summary.json").write_text(json.dumps(summary, indent=2))
        if report is not None:
            from vo_runtime.evaluate import plot_trajectory

            light = "normal light" if summary["lowlight"] is None else f"--lowlight {summary['lowlight']}"
            plot_trajectory(staging / "trajectory.png", report,
                            f"{Path(summary['sequence']).name} ({Path(summary['features']).name}, {light})")
        if viz is not None:
            _write_viz(staging, results, frames, *viz)


def build_parser(prog: str = "python -m vo_runtime") -> argparse.ArgumentParser:
    return command_parser(prog, DESCRIPTION, EPILOG, add_arguments, run)


def main(argv: list[str] | None = None) -> int:
    return run_guarded(build_parser(), argv, (VORuntimeError,))
