"""One table of the VO on every dev sequence: frames tracked and lost, ATE and RPE (evo, Sim(3)), FPS on one core.

    python bench/eval_vo.py --workers 2 -o runs/vo_eval    # KITTI 06, KITTI 07, TUM fr2 desk, EuRoC MH_05; the
                                                            # shipped artefact and ORB; normal, dark, onboard light
    python bench/eval_vo.py --features orb --light normal      # a subset
    python bench/eval_vo.py --set keyframe_max_gap=6 --keypoints 500,1000,2000 --starts 0   # sensitivity
    python bench/eval_vo.py --size 320x240                      # every frame resized first (the speed setting)
    python bench/eval_vo.py --starts 0,25,50 --light normal     # each sequence from these first frames
    python bench/eval_vo.py --stride 2                          # every second frame: a flight twice as fast

Single runs of 20-200 frame clips move by tens of centimetres with any setting (docs/vo.md), so by default
(``--starts study``) each sequence runs from several first frames (`STARTS`, the same lists as
bench/vo_settings.py) and the summary gives per sequence, features and light the geometric mean and the worst
ATE over the starts, the least tracked share and the frames lost after initialisation. A darkened run's sensor
noise is one draw; ``--seeds N`` runs N draws per start (by default six for TUM's one-start snippet,
`STUDY_SEEDS`), and the summary counts each draw as a run. Normal light has no noise to draw, so ``--light grain``
(normal light plus one grey level of sensor noise, at normal light's starts) with ``--seeds N`` shows how much of
a normal-light row is the chaos of single runs (docs/vo_euroc.md, "More starts and noise draws").

Every run: the sequence at its own resolution (the artefact resizes to its input; by default the shipped
artefact for that camera's aspect), onnxruntime, OpenCV and BLAS on one thread, one process per run
(``--workers`` side by side: run it on an otherwise idle machine, or the FPS mean little). Writes ``table.md``
(the tables docs/vo.md keeps), ``results.json``, one trajectory plot per run (start and end marked) and its scored
frames in TUM format (``trajectories/``, for evo) into ``-o``. When ORB ran the same starts, a second table
scores each learned run and ORB's again on the frames both scored (bench/vo_shared_frames.py): ORB starts later
in the dark, so its own ATE covers less of the flight. "Tracked" counts frames with a pose from tracking,
relocalisation or re-initialisation, over the frames after the first initialisation; "lost" the rest of those.
FPS counts extraction and tracking, not reading or darkening the frames.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vo_runtime import FeatureExtractor, OrbExtractor, VisualOdometry, VOConfig  # noqa: E402
from vo_runtime.artefact import default_artefact  # noqa: E402
from vo_runtime.config_overrides import config_from_overrides  # noqa: E402
from vo_runtime.datasets import frame_size, open_sequence  # noqa: E402
from vo_runtime.errors import VORuntimeError  # noqa: E402
from vo_runtime.evaluate import evaluate, plot_trajectory, scored_results, sequence_groundtruth  # noqa: E402
from vo_runtime.features import KeypointBudget, to_gray_u8  # noqa: E402
from vo_runtime.lowlight import PRESETS  # noqa: E402
from vo_runtime.odometry import INITIALISING, REINITIALISED, SKIPPED, TRACKED_STATES  # noqa: E402
from vo_runtime.sequence import read_frames  # noqa: E402
from vo_runtime.trajectory import write_trajectory  # noqa: E402
from bench.vo_peers import PEER_KEYPOINTS, PeerExtractor, is_peer  # noqa: E402
from bench.vo_shared_frames import geometric_mean, shared_frames_summary  # noqa: E402

SEQUENCES = ("kitti_odom06_f000000-000050", "kitti_odom07_f000000-000159", "tum_fr2_desk_snippet",
             "euroc_mh05_f000000-000199")
SHORT_NAMES = {"kitti_odom06_f000000-000050": "KITTI 06", "kitti_odom07_f000000-000159": "KITTI 07",
               "tum_fr2_desk_snippet": "TUM fr2 desk", "euroc_mh05_f000000-000199": "EuRoC MH_05"}
# First frames per sequence: single runs of these 20-200-frame clips move by tens of centimetres with any change
# (docs/vo.md), so every figure is a geometric mean over several starts. Normal light, and each dark preset.
STARTS = {
    "normal": {"kitti_odom07_f000000-000159": range(0, 131, 10), "kitti_odom06_f000000-000050": range(0, 31, 5),
               "tum_fr2_desk_snippet": [0], "euroc_mh05_f000000-000199": range(0, 101, 20)},
    "low": {"kitti_odom07_f000000-000159": range(0, 101, 25), "kitti_odom06_f000000-000050": range(0, 21, 10),
            "tum_fr2_desk_snippet": [0], "euroc_mh05_f000000-000199": range(0, 101, 20)},
}
# "grain": normal light plus one grey level of sensor noise. Normal light is deterministic, so each start is one
# run, and a KITTI 07 run is chaotic enough that this much noise moved a start from 0.165 to 0.32-0.35 m: draws
# of it (--seeds) tell the weights' or settings' effect on a normal-light row from the chaos of single runs.
GRAIN_SIGMA = 1.0


def sensor_grain(gray: np.ndarray, seed: int = 0) -> np.ndarray:
    """HxW uint8 -> the same frame plus Gaussian noise of GRAIN_SIGMA grey levels (seeded), rounded and clipped."""
    noise = np.random.default_rng(seed).normal(0.0, GRAIN_SIGMA, gray.shape)
    return np.clip(np.rint(gray + noise), 0, 255).astype(np.uint8)


# normal light; "low": the global --lowlight dark preset (2,3,0.3); "onboard": a light riding on the camera
LIGHTS = {"normal": None, "low": PRESETS["dark"], "onboard": PRESETS["onboard"], "grain": sensor_grain}
# Sensor-noise draws per start of a darkened run. TUM's 23-frame snippet allows one start, and one draw of the
# noise moved its dark ATE from 0.005 to 0.032 m (12 draws, default artefact): there the study runs six.
STUDY_SEEDS = {"tum_fr2_desk_snippet": 6}
NOISE_SEED_STRIDE = 100_000  # draw k darkens frame i with seed start + i + k * stride (k = 0: the single-draw noise)


def lit_frame(image: np.ndarray, light: str, start: int, index: int, draw: int = 0) -> np.ndarray:
    """Frame ``index`` of a run from ``start`` as that run sees it under ``light`` (LIGHTS) in noise draw ``draw``:
    the same noise for a frame at any start, another for each draw; unchanged in normal light."""
    if LIGHTS[light] is None:
        return image
    return LIGHTS[light](to_gray_u8(image), seed=start + index + NOISE_SEED_STRIDE * draw)


def run_one(sequence_dir: Path, features: str, light: str, keypoints: int, config: VOConfig, artefact: Path,
            plot_dir: Path | None, size: tuple[int, int] | None = None, start: int = 0,
            budget: tuple[int, tuple[int, int] | None] | None = None, seed: int = 0, stride: int = 1) -> dict:
    sequence = open_sequence(sequence_dir)
    frames, stamps = sequence.frames[start::stride], sequence.timestamps[start::stride]
    camera = sequence.camera
    if size is not None:  # frames resized to width x height, intrinsics scaled to match
        height, width = next(read_frames(sequence.frames[:1])).shape[:2]
        camera = camera.resized((width, height), size)
    if is_peer(features):  # XFeat or the teacher, in PyTorch (bench/vo_peers.py)
        extractor = PeerExtractor(features)
    else:
        extractor = OrbExtractor(keypoints) if features == "orb" else FeatureExtractor(artefact, threads=1)
    if budget is not None:  # at most N keypoints a frame, spread over a grid (KeypointBudget)
        extractor = KeypointBudget(extractor, *budget)
    vo = VisualOdometry(extractor, camera, config)
    for index, image in enumerate(read_frames(frames)):
        if size is not None:
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        # a frame keeps its own noise draw whatever the stride: the same frames, only fewer of them
        vo.track(lit_frame(image, light, start, index * stride, seed), stamps[index])
    vo.finish()  # a keyframe's mapping still on the worker thread (--set mapping_thread=true)
    results = vo.results
    states = [r.status for r in results]
    first = next((i for i, s in enumerate(states) if s not in (INITIALISING, SKIPPED)), len(states))
    after = states[first:]
    row = {"sequence": sequence_dir.name + (f" from {start}" if start else "") + (f" noise {seed}" if seed else "")
           + (f" every {stride}" if stride > 1 else ""),
           "name": sequence_dir.name, "start": start, "seed": seed, "stride": stride,
           "features": features if features == "orb" or is_peer(features) else artefact.name,
           "keypoints": keypoints if features == "orb" else PEER_KEYPOINTS if is_peer(features) else None,
           "light": light, "frames": len(states),
           "initialised_at": first, "tracked": sum(s in TRACKED_STATES for s in after), "after_init": len(after),
           "states": {s: states.count(s) for s in dict.fromkeys(states)},
           "keyframes": sum(r.keyframe for r in results),
           "merges": [(r.index, round(r.merged_scale, 3)) for r in results if r.merged_scale is not None],
           "abandoned_at": [r.index for r in results if r.problem and r.problem.startswith("map abandoned")],
           "reinitialised_at": [r.index for r in results if r.status == REINITIALISED],
           "first_map_landmarks": results[first].num_landmarks if first < len(results) else None,
           "fps": 1000.0 * len(results) / max(sum(r.extract_ms + r.track_ms for r in results), 1e-9),
           "extract_ms": float(np.median([r.extract_ms for r in results])),
           "track_ms": float(np.median([r.track_ms for r in results])), "ate": None, "rpe": None,
           "_results": results}  # for the shared-frames table; not written to results.json
    row["tracked_pct"] = 100.0 * row["tracked"] / max(row["after_init"], 1)
    try:
        report = evaluate(results, sequence_groundtruth(sequence), sequence.layout, stamps)
        row["ate"], row["rpe"] = report["ate_rmse_m"], report["rpe_rmse_m"]
        if plot_dir is not None:
            name = f"{sequence_dir.name}{f'_from{start}' if start else ''}_{row['features']}_{light}" + \
                (f"_noise{seed}" if seed else "") + (f"_every{stride}" if stride > 1 else "")
            # the scored frames in TUM format, so that anyone can score them again with evo_ape
            (plot_dir / "trajectories").mkdir(exist_ok=True)
            write_trajectory(plot_dir / "trajectories" / f"{name}.txt", scored_results(results))
            plot_trajectory(plot_dir / f"{name}.png", report,
                            f"{SHORT_NAMES.get(sequence_dir.name, sequence_dir.name)} from frame {start} "
                            f"({row['features']}, {light} light)")
    except VORuntimeError as exc:
        row["error"] = str(exc)
    return row


def table(rows: list[dict]) -> str:
    lines = ["| sequence | features | light | initialised at | tracked after init | states | ATE m | RPE m | FPS | "
             "track ms (median) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        states = ", ".join(f"{v} {k}" for k, v in r["states"].items())
        ate = "-" if r["ate"] is None else f"{r['ate']:.3f}"
        rpe = "-" if r["rpe"] is None else f"{r['rpe']:.3f}"
        feats = r["features"] + (f" {r['keypoints']}" if r["keypoints"] else "")
        lines.append(f"| {r['sequence']} | {feats} | {r['light']} | {r['initialised_at']} | {r['tracked_pct']:.0f} % ({r['tracked']}/"
                     f"{r['after_init']}) | {states} | {ate} | {rpe} | {r['fps']:.0f} | {r['track_ms']:.1f} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Per sequence, features and light over the starts: ATE geometric mean and worst, RPE geometric mean,
    the least tracked share, frames lost after initialisation, FPS (median)."""
    lines = ["| sequence | features | light | runs | ATE m (geo. mean) | worst ATE m | RPE m (geo. mean) | "
             "least tracked after init | lost frames | initialised at (median, worst) | FPS (1 core) | ATE m per run |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["name"], r["features"], r["keypoints"], r["light"]), []).append(r)
    for (name, feats, keypoints, light), group in groups.items():
        ates = [r["ate"] for r in group]
        failed = None in ates  # never initialised: no ATE; the row says so instead of a mean of the others
        mean = "-" if failed else f"{geometric_mean(ates):.3f}"
        worst = "-" if failed else f"{max(ates):.3f}"
        rpe = "-" if None in [r["rpe"] for r in group] else f"{geometric_mean([r['rpe'] for r in group]):.3f}"
        each = ", ".join("-" if a is None else f"{a:.3f}" for a in ates)
        label = feats + (f" {keypoints}" if keypoints else "")
        least = min(r["tracked_pct"] for r in group)
        lost = sum(r["after_init"] - r["tracked"] for r in group)
        fps = float(np.median([r["fps"] for r in group]))
        inits = [r["initialised_at"] for r in group]
        lines.append(f"| {SHORT_NAMES.get(name, name)} | {label} | {light} | {len(group)} | {mean} | {worst} | {rpe} | "
                     f"{least:.0f} % | {lost} | {int(np.median(inits))}, {max(inits)} | {fps:.0f} | {each} |")
    return "\n".join(lines)


def study_starts(name: str, light: str, length: int) -> list[int]:
    """The first frames of the settings study (`STARTS`), or 0 for a sequence it does not list."""
    starts = STARTS["normal" if light in ("normal", "grain") else "low"].get(name, [0])
    return [v for v in starts if v == 0 or v < length - 20]


def _reference(data: Path, stride: int = 1):
    """(ground truth, layout, timestamps of the frames run from ``start``) of a sequence by name, each sequence
    read once."""
    opened: dict[str, tuple] = {}

    def reference(name: str, start: int) -> tuple:
        if name not in opened:
            sequence = open_sequence(data / name)
            opened[name] = (sequence_groundtruth(sequence), sequence.layout, list(sequence.timestamps))
        groundtruth, layout, stamps = opened[name]
        return groundtruth, layout, stamps[start::stride]
    return reference


def _run_job(job: tuple) -> dict:
    """One run in a worker process (one thread, as the main process)."""
    cv2.setNumThreads(1)
    began = time.perf_counter()
    row = run_one(*job)
    row["wall_s"] = round(time.perf_counter() - began, 1)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared/data")
    parser.add_argument("--sequences", default=",".join(SEQUENCES))
    parser.add_argument("--features", default="artefact,orb",
                        help="artefact, orb and/or the learned peers xfeat, teacher:alike-n (PyTorch; bench/vo_peers.py)")
    parser.add_argument("--artefact", type=Path, default=None,
                        help="default: the shipped artefact for each sequence's camera (default_artefact)")
    parser.add_argument("--light", default="normal,low,onboard",
                        help="normal, low (--lowlight dark: 2,3,0.3), onboard (--lowlight onboard) and/or grain "
                             "(normal light plus one grey level of sensor noise, at normal light's starts)")
    parser.add_argument("--keypoints", default="2000", help="ORB features per frame; a list for a sensitivity table")
    parser.add_argument("--set", action="append", default=[], help="VOConfig field=value (JSON value; mapping.FIELD for MappingConfig), repeatable")
    parser.add_argument("--size", help="WIDTHxHEIGHT: resize every frame first (e.g. 320x240); default: as stored")
    parser.add_argument("--starts", default="study",
                        help="first frames to run each sequence from, e.g. 0,25,50; study (default): the start lists of "
                             "bench/vo_settings.py, per sequence and light")
    parser.add_argument("--seeds", default="study",
                        help="noise draws per start of each dark or grain run (N); study (default): STUDY_SEEDS, else 1")
    parser.add_argument("--workers", type=int, default=1, help="runs in parallel, one process and thread each")
    parser.add_argument("--budget", help="N or N,COLUMNSxROWS: keep at most N keypoints a frame (any extractor), "
                        "spread over a grid of cells when given (round-robin by rank in the cell)")
    parser.add_argument("--stride", type=int, default=1,
                        help="run every N-th frame (from each start): the same flight N times as fast")
    parser.add_argument("--summary-only", action="store_true", help="print the summary, not every run's row")
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    try:  # a mistyped --set refused before any run starts (the vo command's own check)
        config, overrides = config_from_overrides(args.set)
    except VORuntimeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    unknown = [light for light in args.light.split(",") if light not in LIGHTS]
    if unknown:
        print(f"error: --light {unknown[0]!r} is none of {', '.join(LIGHTS)}", file=sys.stderr)
        return 2
    odd = [f for f in args.features.split(",") if f not in ("artefact", "orb") and not is_peer(f)]
    if odd:
        print(f"error: --features {odd[0]!r} is none of artefact, orb, xfeat, teacher:NAME", file=sys.stderr)
        return 2
    if args.stride < 1:
        print(f"error: --stride takes a positive number of frames, got {args.stride}", file=sys.stderr)
        return 2
    if args.seeds != "study" and (not args.seeds.isdigit() or int(args.seeds) < 1):
        print(f"error: --seeds takes a positive number of noise draws or study, got {args.seeds!r}", file=sys.stderr)
        return 2
    budget = None
    if args.budget:
        count, _, grid = args.budget.partition(",")
        budget = (int(count), tuple(int(v) for v in grid.lower().split("x")) if grid else None)
    size = tuple(int(v) for v in args.size.lower().split("x")) if args.size else None
    jobs = []
    for name in args.sequences.split(","):
        try:
            sequence = open_sequence(args.data / name)
        except VORuntimeError as error:  # an unknown or malformed sequence: say so before any run starts
            print(f"error: {error}", file=sys.stderr)
            return 2
        height, width = frame_size(sequence.camera, sequence.frames)
        artefact = args.artefact or default_artefact(*(size or (width, height)))
        frames_left = len(sequence) - 20 * (args.stride - 1)  # a start keeps >= 20 frames at any stride
        for features in args.features.split(","):
            for light in args.light.split(","):
                starts = (study_starts(name, light, frames_left) if args.starts == "study" else
                          [v for v in map(int, args.starts.split(",")) if v == 0 or v < frames_left - 20])
                draws = (1 if light == "normal" else STUDY_SEEDS.get(name, 1) if args.seeds == "study"
                         else int(args.seeds))
                for keypoints in [int(k) for k in args.keypoints.split(",")]:
                    jobs += [(args.data / name, features, light, keypoints, config, artefact, args.output, size, first,
                              budget, seed, args.stride) for first in starts for seed in range(draws)]
    if args.output is not None:
        args.output.mkdir(parents=True, exist_ok=True)
    if args.workers > 1:
        with ProcessPoolExecutor(args.workers) as pool:
            rows = list(pool.map(_run_job, jobs))
    else:
        rows = []
        for job in jobs:
            rows.append(_run_job(job))
            print(table([rows[-1]]).splitlines()[-1], flush=True)
    began_all = sum(r["wall_s"] for r in rows)
    text = table(rows)
    if len(rows) > len({(r["name"], r["features"], r["light"], r["keypoints"]) for r in rows}):
        text = summary(rows) + ("" if args.summary_only else "\n\n" + text)
    shared = shared_frames_summary(rows, _reference(args.data, args.stride), short_names=SHORT_NAMES)
    if shared:
        text += ("\n\nEach learned run against ORB's run of the same start, both scored on the frames both scored:"
                 "\n\n" + shared)
    for row in rows:
        del row["_results"]
    print(f"{len(rows)} runs ({began_all:.0f} s of runs), settings {overrides or 'default'}")
    print(text)
    if args.output is not None:
        (args.output / "table.md").write_text(text + "\n")
        (args.output / "results.json").write_text(json.dumps({"overrides": overrides, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
