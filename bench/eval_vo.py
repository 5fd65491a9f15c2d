"""One evaluation of the VO on every dev sequence: frames tracked, ATE and RPE (evo, Sim(3)), FPS.

    python bench/eval_vo.py -o runs/vo_eval                    # default artefact and ORB, normal and low light
    python bench/eval_vo.py --features orb --light normal      # a subset
    python bench/eval_vo.py --set keyframe_max_gap=6 --keypoints 500,1000,2000   # sensitivity
    python bench/eval_vo.py --size 320x240                      # every frame resized first (the speed setting)
    python bench/eval_vo.py --starts 0,25,50,75,100 --light normal   # each sequence from several first frames

Single runs of 50-160 frame sequences move by tens of centimetres with any setting (docs/vo.md), so
``--starts`` runs each sequence again from later first frames (starts within 20 frames of the end are
left out) and adds a summary: the geometric mean of the ATE over the starts and the least tracked share.

Runs each (sequence, features, light) in this process, one after the other, at the sequences' own
resolution (the artefact resizes to its input), with onnxruntime and OpenCV on one thread. Writes
``table.md`` (the table docs/vo.md keeps), ``results.json`` and one trajectory plot per run into ``-o``.
"Tracked" counts frames with a pose from tracking, relocalisation or re-initialisation, over the frames
after the first initialisation. FPS counts extraction and tracking, not reading or darkening the frames.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vo_runtime import FeatureExtractor, OrbExtractor, VisualOdometry, VOConfig  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.datasets import open_sequence  # noqa: E402
from vo_runtime.errors import VORuntimeError  # noqa: E402
from vo_runtime.evaluate import evaluate, plot_trajectory, sequence_groundtruth  # noqa: E402
from vo_runtime.features import to_gray_u8  # noqa: E402
from vo_runtime.lowlight import PRESETS  # noqa: E402
from vo_runtime.mapping import MappingConfig  # noqa: E402
from vo_runtime.odometry import INITIALISING, SKIPPED, TRACKED_STATES  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402

SEQUENCES = ("kitti_odom06_f000000-000050", "kitti_odom07_f000000-000159", "tum_fr2_desk_snippet")
# normal light; "low": the global --lowlight dark preset (2,3,0.3); "onboard": a light riding on the camera
LIGHTS = {"normal": None, "low": PRESETS["dark"], "onboard": PRESETS["onboard"]}


def parse_overrides(items: list[str]) -> dict:
    overrides = {}
    for item in items:
        key, _, value = item.partition("=")
        overrides[key] = json.loads(value)
    return overrides


def run_one(sequence_dir: Path, features: str, light: str, keypoints: int, overrides: dict, artefact: Path,
            plot_dir: Path | None, size: tuple[int, int] | None = None, start: int = 0) -> dict:
    sequence = open_sequence(sequence_dir)
    frames, stamps = sequence.frames[start:], sequence.timestamps[start:]
    camera = sequence.camera
    if size is not None:  # frames resized to width x height, intrinsics scaled to match
        height, width = next(read_frames(sequence.frames[:1])).shape[:2]
        camera = camera.resized((width, height), size)
    extractor = OrbExtractor(keypoints) if features == "orb" else FeatureExtractor(artefact, threads=1)
    top = {k: v for k, v in overrides.items() if "." not in k}
    mapping = {k.split(".", 1)[1]: v for k, v in overrides.items() if k.startswith("mapping.")}
    config = VOConfig(**top, mapping=MappingConfig(**mapping))
    vo = VisualOdometry(extractor, camera, config)
    for index, image in enumerate(read_frames(frames)):
        if size is not None:
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        if LIGHTS[light] is not None:
            image = LIGHTS[light](to_gray_u8(image), seed=start + index)  # the same noise at any start
        vo.track(image, stamps[index])
    vo.finish()  # a keyframe's mapping still on the worker thread (--set mapping_thread=true)
    results = vo.results
    states = [r.status for r in results]
    first = next((i for i, s in enumerate(states) if s not in (INITIALISING, SKIPPED)), len(states))
    after = states[first:]
    row = {"sequence": sequence_dir.name + (f" from {start}" if start else ""), "name": sequence_dir.name,
           "start": start, "features": features if features == "orb" else artefact.name,
           "keypoints": keypoints if features == "orb" else None, "light": light, "frames": len(states),
           "initialised_at": first, "tracked": sum(s in TRACKED_STATES for s in after), "after_init": len(after),
           "states": {s: states.count(s) for s in dict.fromkeys(states)},
           "keyframes": sum(r.keyframe for r in results),
           "fps": 1000.0 * len(results) / max(sum(r.extract_ms + r.track_ms for r in results), 1e-9),
           "extract_ms": float(np.median([r.extract_ms for r in results])),
           "track_ms": float(np.median([r.track_ms for r in results])), "ate": None, "rpe": None}
    row["tracked_pct"] = 100.0 * row["tracked"] / max(row["after_init"], 1)
    try:
        report = evaluate(results, sequence_groundtruth(sequence), sequence.layout, stamps)
        row["ate"], row["rpe"] = report["ate_rmse_m"], report["rpe_rmse_m"]
        if plot_dir is not None:
            name = f"{sequence_dir.name}{f'_from{start}' if start else ''}_{row['features']}_{light}.png"
            plot_trajectory(plot_dir / name, report, f"{sequence_dir.name} ({row['features']}, {light} light)")
    except VORuntimeError as exc:
        row["error"] = str(exc)
    return row


def table(rows: list[dict]) -> str:
    lines = ["| sequence | features | light | tracked after init | states | ATE m | RPE m | FPS | track ms (median) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        states = ", ".join(f"{v} {k}" for k, v in r["states"].items())
        ate = "-" if r["ate"] is None else f"{r['ate']:.3f}"
        rpe = "-" if r["rpe"] is None else f"{r['rpe']:.3f}"
        feats = r["features"] + (f" {r['keypoints']}" if r["keypoints"] else "")
        lines.append(f"| {r['sequence']} | {feats} | {r['light']} | {r['tracked_pct']:.0f} % ({r['tracked']}/"
                     f"{r['after_init']}) | {states} | {ate} | {rpe} | {r['fps']:.0f} | {r['track_ms']:.1f} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Per sequence, features and light: ATE geometric mean over the starts, and the least tracked share."""
    lines = ["| sequence | features | light | runs | ATE m (geometric mean) | ATE m per start | least tracked |",
             "|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["name"], r["features"], r["keypoints"], r["light"]), []).append(r)
    for (name, feats, keypoints, light), group in groups.items():
        ates = [r["ate"] for r in group]
        mean = "-" if None in ates else f"{float(np.exp(np.mean(np.log(np.maximum(ates, 1e-6))))):.3f}"
        each = ", ".join("-" if a is None else f"{a:.2f}" for a in ates)
        label = feats + (f" {keypoints}" if keypoints else "")
        least = min(r["tracked_pct"] for r in group)
        lines.append(f"| {name} | {label} | {light} | {len(group)} | {mean} | {each} | {least:.0f} % |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared/data")
    parser.add_argument("--sequences", default=",".join(SEQUENCES))
    parser.add_argument("--features", default="artefact,orb", help="artefact and/or orb")
    parser.add_argument("--artefact", type=Path, default=None, help="default: the shipped artefact")
    parser.add_argument("--light", default="normal,low", help="normal and/or low (--lowlight 2,3,0.3)")
    parser.add_argument("--keypoints", default="2000", help="ORB features per frame; a list for a sensitivity table")
    parser.add_argument("--set", action="append", default=[], help="VOConfig field=value (JSON value; mapping.FIELD for MappingConfig), repeatable")
    parser.add_argument("--size", help="WIDTHxHEIGHT: resize every frame first (e.g. 320x240); default: as stored")
    parser.add_argument("--starts", default="0", help="first frames to run each sequence from, e.g. 0,25,50")
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    artefact = args.artefact or default_artefact()
    overrides = parse_overrides(args.set)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    if args.output is not None:
        args.output.mkdir(parents=True, exist_ok=True)
    starts = [int(v) for v in args.starts.split(",")]
    rows = []
    for name in args.sequences.split(","):
        length = len(open_sequence(args.data / name).frames)
        for features in args.features.split(","):
            for light in args.light.split(","):
                for keypoints in [int(k) for k in args.keypoints.split(",")]:
                    for first in [v for v in starts if v == 0 or v < length - 20]:
                        began = time.perf_counter()
                        row = run_one(args.data / name, features, light, keypoints, overrides, artefact,
                                      args.output, size, first)
                        row["wall_s"] = round(time.perf_counter() - began, 1)
                        rows.append(row)
                        print(table([row]).splitlines()[-1], flush=True)
    text = table(rows)
    if len(starts) > 1:
        text += "\n\n" + summary(rows)
    print(text)
    if args.output is not None:
        (args.output / "table.md").write_text(text + "\n")
        (args.output / "results.json").write_text(json.dumps({"overrides": overrides, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
