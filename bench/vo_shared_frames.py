"""Two VO runs scored on the frames both scored: a like-for-like ATE beside each run's own (bench/eval_vo.py).

A run's ATE covers the frames after its own initialisation. In the dark ORB starts tens of frames later than the
learned feature (EuRoC MH_05, dark preset, 18 starts: a median of 25 frames after the first against 9), and a
later start scores a shorter stretch of the flight, which a Sim(3) alignment fits with less drift to show: from
frame 90 ORB's 0.004 m is over 36 frames and 2.0 m of flight, the learned run's 0.018 m over 102 frames and
5.0 m. Scoring both again on the frames both scored (each aligned by Sim(3) on those frames alone) separates how
much of the flight a VO follows from how precisely it follows it; the table reports both, the targets stay on
each run's own ATE.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from toolkit.evaluation.intervals import BootstrapSettings, pooled_mean_interval, resample_weights
from vo_runtime.errors import VORuntimeError
from vo_runtime.evaluate import evaluate, scored_results
from vo_runtime.odometry import VOResult

MIN_SHARED_FRAMES = 10  # fewer and a Sim(3) alignment fits nearly anything: the pair is not compared


def scored_frames(results: list[VOResult]) -> set[int]:
    """The indexes of `scored_results`."""
    return {r.index for r in scored_results(results)}


def shared_frame_ates(results_a: list[VOResult], results_b: list[VOResult], groundtruth: Any, layout: str,
                      timestamps: list[float], min_frames: int = MIN_SHARED_FRAMES) -> tuple[float, float, int] | None:
    """(ATE of a, ATE of b, frames) on the frames both runs scored, each aligned by Sim(3) on those frames;
    None when they share fewer than ``min_frames`` or either cannot be aligned there (no motion tracked)."""
    shared = scored_frames(results_a) & scored_frames(results_b)
    if len(shared) < min_frames:
        return None
    try:
        ates = [evaluate([r for r in results if r.index in shared], groundtruth, layout, timestamps)["ate_rmse_m"]
                for results in (results_a, results_b)]
    except VORuntimeError:
        return None
    return ates[0], ates[1], len(shared)


def geometric_mean(values: list[float]) -> float:
    """Of ATEs and RPEs over starts (a floor of 1 micrometre keeps an exact run from zeroing it)."""
    return float(np.exp(np.mean(np.log(np.maximum(values, 1e-6)))))


def ratio_interval(pairs: list[tuple[int, float, float]], level: float = 0.95) -> tuple[float, float, float]:
    """Ratio of the geometric means of paired ATEs (start, this, peer), with a bootstrap interval that resamples
    starts: the noise draws of one start share its frames, so they are not independent runs. With a single start
    (TUM's snippet) the draws are resampled instead: the only spread there is to see."""
    starts = sorted({start for start, _, _ in pairs})
    logs = [[np.log(max(a, 1e-6) / max(b, 1e-6)) for s, a, b in pairs if s == start] for start in starts]
    if len(starts) == 1:
        logs = [[value] for value in logs[0]]
    low, high = pooled_mean_interval(logs, resample_weights(len(logs), BootstrapSettings(level=level)), level)
    return float(np.exp(np.mean(np.concatenate(logs)))), float(np.exp(low)), float(np.exp(high))


def shared_frames_summary(rows: list[dict], reference: Callable[[str, int], tuple[Any, str, list[float]]],
                          peer: str = "orb", short_names: dict[str, str] | None = None) -> str:
    """Markdown table: for every sequence, light and feature, its runs against ``peer``'s runs of the same start
    and noise draw, scored on their shared frames (`shared_frame_ates`). ``rows`` are eval_vo rows holding their
    ``_results``; ``reference(name, start)`` gives (ground truth, layout, timestamps from that start). "" when
    no run has a peer."""
    peers = {(r["name"], r["light"], r["start"], r.get("seed", 0)): r for r in rows
             if r["features"] == peer and r.get("_results")}
    groups: dict[tuple, list[tuple]] = {}
    for row in rows:
        other = peers.get((row["name"], row["light"], row["start"], row.get("seed", 0)))
        if row["features"] == peer or other is None or not row.get("_results"):
            continue
        try:
            groundtruth, layout, stamps = reference(row["name"], row["start"])
        except VORuntimeError:  # a sequence without ground truth: nothing to score
            continue
        scored = shared_frame_ates(row["_results"], other["_results"], groundtruth, layout, stamps)
        groups.setdefault((row["name"], row["features"], row["light"]), []).append((row, other, scored))
    if not groups:
        return ""
    lines = [f"| sequence | features | light | runs compared | shared frames (median) | ATE m on shared frames "
             f"(geo. mean) | {peer}'s on the same frames | ratio [95 % interval over starts] | own-frames ratio [95 %] "
             f"| frames scored (this / {peer}) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (name, feats, light), pairs in groups.items():
        compared = [(row, other, s) for row, other, s in pairs if s is not None]
        own_pairs = [(row["start"], row["ate"], other["ate"]) for row, other, _ in compared
                     if row["ate"] is not None and other["ate"] is not None]
        scored_this = sum(len(scored_frames(row["_results"])) for row, _, _ in pairs)
        scored_peer = sum(len(scored_frames(other["_results"])) for _, other, _ in pairs)
        if compared:
            this, that = geometric_mean([s[0] for *_, s in compared]), geometric_mean([s[1] for *_, s in compared])
            shared = _ratio_cell([(row["start"], s[0], s[1]) for row, _, s in compared])
            own = _ratio_cell(own_pairs)  # the same runs' ATEs, each on its own frames
            cells = f"{int(np.median([s[2] for *_, s in compared]))} | {this:.4f} | {that:.4f} | {shared} | {own}"
        else:
            cells = "- | - | - | - | -"
        label = (short_names or {}).get(name, name)
        lines.append(f"| {label} | {feats} | {light} | {len(compared)} of {len(pairs)} | {cells} | "
                     f"{scored_this} / {scored_peer} |")
    return "\n".join(lines)


def _ratio_cell(pairs: list[tuple[int, float, float]]) -> str:
    if not pairs:
        return "-"
    ratio, low, high = ratio_interval(pairs)
    return f"{ratio:.2f}x [{low:.2f}, {high:.2f}]"
