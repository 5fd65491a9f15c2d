"""Trajectory accuracy against ground truth through evo (ATE and RPE after Sim(3) alignment), and a plot.

evo and matplotlib are imported only here, so the runtime itself needs neither.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any
from typing import Sequence as Seq

import numpy as np

from vo_runtime.errors import VORuntimeError, first_line
from vo_runtime.odometry import INITIALISING, SKIPPED, VOResult


EVALUATION_EXTRAS = ("edgefeat-runtime[eval]", "edgefeat[eval]")  # the runtime wheel's extra, the full install's


def require_evaluation_packages() -> None:
    """Raise one line naming the extra when evo or matplotlib is missing (a runtime-only install)."""
    import importlib.util

    missing = [name for name in ("evo", "matplotlib") if importlib.util.find_spec(name) is None]
    if missing:
        raise VORuntimeError(f"--gt needs {' and '.join(missing)}, which a runtime-only install leaves out: "
                             f"pip install '{EVALUATION_EXTRAS[0]}' (the runtime wheel) or '{EVALUATION_EXTRAS[1]}'")


def require_groundtruth_file(path: Path) -> None:
    """`VORuntimeError` unless ``path`` is a file: a folder is named as one, not reported missing."""
    if path.is_dir():
        raise VORuntimeError(f"ground truth {path} is a folder, not a file")
    if not path.is_file():
        raise VORuntimeError(f"ground truth not found: {path}")


def load_groundtruth(path: str | Path, layout: str, timestamps: Seq[float]) -> Any:
    """Ground truth as an evo trajectory: KITTI ``poses.txt`` (12 numbers a line, one line per frame, stamped
    with ``timestamps``) or TUM ``groundtruth.txt``. Raises `VORuntimeError` for anything else, before a run."""
    from evo import EvoException
    from evo.core.trajectory import PoseTrajectory3D
    from evo.tools import file_interface

    path = Path(path)
    require_groundtruth_file(path)
    if layout == "tum":
        try:
            trajectory = file_interface.read_tum_trajectory_file(str(path))
        except (EvoException, OSError, ValueError, UnicodeDecodeError) as exc:
            raise VORuntimeError(f"{path} is not a TUM trajectory (timestamp tx ty tz qx qy qz qw a line): "
                                 f"{first_line(exc)}") from None
        if trajectory.num_poses < 2:
            raise VORuntimeError(f"{path} holds {trajectory.num_poses} poses: nothing to evaluate against")
        # Checked now: a NaN pose passed this reader and failed the alignment after the whole run.
        # (Repeated stamps are real: TUM's own files hold some, and the association copes with them.)
        values = (trajectory.timestamps, trajectory.positions_xyz, trajectory.orientations_quat_wxyz)
        if not all(np.all(np.isfinite(value)) for value in values):
            raise VORuntimeError(f"{path} holds non-finite poses or timestamps (NaN or inf)")
        return trajectory
    rows = _kitti_rows(path)
    if len(rows) < len(timestamps):
        raise VORuntimeError(f"{path} has {len(rows)} poses for {len(timestamps)} frames")
    poses = np.tile(np.eye(4), (len(timestamps), 1, 1))
    poses[:, :3, :] = rows[: len(timestamps)].reshape(-1, 3, 4)
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=np.asarray(timestamps, float))


def sequence_groundtruth(sequence: Any, path: str | Path | None = None) -> Any:
    """The ground truth of a `datasets.Sequence` (its own file, or ``path``) as an evo trajectory of camera
    poses: EuRoC body poses become camera poses (``T_WB @ T_BS``) at the frames' timestamps (nearest within
    5 ms); KITTI and TUM files as `load_groundtruth` reads them."""
    path = Path(path) if path is not None else sequence.groundtruth
    if path is None:
        raise VORuntimeError("the sequence has no ground truth (poses.txt, groundtruth.txt or "
                             "state_groundtruth_estimate0/data.csv)")
    if sequence.layout != "euroc":
        return load_groundtruth(path, "tum" if sequence.layout == "tum" else "kitti", sequence.timestamps)
    from evo.core.trajectory import PoseTrajectory3D

    from vo_runtime.euroc import camera_groundtruth

    require_groundtruth_file(path)
    stamps, poses = camera_groundtruth(path, sequence.body_from_camera, sequence.timestamps)
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps)


def _kitti_rows(path: Path) -> np.ndarray:
    """The [N, 12] finite numbers of a KITTI poses file; `VORuntimeError` naming what is wrong."""
    try:
        with warnings.catch_warnings():  # numpy warns about an empty file before returning nothing
            warnings.simplefilter("ignore")
            rows = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise VORuntimeError(f"{path} is not a KITTI poses file (12 numbers a line): {first_line(exc)}") from None
    if rows.size == 0:
        raise VORuntimeError(f"{path} holds no poses")
    if rows.shape[1] != 12:
        raise VORuntimeError(f"{path}: expected 12 values a line (KITTI 3x4 poses), got {rows.shape[1]}")
    if not np.all(np.isfinite(rows)):
        raise VORuntimeError(f"{path} holds non-finite values")
    return rows


def scored_results(results: Seq[VOResult]) -> list[VOResult]:
    """The frames `evaluate` scores: every frame past the first initialisation (lost ones hold a pose)."""
    return [r for r in results if r.status not in (INITIALISING, SKIPPED)]


def evaluate(results: Seq[VOResult], groundtruth: Any, layout: str, timestamps: Seq[float]) -> dict[str, Any]:
    """ATE RMSE and RPE RMSE (1-frame translation, metres) of the frames past initialisation.

    ``groundtruth`` is a file (read by `load_groundtruth`) or the trajectory it returned. The estimate is
    aligned to the ground truth by Sim(3) (Umeyama with scale), as monocular VO needs. ``layout`` is "kitti"
    (poses.txt, one per frame, with ``timestamps``) or "tum" (groundtruth.txt, associated by nearest
    timestamp within 10 ms).
    """
    from evo import EvoException
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    used = scored_results(results)
    if len(used) < 3:
        raise VORuntimeError(f"only {len(used)} frames past initialisation: nothing to evaluate")
    stamps = np.array([timestamps[r.index] for r in used], float)
    est = PoseTrajectory3D(poses_se3=[r.pose for r in used], timestamps=stamps)
    ref = load_groundtruth(groundtruth, layout, timestamps) if isinstance(groundtruth, (str, Path)) else groundtruth
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
        _, _, scale = est.align(ref, correct_scale=True)
        ate = metrics.APE(metrics.PoseRelation.translation_part)
        ate.process_data((ref, est))
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames,
                          all_pairs=False)
        rpe.process_data((ref, est))
    except EvoException as exc:  # no common timestamps, or no motion tracked (degenerate alignment)
        raise VORuntimeError(f"cannot evaluate against the ground truth: {first_line(exc)}") from None
    return {
        "frames_evaluated": int(est.num_poses),
        "path_length_m": round(float(ref.path_length), 3),
        "ate_rmse_m": round(float(ate.get_statistic(metrics.StatisticsType.rmse)), 4),
        "rpe_rmse_m": round(float(rpe.get_statistic(metrics.StatisticsType.rmse)), 4),
        "sim3_scale": round(float(scale), 4),
        "_aligned": (est, ref),
        "_lost": _lost_mask(used, est.timestamps),  # per aligned pose: its frame was not tracked (pose held)
    }


def _lost_mask(used: Seq[VOResult], stamps: np.ndarray) -> np.ndarray:
    """For each pose evo kept after association, whether its frame was lost (matched back by timestamp)."""
    from vo_runtime.odometry import TRACKED_STATES

    lost_stamps = np.array([r.timestamp for r in used if r.status not in TRACKED_STATES and r.timestamp is not None],
                           float)
    return np.isin(np.asarray(stamps, float), lost_stamps)  # evo keeps the stamps it was given, bit for bit


def plot_trajectory(path: str | Path, report: dict[str, Any], title: str) -> None:
    """PNG of the aligned estimate against ground truth, seen from above (the two axes the ground truth spans
    most), start and end marked, frames where the VO was lost (pose held) in another colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est, ref = report["_aligned"]
    lost = report.get("_lost", np.zeros(est.num_poses, bool))
    spread = np.ptp(ref.positions_xyz, axis=0)
    a, b = sorted(np.argsort(spread)[-2:])  # the plane the motion spans: x-z for a car, x-y for a drone's world
    names = "xyz"
    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    ax.plot(ref.positions_xyz[:, a], ref.positions_xyz[:, b], "k-", label="ground truth")
    ax.plot(est.positions_xyz[:, a], est.positions_xyz[:, b], "r.-", markersize=3, linewidth=1,
            label="VO (Sim(3) aligned)")
    if np.any(lost):
        ax.plot(est.positions_xyz[lost, a], est.positions_xyz[lost, b], "x", color="orange", markersize=6,
                label=f"lost, pose held ({int(np.count_nonzero(lost))} frames)")
    for positions in (ref.positions_xyz, est.positions_xyz):
        ax.plot(*positions[0, [a, b]], "o", color="tab:green", markersize=8, markeredgecolor="k")
        ax.plot(*positions[-1, [a, b]], "s", color="tab:blue", markersize=8, markeredgecolor="k")
    ax.plot([], [], "o", color="tab:green", markeredgecolor="k", label="start")
    ax.plot([], [], "s", color="tab:blue", markeredgecolor="k", label="end")
    ax.set_xlabel(f"{names[a]} [m]")
    ax.set_ylabel(f"{names[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{title}\nATE {report['ate_rmse_m']:.3f} m, RPE {report['rpe_rmse_m']:.3f} m", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
