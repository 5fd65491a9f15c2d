"""A long flight: does the VO's time per frame or its memory grow with the frames it has flown?

    python bench/palindrome_sequence.py ../shared/data/euroc_mh05_f000000-000199 runs/mh05_laps5 --laps 5
    python bench/long_flight.py --sequence runs/mh05_laps5 --light low

Every ``--every`` frames it prints the frames' mean time (extraction and tracking, and the keyframes' mapping,
which runs inline), the keyframes made, the landmarks alive, the rows the landmark arrays hold and the bytes
the map holds (the keyframes' arrays and the landmarks', counted exactly, so other allocations do not blur it),
and the process's peak resident memory. Frames are read from disk one at a time, so nothing else grows.
One thread for onnxruntime, OpenCV and numpy's BLAS; the ATE against the ground truth at the end.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from eval_vo import LIGHTS, lit_frame  # noqa: E402
from vo_runtime import FeatureExtractor, OrbExtractor, VisualOdometry, VOConfig  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.datasets import frame_size, open_sequence  # noqa: E402
from vo_runtime.errors import VORuntimeError  # noqa: E402
from vo_runtime.evaluate import evaluate, sequence_groundtruth  # noqa: E402
from vo_runtime.localmap import LANDMARK_ARRAYS, LocalMap  # noqa: E402
from vo_runtime.odometry import TRACKED_STATES  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402


def map_bytes(local_map: LocalMap | None) -> int:
    """Bytes of the map's arrays: every keyframe's and the landmarks' (the observation dicts left out); 0 before
    the first map."""
    if local_map is None:
        return 0
    total = sum(getattr(local_map, name).nbytes for name in LANDMARK_ARRAYS)
    for keyframe in local_map.keyframes:
        total += sum(array.nbytes for array in (keyframe.points, keyframe.pixels, keyframe.descriptors,
                                                 keyframe.landmark, keyframe.gray, keyframe.sigma)
                     if array is not None)
    return total


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, required=True, help="a sequence folder (any layout `toolkit vo` reads)")
    parser.add_argument("--features", choices=("artefact", "orb"), default="artefact")
    parser.add_argument("--artefact", type=Path, help="default: the shipped artefact for the camera")
    parser.add_argument("--light", choices=sorted(LIGHTS), default="normal")
    parser.add_argument("--seed", type=int, default=0, help="noise draw, as eval_vo's --seeds numbers them")
    parser.add_argument("--every", type=int, default=200, help="frames per printed row")
    args = parser.parse_args()
    if args.every < 1:
        print("error: --every must be at least 1", file=sys.stderr)
        return 2
    try:
        sequence = open_sequence(args.sequence)
        if args.features == "orb":
            extractor = OrbExtractor(2000)
        else:
            height, width = frame_size(sequence.camera, sequence.frames)
            extractor = FeatureExtractor(args.artefact or default_artefact(width, height), threads=1)
    except (VORuntimeError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    cv2.setNumThreads(1)
    vo = VisualOdometry(extractor, sequence.camera, VOConfig())
    print("| frames | ms a frame | tracked | keyframes | landmarks alive | landmark rows | map MB | peak RSS MB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    spent, tracked = 0.0, 0
    with threadpool_limits(1):
        for index, image in enumerate(read_frames(sequence.frames)):
            frame = lit_frame(image, args.light, 0, index, args.seed)
            start = time.perf_counter()
            result = vo.track(frame, sequence.timestamps[index])
            spent += time.perf_counter() - start
            tracked += result.status in TRACKED_STATES
            if (index + 1) % args.every == 0 or index + 1 == len(sequence.frames):
                count = (index % args.every) + 1
                rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                keyframes, alive, rows = (0, 0, 0) if vo.map is None else \
                    (len(vo.map.keyframes), int(vo.map.alive.sum()), len(vo.map.alive))
                print(f"| {index + 1} | {1e3 * spent / count:.1f} | {tracked} | {keyframes} | {alive} | {rows} | "
                      f"{map_bytes(vo.map) / 2**20:.1f} | {rss:.0f} |", flush=True)
                spent, tracked = 0.0, 0
    vo.finish()
    try:
        report = evaluate(vo.results, sequence_groundtruth(sequence), sequence.layout, sequence.timestamps)
        print(f"ATE {report['ate_rmse_m']:.4f} m over {report['path_length_m']:.1f} m of path, "
              f"{report['frames_evaluated']} frames")
    except VORuntimeError as error:
        print(f"no ATE: {error}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
