"""How precisely two frames' matches land, against the ground truth: keypoints of frames ``--gap`` apart matched
by mutual nearest neighbours (the VO's distance gate and ratio), each match's distance to its epipolar line
under the true relative pose.

    python bench/pair_precision.py --artefact runs/art_x --orb        # the shipped drone artefact beside them
    python bench/pair_precision.py --gap 5 --light low

No VO, no map: this isolates the features. Per light and extractor it prints the matches a pair, those within
1.5 px of their line, their share, and the median distance of those within 5 px. Frames are darkened as
`bench/eval_vo.py` does (`lit_frame`; two noise draws a pair in the dark presets).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.eval_vo import LIGHTS, lit_frame  # noqa: E402
from vo_runtime import FeatureExtractor, OrbExtractor  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.config import VOConfig  # noqa: E402
from vo_runtime.datasets import frame_size, open_sequence  # noqa: E402
from vo_runtime.errors import VORuntimeError, first_line  # noqa: E402
from vo_runtime.evaluate import sequence_groundtruth  # noqa: E402
from vo_runtime.matching import match_mutual_nn  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402

GOOD_PX = 1.5


def epipolar_distances(camera, features_a, features_b, relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(matched rows [M, 2], pixel distance of each match to its epipolar line) for frame b's pose ``relative``
    to frame a's."""
    config = VOConfig()
    points_a = camera.normalise(np.asarray(features_a.keypoints, np.float64))
    points_b = camera.normalise(np.asarray(features_b.keypoints, np.float64))
    pairs = match_mutual_nn(features_a.descriptors, features_b.descriptors, config.match_max_distance,
                            config.match_ratio)
    t = relative[:3, 3]
    essential = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ relative[:3, :3]
    rays_a = np.c_[points_a[pairs[:, 0]], np.ones(len(pairs))]
    rays_b = np.c_[points_b[pairs[:, 1]], np.ones(len(pairs))]
    lines = rays_a @ essential.T
    return pairs, camera.focal * np.abs(np.sum(rays_b * lines, 1)) / np.linalg.norm(lines[:, :2], axis=1)


def quartile_shares(traits: np.ndarray) -> None:
    """Share of matches within GOOD_PX by quartile of the weaker keypoint's score and of the descriptor distance
    (``traits`` [M, 3]: pixels, score, distance)."""
    for column, label in ((1, "score (low -> high)"), (2, "descriptor distance (near -> far)")):
        edges = np.quantile(traits[:, column], [0.0, 0.25, 0.5, 0.75, 1.0])
        quarter = np.clip(np.searchsorted(edges, traits[:, column], side="right") - 1, 0, 3)
        shares = [float(np.mean(traits[quarter == q, 0] < GOOD_PX)) for q in range(4)]
        print(f"    within {GOOD_PX} px by quartile of {label}: " + " / ".join(f"{v:.2f}" for v in shares))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, default=ROOT.parent / "shared/data/euroc_mh05_f000000-000199")
    parser.add_argument("--artefact", type=Path, action="append", default=[], help="also this artefact (repeatable)")
    parser.add_argument("--orb", action="store_true", help="also ORB (2,000 features)")
    parser.add_argument("--gap", type=int, default=3)
    parser.add_argument("--first", type=int, default=40, help="first frame of the first pair")
    parser.add_argument("--every", type=int, default=6, help="frames between pairs")
    parser.add_argument("--light", default="normal,low,onboard")
    parser.add_argument("--quartiles", action="store_true", help="also the share by quartile of score and distance")
    args = parser.parse_args(argv)
    try:
        sequence = open_sequence(args.sequence)
        lights = args.light.split(",")
        if any(light not in LIGHTS for light in lights) or args.gap < 1 or args.every < 1:
            raise VORuntimeError(f"--light takes {', '.join(LIGHTS)}; --gap and --every must be >= 1")
        width_height = frame_size(sequence.camera, sequence.frames)[::-1]
        extractors = {"shipped": FeatureExtractor(default_artefact(*width_height), threads=1)}
        extractors.update({path.name: FeatureExtractor(path, threads=1) for path in args.artefact})
        if args.orb:
            extractors["orb"] = OrbExtractor(2000)
    except VORuntimeError as exc:
        print(f"error: {first_line(exc)}", file=sys.stderr)
        return 2
    groundtruth = sequence_groundtruth(sequence)
    truth = dict(zip(groundtruth.timestamps, groundtruth.poses_se3))
    pairs = [(a, a + args.gap) for a in range(args.first, len(sequence.frames) - args.gap, args.every)]
    frames = dict(enumerate(read_frames(sequence.frames)))
    print(f"{args.sequence.name}: {len(pairs)} pairs {args.gap} frames apart; matches a pair, within {GOOD_PX} px of "
          f"the true epipolar line, share, median px of those within 5 px")
    for light in lights:
        for name, extract in extractors.items():
            counts, good, near, traits = [], [], [], []
            for a, b in pairs:
                for draw in (0, 1) if LIGHTS[light] is not None else (0,):
                    relative = np.linalg.inv(truth[sequence.timestamps[b]]) @ truth[sequence.timestamps[a]]
                    first, second = extract(lit_frame(frames[a], light, 0, a, draw)), \
                        extract(lit_frame(frames[b], light, 0, b, draw))
                    matched, pixels = epipolar_distances(sequence.camera, first, second, relative)
                    counts.append(len(matched))
                    weaker = np.minimum(first.scores[matched[:, 0]], second.scores[matched[:, 1]])
                    distance = np.linalg.norm(first.descriptors[matched[:, 0]] - second.descriptors[matched[:, 1]],
                                              axis=1)
                    traits.append(np.c_[pixels, weaker, distance])
                    good.append(int(np.count_nonzero(pixels < GOOD_PX)))
                    near.append(pixels[pixels < 5])
            share = sum(good) / max(sum(counts), 1)
            print(f"{light:8s} {name:16s} {np.mean(counts):7.1f} {np.mean(good):7.1f} {share:6.2f} "
                  f"{np.median(np.concatenate(near)):6.3f}", flush=True)
            if args.quartiles and name != "orb":
                quartile_shares(np.concatenate(traits))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
