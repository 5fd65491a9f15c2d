"""A EuRoC ASL sequence played forward and then backward, as a longer flight for the VO.

    python bench/palindrome_sequence.py ../shared/data/euroc_mh05_f000000-000199 runs/mh05_there_and_back
    python bench/eval_vo.py --data runs --sequences mh05_there_and_back --starts 0 --seeds 3 \\
        --features artefact,orb --light normal,low,onboard

The drone clip is 10 s of one take-off; played back it becomes a 20 s flight that ends where it began: the
camera slows, turns back and descends towards the near structure it took off from, which the forward clip
never asks of a map built on the far hall (docs/vo_euroc.md, "A young map's baseline rule"). Frames 0..N-1
then N-2..0, restamped every 50 ms; each frame's ground truth is the body pose at its original stamp. The frames
are symbolic links to the source's images (nothing is copied); the output folder must not exist yet.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vo_runtime.euroc import MAX_ASSOCIATION_S  # noqa: E402
from vo_runtime.timestamps import nearest_samples  # noqa: E402

FRAME_NS = 50_000_000  # 20 Hz, the EuRoC camera's rate


def _rows(path: Path) -> tuple[str, list[list[str]]]:
    lines = path.read_text().splitlines()
    return lines[0], [line.split(",") for line in lines[1:] if line and not line.startswith("#")]


def write_palindrome(source: Path, target: Path, laps: int = 1) -> int:
    """Write ``target``/mav0 from ``source``/mav0 (cam0 and the ground truth), the flight there and back
    ``laps`` times; returns the frame count."""
    cam_header, frames = _rows(source / "mav0/cam0/data.csv")
    truth_header, truth = _rows(source / "mav0/state_groundtruth_estimate0/data.csv")
    lap = list(range(len(frames) - 1)) + list(range(len(frames) - 1, 0, -1))  # there and back, less the last 0
    order = lap * laps + [0]
    # Each source frame's ground-truth row as the VO's reader associates it (nearest, within 5 ms; none beyond).
    nearest, gaps = nearest_samples(np.array([int(row[0]) for row in truth], np.float64),
                                    [int(row[0]) for row in frames])
    truth_of = [truth[j][1:] if gap <= MAX_ASSOCIATION_S * 1e9 else None for j, gap in zip(nearest, gaps)]
    (target / "mav0/cam0/data").mkdir(parents=True, exist_ok=True)
    (target / "mav0/state_groundtruth_estimate0").mkdir(parents=True)
    shutil.copy(source / "mav0/cam0/sensor.yaml", target / "mav0/cam0/sensor.yaml")
    first = int(frames[0][0])
    cam_lines, truth_lines = [cam_header], [truth_header]
    for k, i in enumerate(order):
        stamp = first + k * FRAME_NS
        (target / f"mav0/cam0/data/{stamp}.png").symlink_to((source / "mav0/cam0/data" / frames[i][1]).resolve())
        cam_lines.append(f"{stamp},{stamp}.png")
        if truth_of[i] is not None:
            truth_lines.append(",".join([str(stamp)] + truth_of[i]))
    (target / "mav0/cam0/data.csv").write_text("\n".join(cam_lines) + "\n")
    (target / "mav0/state_groundtruth_estimate0/data.csv").write_text("\n".join(truth_lines) + "\n")
    return len(order)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a EuRoC ASL sequence (the folder holding mav0/)")
    parser.add_argument("target", type=Path, help="the new sequence's folder (must not exist)")
    parser.add_argument("--laps", type=int, default=1, help="times the flight goes there and back (default 1)")
    args = parser.parse_args()
    if args.laps < 1:
        print(f"error: --laps must be at least 1, got {args.laps}", file=sys.stderr)
        return 2
    if not (args.source / "mav0/cam0/data.csv").is_file() \
            or not (args.source / "mav0/state_groundtruth_estimate0/data.csv").is_file():
        print(f"error: {args.source} is not a EuRoC ASL sequence with ground truth (mav0/cam0/data.csv, "
              "mav0/state_groundtruth_estimate0/data.csv)", file=sys.stderr)
        return 2
    if args.target.exists():
        print(f"error: {args.target} exists; choose a new folder", file=sys.stderr)
        return 2
    args.target.parent.mkdir(parents=True, exist_ok=True)
    # Written under a fresh name of its own first: nothing half-written under the target's name, and a failure
    # removes only what this run wrote.
    partial = Path(tempfile.mkdtemp(prefix=args.target.name + ".partial-", dir=args.target.parent))
    try:
        count = write_palindrome(args.source, partial, args.laps)
    except (ValueError, IndexError, OSError) as error:
        shutil.rmtree(partial, ignore_errors=True)
        print(f"error: {args.source}: {error}", file=sys.stderr)
        return 2
    partial.rename(args.target)
    print(f"{args.target}: {count} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
