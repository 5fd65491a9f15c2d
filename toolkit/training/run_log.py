"""A training run's logs: CSV rows replayed exactly on resume, and the curves as PNGs."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from vo_runtime.atomic_file import atomic_path, write_atomic


def truncate_csv(path: Path, fields: list[str], last_step: int) -> None:
    """Keep the header and the rows up to ``last_step`` (rows after the resume point are replayed)."""
    rows = []
    if path.exists():
        with path.open(newline="") as file:
            rows = [row for row in csv.DictReader(file) if int(row["step"]) <= last_step]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(path, buffer.getvalue().encode())


def append_csv(path: Path, fields: list[str], row: dict) -> None:
    with path.open("a", newline="") as file:
        csv.DictWriter(file, fieldnames=fields).writerow({key: row[key] for key in fields})


def _plot_columns(csv_path: Path, png_path: Path, keys: tuple[str, ...], ylabel: str, marker: str | None,
                  ylim: tuple[float, float] | None) -> None:
    """Columns of a run CSV against its step, written to ``png_path`` atomically (temp file + rename)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with csv_path.open(newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        return
    steps = [int(r["step"]) for r in rows]
    figure, axis = plt.subplots(figsize=(6, 3.5), dpi=100)
    for key in keys:
        axis.plot(steps, [float(r[key]) for r in rows], marker=marker, label=key)
    axis.set_xlabel("step")
    axis.set_ylabel(ylabel)
    if ylim is not None:
        axis.set_ylim(*ylim)
    axis.legend()
    axis.grid(alpha=0.3)
    figure.tight_layout()
    with atomic_path(png_path) as temporary:
        figure.savefig(temporary, format="png")
    plt.close(figure)


def plot_loss_curve(log_path: Path, png_path: Path) -> None:
    """Loss and its parts against the step, from ``log.csv``."""
    _plot_columns(log_path, png_path, ("loss", "detector_loss", "descriptor_loss"), "loss", None, None)


def plot_validation_curve(val_path: Path, png_path: Path) -> None:
    """Validation metrics against the step, from ``val.csv``: the curve that picks the best checkpoint."""
    _plot_columns(val_path, png_path, ("matching_score", "nn_map", "repeatability"), "held-back pairs", "o", (0.0, 1.0))
