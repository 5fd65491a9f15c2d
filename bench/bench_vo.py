"""Frames per second of the whole VO runtime at 240x320 on this machine, and the share of feature extraction.

    python bench/bench_vo.py                      # ORB and the hand-built Harris test artefact
    python bench/bench_vo.py --artefact out/cpu   # ... plus an exported network artefact

Every extractor runs the same frames (KITTI 07, resized to 320x240 with the camera scaled to match) in one
process, one after the other, with onnxruntime on one thread; the medians per frame are printed side by
side. Times include reading nothing from disk (frames are decoded and resized before the clock starts).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from vo_runtime import FeatureExtractor, OrbExtractor, VisualOdometry  # noqa: E402
from vo_runtime.datasets import open_sequence  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402

SIZE = (320, 240)  # width, height


def run(name: str, extractor, frames: list[np.ndarray], camera, stamps: list[float]) -> dict:
    vo = VisualOdometry(extractor, camera)
    for image, stamp in zip(frames, stamps):
        vo.track(image, stamp)
    extract = np.array([r.extract_ms for r in vo.results])
    track = np.array([r.track_ms for r in vo.results])
    total = extract + track
    states = [r.status for r in vo.results]
    return {"name": name, "fps": 1000.0 * len(total) / total.sum(), "extract_ms": extract.mean(),
            "track_ms": track.mean(), "track_p95": np.percentile(track, 95),
            "extract_share": extract.sum() / total.sum(),
            "tracked": sum(s in ("tracking", "reinitialised") for s in states), "frames": len(states)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--artefact", action="append", default=[], help="artefact directory (repeatable)")
    parser.add_argument("--sequence", default=str(ROOT.parent / "shared/data/kitti_odom07_f000000-000159"))
    parser.add_argument("--frames", type=int, default=160)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    sequence = open_sequence(args.sequence)
    frames = [cv2.resize(im, SIZE, interpolation=cv2.INTER_AREA) for im in read_frames(sequence.frames[: args.frames])]
    height, width = next(read_frames(sequence.frames[:1])).shape[:2]
    camera = sequence.camera.resized((width, height), SIZE)
    from test_vo_artefact import write_artefact

    with tempfile.TemporaryDirectory() as tmp:
        extractors = [("orb-1000", OrbExtractor(1000)),
                      ("harris-fixture", FeatureExtractor(write_artefact(Path(tmp) / "harris"), threads=1))]
        extractors += [(Path(a).name, FeatureExtractor(a, threads=1)) for a in args.artefact]
        rows = [run(name, ex, frames, camera, sequence.timestamps) for name, ex in extractors]
    print(f"{len(frames)} frames of {Path(args.sequence).name} at {SIZE[1]}x{SIZE[0]}, means per frame, 1 thread")
    print(f"{'extractor':<18}{'fps':>7}{'extract ms':>12}{'track ms':>10}{'track p95':>11}{'extract share':>15}"
          f"{'tracked':>10}")
    for r in rows:
        print(f"{r['name']:<18}{r['fps']:>7.1f}{r['extract_ms']:>12.2f}{r['track_ms']:>10.2f}{r['track_p95']:>11.2f}"
              f"{r['extract_share']:>14.0%}{r['tracked']:>6}/{r['frames']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
