"""The picture of docs/vo_takeoff.md: the drone's take-off on EuRoC MH_05 (frames 10, 33 and 45) as recorded and
through ``--lowlight dark``, with the keypoints a network artefact (green; default: the one shipped for this
camera) and ORB 2000 (red) detect in the dark.

    python bench/takeoff_picture.py                  # writes docs/vo_takeoff_frames.png
    python bench/takeoff_picture.py --artefact DIR -o /tmp/takeoff.png   # e.g. the full network at 480x752
    python bench/takeoff_picture.py --frames 0,20,40 -o /tmp/takeoff.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vo_runtime import FeatureExtractor, OrbExtractor  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.datasets import open_sequence  # noqa: E402
from vo_runtime.features import to_gray_u8  # noqa: E402
from vo_runtime.lowlight import PRESETS  # noqa: E402
from vo_runtime.sequence import read_frame  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, default=ROOT.parent / "shared/data/euroc_mh05_f000000-000199")
    parser.add_argument("--frames", default="10,33,45")
    parser.add_argument("--artefact", type=Path, help="default: the artefact shipped for the sequence's camera")
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "docs" / "vo_takeoff_frames.png")
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sequence = open_sequence(args.sequence)
    frames = [int(v) for v in args.frames.split(",")]
    gray = [to_gray_u8(read_frame(sequence.frames[i])) for i in frames]
    height, width = gray[0].shape
    learned = FeatureExtractor(args.artefact or default_artefact(width, height), threads=1)
    orb = OrbExtractor(2000)
    fig, axes = plt.subplots(2, len(frames), figsize=(4.3 * len(frames), 5.8), dpi=64)
    for column, (index, image) in enumerate(zip(frames, gray)):
        dark = PRESETS["dark"](image, seed=index)
        axes[0, column].imshow(image, cmap="gray", vmin=0, vmax=255)
        axes[0, column].set_title(f"frame {index}, as recorded", fontsize=10)
        # The dark frame brightened 4x for the eye; the detectors saw it as it is.
        axes[1, column].imshow(dark, cmap="gray", vmin=0, vmax=64)
        ours, theirs = learned(dark).keypoints, orb(dark).keypoints
        axes[1, column].scatter(ours[:, 0], ours[:, 1], s=2, c="lime", label=f"learned: {len(ours)}")
        axes[1, column].scatter(theirs[:, 0], theirs[:, 1], s=4, c="red", label=f"ORB 2000: {len(theirs)}")
        axes[1, column].legend(loc="lower right", fontsize=8, markerscale=3)
        axes[1, column].set_title(f"frame {index}, --lowlight dark (shown 4x brighter)", fontsize=10)
        for row in (0, 1):
            axes[row, column].axis("off")
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
