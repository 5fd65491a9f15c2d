"""bench/scale_trace.py: the local scale and errors it reports, on a trajectory whose answer is known."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.scale_trace import trace  # noqa: E402
from vo_runtime.config import VOResult  # noqa: E402


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    angle = np.radians(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    pose[0, 3] = x
    return pose


def test_a_scale_collapse_and_a_rotation_error_show_where_they_happen():
    # The truth moves 1 m a frame along x; the estimate 0.5 m a frame (its own unit), then from frame 30 on
    # 0.1 m a frame (the map shrank five-fold), and frame 40 is lost; from frame 50 on it turns 0.2 deg a
    # frame that the truth does not.
    truth = [_pose(float(i)) for i in range(60)]
    position, results = 0.0, []
    for i in range(60):
        position += 0 if i == 0 else (0.5 if i < 30 else 0.1)
        status = "lost" if i == 40 else "tracking"
        results.append(VOResult(index=i, timestamp=0.1 * i, pose=_pose(position, 0.2 * max(0, i - 50)), status=status,
                                num_features=500, num_matches=200, num_inliers=150, num_landmarks=150,
                                extract_ms=0.0, track_ms=0.0))
    rows = {r["frame"]: r for r in trace(results, truth, gap=1)}
    assert rows[10]["scale"] == pytest.approx(1.0) and rows[29]["scale"] == pytest.approx(1.0)
    assert rows[35]["scale"] == pytest.approx(0.2)
    assert 40 not in rows and 41 not in rows  # a lost frame, and the frame after it, have no step
    assert rows[35]["direction_deg"] == pytest.approx(0.0, abs=1e-6)
    assert rows[45]["rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    assert rows[55]["rotation_deg"] == pytest.approx(0.2, abs=1e-6)


def test_a_start_past_the_sequence_is_one_error_line(shared_data, tmp_path):
    plot = tmp_path / "trace.png"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "scale_trace.py"), "--sequence",
                          str(shared_data / "tum_fr2_desk_snippet"), "--start", "100000", "--plot", str(plot)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --start 100000") and not plot.exists()


def test_a_noise_draw_is_eval_vos_run_of_that_draw(shared_data):
    # TUM in the dark, draw 1: the tracer's per-frame inliers are those of bench/eval_vo.py's run of draw 1
    # (the same darkening seeds), and differ from draw 0's.
    from bench.eval_vo import run_one
    from vo_runtime import VOConfig
    from vo_runtime.artefact import default_artefact

    sequence = shared_data / "tum_fr2_desk_snippet"
    traced = {}
    for seed in (0, 1):
        run = subprocess.run([sys.executable, str(ROOT / "bench" / "scale_trace.py"), "--sequence", str(sequence),
                              "--light", "low", "--seed", str(seed), "--every", "1", "--gap", "2"],
                             capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        lines = [line.split() for line in run.stdout.splitlines()[2:] if line.strip()]
        traced[seed] = {int(cells[0]): int(cells[2]) for cells in lines}
    assert traced[0] != traced[1]
    row = run_one(sequence, "artefact", "low", 2000, VOConfig(), default_artefact(640, 480), None, seed=1)
    inliers = {result.index: result.num_inliers for result in row["_results"]}
    assert traced[1] and all(inliers[frame] == count for frame, count in traced[1].items())


def test_a_negative_noise_draw_is_one_error_line(shared_data):
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "scale_trace.py"), "--sequence",
                          str(shared_data / "tum_fr2_desk_snippet"), "--light", "low", "--seed", "-1"],
                         capture_output=True, text=True, timeout=120)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: --seed -1")


def test_a_denser_ground_truth_is_taken_at_the_frames_timestamps():
    # A motion-capture stream at 100 Hz (x = its time in metres) and frames at 10 Hz between its samples: each
    # frame gets the nearest sample, not the stream's k-th row; a frame 50 ms from any sample is refused.
    from evo.core.trajectory import PoseTrajectory3D

    from bench.scale_trace import truth_at_frames
    from vo_runtime.errors import VORuntimeError

    times = np.arange(0.0, 3.0, 0.01)
    stream = PoseTrajectory3D(poses_se3=[_pose(t) for t in times], timestamps=times)
    frames = [0.504, 0.6031, 0.7, 1.2996]
    picked = truth_at_frames(stream, frames)
    assert [round(p[0, 3], 2) for p in picked] == [0.5, 0.6, 0.7, 1.3]
    # One pose a frame, stamped with the frames' own stamps (KITTI, EuRoC): each frame gets its own row.
    per_frame = [_pose(10.0 * k) for k in range(4)]
    own = truth_at_frames(PoseTrajectory3D(poses_se3=per_frame, timestamps=np.array([5.0, 6.0, 7.0, 8.0])),
                          [5.0, 6.0, 7.0, 8.0])
    assert [p[0, 3] for p in own] == [0.0, 10.0, 20.0, 30.0]
    with pytest.raises(VORuntimeError, match="frame 1: no ground-truth pose within 20 ms"):
        truth_at_frames(stream, [0.5, 3.05])


def test_tums_trace_measures_travel_between_the_frames_poses(shared_data):
    # TUM's groundtruth.txt is the mocap stream: the traced true travel over two frames is the distance
    # between the stream's samples at those frames' timestamps (~20 mm a frame at 10 Hz), not between rows.
    from vo_runtime.datasets import open_sequence
    from vo_runtime.evaluate import sequence_groundtruth

    sequence = shared_data / "tum_fr2_desk_snippet"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "scale_trace.py"), "--sequence", str(sequence),
                          "--every", "1", "--gap", "1"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    traced = {int(cells[0]): float(cells[-1]) for cells in
              (line.split() for line in run.stdout.splitlines()[2:] if line.strip())}
    opened = open_sequence(sequence)
    truth = sequence_groundtruth(opened)
    times = np.asarray(truth.timestamps)
    at = [int(np.argmin(np.abs(times - stamp))) for stamp in opened.timestamps]
    assert len(traced) >= 10
    for frame, travel_mm in traced.items():
        expected = np.linalg.norm(truth.positions_xyz[at[frame]] - truth.positions_xyz[at[frame - 1]])
        assert travel_mm == pytest.approx(1e3 * expected, abs=0.06)
    assert np.median(list(traced.values())) > 10.0
