"""The picture of docs/vo.md's darkness presets: one EuRoC MH_05 frame as the camera gave it, through
``--lowlight dark`` and through ``--lowlight onboard``, each with its grey-level histogram.

    python bench/lowlight_picture.py                     # writes docs/lowlight_presets.png
    python bench/lowlight_picture.py --frame 120 -o /tmp/presets.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vo_runtime.datasets import open_sequence  # noqa: E402
from vo_runtime.features import to_gray_u8  # noqa: E402
from vo_runtime.lowlight import PRESETS  # noqa: E402
from vo_runtime.sequence import read_frame  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, default=ROOT.parent / "shared/data/euroc_mh05_f000000-000199")
    parser.add_argument("--frame", type=int, default=60)
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "docs" / "lowlight_presets.png")
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gray = to_gray_u8(read_frame(open_sequence(args.sequence).frames[args.frame]))
    views = [("as recorded", gray), ("--lowlight dark (2,3,0.3)", PRESETS["dark"](gray, seed=args.frame)),
             ("--lowlight onboard", PRESETS["onboard"](gray, seed=args.frame))]
    fig, axes = plt.subplots(2, 3, figsize=(13, 5.6), dpi=90, gridspec_kw={"height_ratios": [3, 1]})
    for column, (title, image) in enumerate(views):
        axes[0, column].imshow(image, cmap="gray", vmin=0, vmax=255)
        axes[0, column].set_title(f"{title}: mean {image.mean():.0f}", fontsize=10)
        axes[0, column].axis("off")
        axes[1, column].hist(image.ravel(), bins=64, range=(0, 255), color="0.3")
        axes[1, column].set_yticks([])
        axes[1, column].set_xlabel("grey level", fontsize=8)
    fig.suptitle(f"{args.sequence.name}, frame {args.frame}: the two darkness presets (seeded per frame)", fontsize=11)
    fig.tight_layout()
    fig.savefig(args.output)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
