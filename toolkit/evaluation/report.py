"""Report outputs of `toolkit eval`: terminal table, JSON, markdown and a PNG of matches per model.

A report directory holds ``results.json``, ``results.md`` and ``matches_<model>.png``. It is written into a
temporary directory beside the target and renamed into place, so a crash never leaves half a report.
"""
from __future__ import annotations

import json
import re
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from toolkit.atomic import OutputClaim, OutputKind, claim_output_dir
from toolkit.evaluation.metrics import warp_points
from toolkit.evaluation.runner import PairExample, stretch_contrast

REPORT_JSON = "results.json"
REPORT_MARKDOWN = "results.md"

# (key in a summary, column header, number format)
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("num_pairs", "pairs", "{:d}"),
    ("num_keypoints", "kpts", "{:.0f}"),
    ("repeatability", "rep", "{:.3f}"),
    ("localisation_error", "MLE px", "{:.3f}"),
    ("nn_map", "NN mAP", "{:.3f}"),
    ("matching_score", "M.score", "{:.3f}"),
    ("homography_1px", "H e=1", "{:.3f}"),
    ("homography_3px", "H e=3", "{:.3f}"),
    ("homography_5px", "H e=5", "{:.3f}"),
)


def table_rows(report: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """Header and string rows (one per model and group) of a report dict."""
    header = ["model", "set"] + [title for _, title, _ in COLUMNS]
    rows = []
    for model in report["models"]:
        for group, summary in model["summary"].items():
            cells = [model["label"], group]
            intervals = summary.get("intervals", {})
            for key, _, fmt in COLUMNS:
                cells.append(_cell(summary.get(key), intervals.get(key), fmt))
            rows.append(cells)
    return header, rows


def _cell(value: Any, interval: list[float] | None, fmt: str) -> str:
    """``0.440`` or, with a bootstrap interval, ``0.440 [0.410, 0.470]``; ``-`` for an undefined value."""
    if value is None:
        return "-"
    if interval is None:
        return fmt.format(value)
    return f"{fmt.format(value)} [{fmt.format(interval[0])}, {fmt.format(interval[1])}]"


def format_terminal_table(report: dict[str, Any]) -> str:
    """A fixed-width table for the terminal."""
    header, rows = table_rows(report)
    widths = [max(len(line[i]) for line in [header] + rows) for i in range(len(header))]
    lines = ["  ".join(cell.ljust(w) if i < 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(line, widths)))
             for line in [header] + rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_markdown(report: dict[str, Any]) -> str:
    """A markdown section: the conditions, then one table row per model and group."""
    protocol = report["protocol"]
    size = "native" if protocol["size"] is None else "x".join(str(v) for v in protocol["size"])
    header, rows = table_rows(report)
    data = report["data"] if isinstance(report["data"], list) else [report["data"]]
    lines = [
        f"### `toolkit eval {report['command']}` on {', '.join(f'`{Path(d).name}`' for d in data)}",
        "",
        f"Size {size}, at most {protocol['max_keypoints']} keypoints, NMS radius {protocol['nms_radius']} "
        f"(networks run in Python), correctness threshold {protocol['correct_threshold']:g} px, RANSAC "
        f"threshold {protocol['ransac_threshold']:g} px, contrast normalisation {protocol['normalise']}. "
        "Definitions: docs/evaluation.md.",
        "",
        *[line for note in report.get("notes", []) for line in (note, "")],
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def safe_file_stem(label: str) -> str:
    """A label turned into a file-name part: letters, digits, ``.-_`` only."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label).strip("_") or "model"


DARK_MEAN = 60  # a pair image darker than this (mean grey level) is shown contrast-stretched


def _shown(image: np.ndarray) -> np.ndarray:
    """A dark image min-max stretched for the eye (detections ran on the image as it was)."""
    return stretch_contrast(image) if image.mean() < DARK_MEAN else image


def plot_matches(examples: list[PairExample], path: Path, label: str, threshold: float = 3.0) -> None:
    """PNG of a grid of pairs, one pair a row side by side, with their mutual-NN matches: green within
    ``threshold`` px of the truth, red not; dark images are shown stretched (the title says so)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width = max(e.image_a.shape[1] + e.image_b.shape[1] for e in examples)
    heights = [max(e.image_a.shape[0], e.image_b.shape[0]) for e in examples]
    scale = min(1.0, 1400 / width)  # keep the figure a screen wide
    figure = Figure(figsize=(width * scale / 100, (sum(heights) + 22 * len(examples)) * scale / 100), dpi=100)
    FigureCanvasAgg(figure)
    top = 1.0
    for example, height in zip(examples, heights):
        share = (height + 22) / (sum(heights) + 22 * len(examples))
        axes = figure.add_axes((0, top - share, 1, share * height / (height + 22)))
        top -= share
        _draw_pair(axes, example, threshold, label)
    figure.savefig(path, dpi=100)


def _draw_pair(axes: Any, example: PairExample, threshold: float, label: str) -> None:
    image_a, image_b = _shown(example.image_a), _shown(example.image_b)
    stretched = image_a is not example.image_a or image_b is not example.image_b
    height = max(image_a.shape[0], image_b.shape[0])
    canvas = np.zeros((height, image_a.shape[1] + image_b.shape[1]), dtype=np.uint8)
    canvas[: image_a.shape[0], : image_a.shape[1]] = image_a
    canvas[: image_b.shape[0], image_a.shape[1]:] = image_b
    offset = image_a.shape[1]
    points_a = example.detection_a.keypoints.astype(np.float64)
    points_b = example.detection_b.keypoints.astype(np.float64)
    matched_a, matched_b = points_a[example.matches[:, 0]], points_b[example.matches[:, 1]]
    correct = np.linalg.norm(warp_points(matched_a, example.homography) - matched_b, axis=1) <= threshold
    axes.imshow(canvas, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    axes.scatter(points_a[:, 0], points_a[:, 1], s=2, c="yellow", linewidths=0)
    axes.scatter(points_b[:, 0] + offset, points_b[:, 1], s=2, c="yellow", linewidths=0)
    for (xa, ya), (xb, yb), ok in zip(matched_a, matched_b, correct):
        axes.plot([xa, xb + offset], [ya, yb], color="lime" if ok else "red", linewidth=0.5, alpha=0.8)
    axes.set_axis_off()
    axes.set_title(f"{label}  {example.name}: {int(correct.sum())}/{len(correct)} mutual-NN matches within "
                   f"{threshold:g} px" + ("  (shown contrast-stretched)" if stretched else ""), fontsize=8, pad=2)


# An earlier report is replaced (eval has no --force: its reports are cheap to remake); anything else is refused.
EVAL_REPORT = OutputKind("eval-report", "an eval report")


def claim_report_dir(path: Path, inputs: Iterable[Path] = ()) -> AbstractContextManager[OutputClaim]:
    """Hold ``path`` for a report: refused below a file, on a file, on a non-empty folder that is not only
    an earlier report, or in, on or above one of ``inputs`` (`vo_runtime.outputs`)."""
    return claim_output_dir(path, EVAL_REPORT, True, inputs)


def write_report(claim: OutputClaim, report: dict[str, Any], examples: dict[str, PairExample]) -> None:
    """Write results.json, results.md and the match PNGs into a temp dir beside the claimed folder, then swap
    it in."""
    with claim.writing() as staging:
        (staging / REPORT_JSON).write_text(json.dumps(report, indent=2) + "\n")
        (staging / REPORT_MARKDOWN).write_text(format_markdown(report))
        for label, shown in examples.items():
            plot_matches(shown, staging / f"matches_{safe_file_stem(label)}.png", label,
                         report["protocol"]["correct_threshold"])
