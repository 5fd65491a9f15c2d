"""Two bench/eval_vo.py runs side by side: per sequence and light, the ratio of ATE geometric means with a 95 %
bootstrap interval over starts.

    python bench/compare_runs.py runs/before/results.json runs/after/results.json
    python bench/compare_runs.py runs/old/results.json runs/new/results.json --base-features old240 \\
        --new-features default_artefact          # two artefacts' runs against each other
    python bench/compare_runs.py runs/t/results.json runs/t/results.json --base-features orb \\
        --new-features default_artefact_wide --split-delay 5   # ours against ORB, split by when ORB started

A KITTI 07 run moves by tens of per cent with a grey level of noise (docs/vo_euroc.md, "More starts and noise
draws"), so whether a setting helps is a question about many runs, not about two table rows. Runs pair by
sequence, light, start and noise draw; the ratio is NEW / BASE of the paired runs' geometric means, and its
interval resamples starts (a start's draws share its frames; `vo_shared_frames.ratio_interval`). A run without an
ATE (no trajectory) cannot enter a ratio: the table counts those apart, with the frames lost after
initialisation, since a setting that trades a lower ATE for failed runs is no gain.

`--split-delay N` splits each row by when the base run built its first map: at most N frames after the new run's
(or before it), or later than that. Each run's ATE covers its own frames after initialisation, so a base that
starts later is scored on a shorter, later stretch of the flight (`vo_shared_frames.py`); the split shows how much
of a ratio that is (docs/vo_euroc.md, "Where the dark row's 0.84x comes from").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.vo_shared_frames import geometric_mean, ratio_interval  # noqa: E402

Key = tuple[str, str, int, int]  # sequence name, light, start, noise draw


def load_rows(path: Path) -> list[dict]:
    """The rows of an eval_vo results.json; ValueError with a one-line reason when it is not one."""
    try:
        data = json.loads(path.read_text())
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not JSON ({error.msg}, line {error.lineno})") from None
    rows = data.get("rows") if isinstance(data, dict) else None
    needed = ("name", "features", "light", "start", "ate")
    if not isinstance(rows, list) or not all(isinstance(r, dict) and all(k in r for k in needed) for r in rows):
        raise ValueError(f"{path} is not a bench/eval_vo.py results.json (no rows with {', '.join(needed)})")
    return rows


def _by_run(rows: list[dict], features: str) -> dict[Key, dict]:
    return {(r["name"], r["light"], int(r["start"]), int(r.get("seed", 0))): r
            for r in rows if r["features"] == features}


def pair_runs(base: list[dict], new: list[dict], base_features: str,
              new_features: str) -> dict[tuple[str, str], list[tuple[dict, dict]]]:
    """(sequence, light) -> [(base row, new row)] of runs with the same start and noise draw."""
    left, right = _by_run(base, base_features), _by_run(new, new_features)
    groups: dict[tuple[str, str], list[tuple[dict, dict]]] = {}
    for key in sorted(set(left) & set(right)):
        groups.setdefault(key[:2], []).append((left[key], right[key]))
    return groups


def split_by_delay(groups: dict[tuple[str, str], list[tuple[dict, dict]]],
                   frames: int) -> dict[tuple[str, str], list[tuple[dict, dict]]]:
    """Each (sequence, light) group split in two by ``initialised_at``: the base run's first map at most
    ``frames`` frames after the new run's (or before it), or later; ValueError when a row has no ``initialised_at``."""
    split: dict[tuple[str, str], list[tuple[dict, dict]]] = {}
    for (name, light), pairs in groups.items():
        for base, new in pairs:
            if not isinstance(base.get("initialised_at"), int) or not isinstance(new.get("initialised_at"), int):
                raise ValueError("--split-delay needs each run's initialised_at (a results.json from bench/eval_vo.py)")
            later = base["initialised_at"] - new["initialised_at"] > frames
            label = f"{light}, base {'more than' if later else 'at most'} {frames} frames later"
            split.setdefault((name, label), []).append((base, new))
    return dict(sorted(split.items()))


def _lost(row: dict) -> int:
    return int(row.get("after_init", 0)) - int(row.get("tracked", 0))


def comparison_table(groups: dict[tuple[str, str], list[tuple[dict, dict]]]) -> str:
    """Markdown: per (sequence, light) the runs paired, both geometric means over the runs both scored, the ratio
    new / base with its 95 % interval over starts, runs without an ATE and frames lost (base / new)."""
    lines = ["| sequence | light | runs paired | base ATE m (geo. mean) | new ATE m (geo. mean) | "
             "ratio new / base [95 % over starts] | runs without ATE (base / new) | frames lost (base / new) |",
             "|---|---|---|---|---|---|---|---|"]
    for (name, light), pairs in groups.items():
        scored = [(b["start"], n["ate"], b["ate"]) for b, n in pairs if b["ate"] is not None and n["ate"] is not None]
        failed = (sum(b["ate"] is None for b, _ in pairs), sum(n["ate"] is None for _, n in pairs))
        lost = (sum(_lost(b) for b, _ in pairs), sum(_lost(n) for _, n in pairs))
        if scored:
            ratio, low, high = ratio_interval(scored)
            cells = (f"{geometric_mean([s[2] for s in scored]):.4f} | {geometric_mean([s[1] for s in scored]):.4f} | "
                     f"{ratio:.2f}x [{low:.2f}, {high:.2f}]")
        else:
            cells = "- | - | -"
        lines.append(f"| {name} | {light} | {len(pairs)} | {cells} | {failed[0]} / {failed[1]} | "
                     f"{lost[0]} / {lost[1]} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("base", type=Path, help="results.json of the reference run")
    parser.add_argument("new", type=Path, help="results.json of the run compared with it")
    parser.add_argument("--base-features", help="features of the base run to compare (default: each name in both)")
    parser.add_argument("--new-features", help="features of the new run (default: the base's)")
    parser.add_argument("--split-delay", type=int, metavar="N",
                        help="split each row by whether the base run's first map came more than N frames after "
                             "the new run's")
    args = parser.parse_args()
    if args.split_delay is not None and args.split_delay < 0:
        print("error: --split-delay takes a number of frames >= 0", file=sys.stderr)
        return 2
    try:
        base, new = load_rows(args.base), load_rows(args.new)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.base_features or args.new_features:
        names = [(args.base_features or args.new_features, args.new_features or args.base_features)]
    else:
        names = [(f, f) for f in sorted({r["features"] for r in base} & {r["features"] for r in new})]
    sections = []
    for base_features, new_features in names:
        groups = pair_runs(base, new, base_features, new_features)
        if groups and args.split_delay is not None:
            try:
                groups = split_by_delay(groups, args.split_delay)
            except ValueError as error:
                print(f"error: {error}", file=sys.stderr)
                return 2
        if groups:
            sections.append(f"{new_features} against {base_features}:\n\n{comparison_table(groups)}")
    if not sections:
        found = sorted({r["features"] for r in base}), sorted({r["features"] for r in new})
        print(f"error: no runs pair up (same features, sequence, light, start and draw); features in base: "
              f"{', '.join(found[0]) or 'none'}; in new: {', '.join(found[1]) or 'none'}", file=sys.stderr)
        return 2
    print("\n\n".join(sections))
    return 0


if __name__ == "__main__":
    sys.exit(main())
