"""Where a VO run breaks: its scale and rotation against the ground truth, frame by frame.

    python bench/scale_trace.py --sequence ../shared/data/euroc_mh05_f000000-000199 --start 100 --light low
    python bench/scale_trace.py ... --features orb --every 1 --plot runs/trace.png

ATE says that a run failed; this says when and how. For every tracked frame i with a tracked frame i-k
(``--gap``, default 5), it prints the estimated camera's travel over those k frames divided by the true
travel (the local scale; normalised by its median over the first 20 tracked frames, so 1.0 is "the scale of
the first map", and a collapse shows as a drop), the angle between the estimated and the true direction of
travel, and the error of the relative rotation over the k frames, beside the frame's state, inliers and
keyframe flag. Frames are darkened as `bench/eval_vo.py` does (`lit_frame`; ``--seed K`` its K-th noise draw),
so a start, light and draw here is that table's run. Scale-free quantities only: no alignment, so one bad stretch
does not smear over the rest.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.eval_vo import LIGHTS, lit_frame  # noqa: E402
from vo_runtime import FeatureExtractor, OrbExtractor, VisualOdometry  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.config_overrides import config_from_overrides  # noqa: E402
from vo_runtime.datasets import frame_size, open_sequence  # noqa: E402
from vo_runtime.errors import VORuntimeError, first_line  # noqa: E402
from vo_runtime.evaluate import sequence_groundtruth  # noqa: E402
from vo_runtime.odometry import TRACKED_STATES  # noqa: E402
from vo_runtime.probation import rotation_angle_deg  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402
from vo_runtime.timestamps import nearest_samples  # noqa: E402
from vo_runtime.travel_check import angle_deg  # noqa: E402

REFERENCE_FRAMES = 20  # tracked frames whose median local scale is 1.0
MAX_STAMP_GAP_S = 0.02  # a frame's ground truth: the sample nearest its timestamp, at most this far


def truth_at_frames(groundtruth, stamps: list[float]) -> list[np.ndarray]:
    """The ground-truth camera pose of each frame: the sample nearest its timestamp. TUM's groundtruth.txt is the
    motion capture's ~100 Hz stream, not one pose per frame; KITTI's and EuRoC's trajectories are stamped with
    the frames' own timestamps, so each frame finds its own row."""
    times = np.asarray(groundtruth.timestamps, np.float64)
    order = np.argsort(times, kind="stable")
    nearest, gaps = nearest_samples(times[order], stamps)
    if np.any(gaps > MAX_STAMP_GAP_S):
        frame = int(np.argmax(gaps))
        raise VORuntimeError(f"frame {frame}: no ground-truth pose within {1e3 * MAX_STAMP_GAP_S:.0f} ms of its "
                             f"timestamp (nearest {1e3 * gaps[frame]:.0f} ms)")
    poses = groundtruth.poses_se3
    return [poses[order[k]] for k in nearest]


def trace(results: list, truth: list[np.ndarray], gap: int) -> list[dict]:
    """Per tracked frame with a tracked frame ``gap`` back: raw local scale, direction and rotation errors."""
    rows = []
    for result in results:
        i = result.index
        if i < gap or result.status not in TRACKED_STATES or results[i - gap].status not in TRACKED_STATES:
            continue
        estimated = np.linalg.inv(results[i - gap].pose) @ result.pose   # camera i in camera i-gap's frame
        true = np.linalg.inv(truth[i - gap]) @ truth[i]
        travel = float(np.linalg.norm(true[:3, 3]))
        rows.append({"frame": i, "status": result.status, "inliers": result.num_inliers, "keyframe": result.keyframe,
                     "scale": float(np.linalg.norm(estimated[:3, 3])) / max(travel, 1e-9), "travel_m": travel,
                     "direction_deg": angle_deg(estimated[:3, 3], true[:3, 3]),
                     "rotation_deg": rotation_angle_deg(estimated[:3, :3].T @ true[:3, :3])})
    if rows:
        reference = float(np.median([r["scale"] for r in rows[:REFERENCE_FRAMES]]))
        for r in rows:
            r["scale"] /= max(reference, 1e-12)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, required=True)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--light", choices=sorted(LIGHTS), default="normal")
    parser.add_argument("--features", choices=("artefact", "orb"), default="artefact")
    parser.add_argument("--artefact", type=Path, help="default: the shipped artefact for the camera")
    parser.add_argument("--seed", type=int, default=0,
                        help="noise draw of a darkened run, as eval_vo's --seeds numbers them (0: the first)")
    parser.add_argument("--gap", type=int, default=5, help="frames between the two poses compared")
    parser.add_argument("--every", type=int, default=5, help="print every this many frames")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                        help="a VOConfig knob, as the vo command's --set (VALUE as JSON; mapping.FIELD)")
    parser.add_argument("--plot", type=Path, help="also draw scale and errors against the frame index here")
    args = parser.parse_args(argv)
    try:
        return run(args)
    except VORuntimeError as exc:  # a bad path, layout or --set value
        print(f"error: {first_line(exc)}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace) -> int:
    sequence = open_sequence(args.sequence)
    if args.seed < 0:
        raise VORuntimeError(f"--seed {args.seed}: noise draws are numbered from 0")
    if not 0 <= args.start < len(sequence.frames) - args.gap:
        raise VORuntimeError(f"--start {args.start}: the sequence has {len(sequence.frames)} frames")
    frames, stamps = sequence.frames[args.start:], sequence.timestamps[args.start:]
    truth = truth_at_frames(sequence_groundtruth(sequence), sequence.timestamps)[args.start:]
    if args.features == "orb":
        extractor = OrbExtractor(2000)
    else:
        height, width = frame_size(sequence.camera, sequence.frames)
        artefact = args.artefact or default_artefact(width, height)
        extractor = FeatureExtractor(artefact, threads=1)
    config, _ = config_from_overrides(args.set)
    vo = VisualOdometry(extractor, sequence.camera, config)
    for index, image in enumerate(read_frames(frames)):
        vo.track(lit_frame(image, args.light, args.start, index, args.seed), stamps[index])
    vo.finish()
    rows = trace(vo.results, truth, args.gap)
    draw = f" (noise draw {args.seed})" if args.seed else ""
    print(f"{args.sequence.name} from {args.start}, {args.light} light{draw}, {args.features}: {len(rows)} frames "
          f"traced (frame numbers from the start; scale 1.0 = median of the first {REFERENCE_FRAMES})")
    print("frame  state          inliers  kf  scale  dir_err_deg  rot_err_deg  true_travel_mm")
    for r in rows:
        if r["frame"] % max(args.every, 1) == 0:
            print(f"{r['frame']:5d}  {r['status']:13s}  {r['inliers']:7d}  {'K' if r['keyframe'] else ' ':2s}  "
                  f"{r['scale']:5.2f}  {r['direction_deg']:11.1f}  {r['rotation_deg']:11.2f}  {1e3 * r['travel_m']:14.1f}")
    if args.plot is not None and rows:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        frame = [r["frame"] + args.start for r in rows]
        figure, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        for axis, key, label in zip(axes, ("scale", "direction_deg", "rotation_deg"),
                                    ("local scale", "travel dir. error (deg)", "rotation error (deg)")):
            axis.plot(frame, [r[key] for r in rows])
            axis.set_ylabel(label)
        axes[0].set_yscale("log")
        axes[2].set_xlabel("frame of the sequence")
        figure.suptitle(f"{args.sequence.name}, from {args.start}, {args.light} light, {args.features}, gap {args.gap}")
        figure.tight_layout()
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(args.plot, dpi=90)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
