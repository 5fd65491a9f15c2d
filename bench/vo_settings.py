"""How a VO setting does over many runs: every dev sequence from several first frames, in each light.

    python bench/vo_settings.py                                   # the defaults, normal, dark and onboard light
    python bench/vo_settings.py --set align_gain=2 --set keyframe_min_tracked=50   # a variant
    python bench/vo_settings.py --features orb --light normal     # ORB in the same pipeline
    python bench/vo_settings.py --artefact out/cpu-500            # another export (e.g. another keypoint budget)

Single runs of these 20-200-frame clips move by tens of centimetres with any change (docs/vo.md), so a setting
is judged on the geometric mean (and the worst) of the ATE over many starts (`eval_vo.STARTS`): in normal
light KITTI 07 from frames 0, 10, ..., 130, KITTI 06 from 0, 5, ..., 30, TUM fr2 desk from 0 and EuRoC MH_05
from 0, 20, ..., 100 (28 runs); in each dark preset KITTI 07 from 0, 25, ..., 100, KITTI 06 from 0, 10, 20,
TUM and EuRoC as in normal light (15 runs). The same runs as ``eval_vo.py --starts study`` (which does the
work), two processes by default, printing the summary only.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]


def main() -> int:
    import eval_vo

    argv = sys.argv[1:]
    if "--features" not in argv:
        argv += ["--features", "artefact"]
    if "--workers" not in argv:
        argv += ["--workers", "2"]
    sys.argv = [sys.argv[0], *argv, "--starts", "study", "--summary-only"]
    return eval_vo.main()


if __name__ == "__main__":
    sys.exit(main())
