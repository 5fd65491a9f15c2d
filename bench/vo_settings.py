"""How a VO setting does over many runs: every dev sequence from several first frames, normal and low light.

    python bench/vo_settings.py                                   # the defaults, normal and low light
    python bench/vo_settings.py --set align_gain=2 --set keyframe_min_tracked=50   # a variant
    python bench/vo_settings.py --features orb --light normal     # ORB in the same pipeline
    python bench/vo_settings.py --artefact out/cpu-500            # another export (e.g. another keypoint budget)

Single runs of these 20-160-frame sequences move by tens of centimetres with any change (docs/vo.md), so a
setting is judged on the geometric mean of the ATE over many starts: KITTI 07 from frames 0, 10, ..., 130,
KITTI 06 from 0, 5, ..., 30 and TUM fr2 desk from 0 in normal light (22 runs); KITTI 07 from 0, 25, ..., 100,
KITTI 06 from 0, 10, 20 and TUM in simulated low light (`--lowlight 2,3,0.3`, 9 runs). Runs go to
``--workers`` processes (one thread each, as in `eval_vo.py`, whose `run_one` and `summary` do the work); the
table gives per sequence and light the geometric mean, every run's ATE and the least tracked share.
"""
from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

STARTS = {
    "normal": {"kitti_odom07_f000000-000159": range(0, 131, 10), "kitti_odom06_f000000-000050": range(0, 31, 5),
               "tum_fr2_desk_snippet": [0]},
    "low": {"kitti_odom07_f000000-000159": range(0, 101, 25), "kitti_odom06_f000000-000050": range(0, 21, 10),
            "tum_fr2_desk_snippet": [0]},
}


def run(job: tuple) -> dict:
    data, name, features, light, start, overrides, artefact = job
    import cv2

    cv2.setNumThreads(1)
    import eval_vo
    from vo_runtime.artefact import default_artefact

    return eval_vo.run_one(data / name, features, light, 2000, overrides, artefact or default_artefact(), None, None,
                           start)


def main() -> int:
    import eval_vo

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared/data")
    parser.add_argument("--features", default="artefact", choices=["artefact", "orb"])
    parser.add_argument("--artefact", type=Path, help="another artefact directory (default: the shipped one)")
    parser.add_argument("--light", default="normal,low", help="normal and/or low")
    parser.add_argument("--set", action="append", default=[], help="VOConfig field=value (JSON; mapping.FIELD too)")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    overrides = eval_vo.parse_overrides(args.set)
    jobs = [(args.data, name, args.features, light, start, overrides, args.artefact)
            for light in args.light.split(",") for name, starts in STARTS[light].items() for start in starts]
    began = time.perf_counter()
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        rows = list(pool.map(run, jobs))
    print(f"{args.features}, settings {overrides or 'default'}: {len(rows)} runs, {time.perf_counter() - began:.0f} s")
    print(eval_vo.summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
