"""MonoVO on a synthetic scene with known poses: exact geometry, scale consistency, loss and recovery.

The scene is an extractor double that projects a fixed cloud of 3D points (each with its own descriptor)
into a camera moving along a known path, so the answer is known exactly.
"""
from __future__ import annotations

import numpy as np
import pytest

from vo_runtime import CalibrationError, Camera, Features, MonoVO, VOConfig, VORuntimeError
from vo_runtime.odometry import INITIALISING, LOST, REINITIALISED, RELOCALISED, TRACKING

WIDTH, HEIGHT = 640, 480
CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=WIDTH, height=HEIGHT)
BLANK = np.zeros((HEIGHT, WIDTH), np.uint8)  # the frame handed to MonoVO; the double ignores its pixels


def straight_then_turn(frames: int, step: float = 0.3) -> list[np.ndarray]:
    """Camera-to-world poses: forward along z, with a gentle yaw that grows after the first third."""
    poses, position, yaw = [], np.zeros(3), 0.0
    for i in range(frames):
        rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot, position
        poses.append(pose)
        yaw += 0.0 if i < frames // 3 else 0.01
        position = position + step * rot[:, 2]
    return poses


def creeping_before(frame: int, poses: list[np.ndarray]) -> list[np.ndarray]:
    """``poses`` whose four steps before ``frame`` are a tenth as long (as a failing map's last steps look)."""
    steps = np.diff([pose[:3, 3] for pose in poses], axis=0, prepend=np.zeros((1, 3)))
    steps[frame - 4:frame] *= 0.1
    for pose, position in zip(poses, np.cumsum(steps, axis=0)):
        pose[:3, 3] = position
    return poses


class SyntheticExtractor:
    """Returns the visible points of the current pose as `Features`; `blackout` frames get none."""

    def __init__(self, poses: list[np.ndarray], noise_px: float = 0.0, points: int = 6000, seed: int = 0,
                 blackout: frozenset[int] = frozenset(), scramble: frozenset[int] = frozenset(),
                 wall_at: float | None = None) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.poses, self.noise_px, self.blackout, self.scramble = poses, noise_px, blackout, scramble
        centre = np.mean([p[:3, 3] for p in poses], axis=0)
        offsets = np.c_[rng.uniform(-25, 25, points), rng.uniform(-6, 3, points), rng.uniform(-25, 40, points)]
        self.points = centre + offsets
        if wall_at is not None:  # a planar scene: every point on the plane z = wall_at
            self.points = np.c_[rng.uniform(-20, 20, points), rng.uniform(-12, 12, points), np.full(points, wall_at)]
        desc = rng.normal(size=(points, 64))
        self.descriptors = desc / np.linalg.norm(desc, axis=1, keepdims=True)
        self.calls = 0

    def __call__(self, image: np.ndarray) -> Features:
        index = self.calls
        self.calls += 1
        if index in self.blackout:
            return Features(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 64), np.float32))
        world_to_cam = np.linalg.inv(self.poses[index])
        cam = self.points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = CAMERA.fx * cam[:, 0] / z + CAMERA.cx
            v = CAMERA.fy * cam[:, 1] / z + CAMERA.cy
        visible = np.flatnonzero((z > 0.5) & (z < 60) & (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT))[:1500]
        keypoints = np.c_[u[visible], v[visible]] + self.rng.normal(scale=self.noise_px, size=(len(visible), 2))
        descriptors = self.descriptors[visible]
        if index in self.scramble:  # right keypoints, unrelated descriptors: nothing matches
            descriptors = self.rng.normal(size=descriptors.shape)
            descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
        order = self.rng.permutation(len(visible))  # the runtime must not rely on keypoint order
        return Features(keypoints[order].astype(np.float32), np.ones(len(visible), np.float32),
                        descriptors[order].astype(np.float32))


def ate(estimated: list[np.ndarray], reference: list[np.ndarray]) -> tuple[float, float]:
    """ATE (RMSE of positions) after evo's Sim(3) alignment of two lists of 4x4 poses; returns (rmse, scale)."""
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    est, ref = PosePath3D(poses_se3=list(estimated)), PosePath3D(poses_se3=list(reference))
    _, _, scale = est.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse)), float(scale)


def run(extractor: SyntheticExtractor, frames: int, config: VOConfig | None = None) -> MonoVO:
    vo = MonoVO(extractor, CAMERA, config)
    for i in range(frames):
        vo.process(BLANK, timestamp=0.1 * i)
    return vo


def tracked(vo: MonoVO) -> list[int]:
    return [r.index for r in vo.results if r.status in (TRACKING, REINITIALISED)]


def test_noise_free_trajectory_is_exact_up_to_scale():
    poses = straight_then_turn(60)
    vo = run(SyntheticExtractor(poses), 60)
    statuses = [r.status for r in vo.results]
    assert statuses[0] == INITIALISING and statuses[-1] == TRACKING
    assert LOST not in statuses
    first = tracked(vo)[0]
    assert first <= 15, "initialisation should happen within a few frames of enough motion"
    rmse, _ = ate([vo.results[i].pose for i in range(first, 60)], poses[first:])
    assert rmse < 1e-3 * 0.3 * 60  # < 0.1 % of the path
    # World = first camera: the reported pose at frame 0 is the identity.
    np.testing.assert_allclose(vo.results[0].pose, np.eye(4))


def test_initialisation_picks_the_model_that_fits():
    poses = straight_then_turn(30)
    general = run(SyntheticExtractor(poses), 30)
    assert general.init_model == "essential"
    # A wall facing the camera: the homography explains the motion, and its decomposition gives the pose.
    sideways = [p.copy() for p in poses]
    for i, p in enumerate(sideways):
        p[:3, 3] = [0.25 * i, 0.05 * i - 0.004 * i * i, 0.1 * i]
    planar = run(SyntheticExtractor(sideways, wall_at=25.0), 30)
    assert planar.init_model == "homography"
    first = tracked(planar)[0]
    rmse, _ = ate([planar.results[i].pose for i in range(first, 30)], sideways[first:])
    assert rmse < 1e-3


def test_initialisation_waits_for_the_median_ray_angle(monkeypatch):
    """A short first baseline sets a poor scale and map: the two-view fit waits until the median ray angle of
    its landmarks reaches `init_min_median_deg` (the tracks are healthy here, so nothing relaxes it)."""
    from vo_runtime.initialiser import Initialiser

    committed = []
    original = Initialiser.try_initialise

    def recording(self, index, poses_cw, speed):
        outcome = original(self, index, poses_cw, speed)
        if outcome is not None:
            committed.append((index, float(np.median(outcome.angles))))
        return outcome

    monkeypatch.setattr(Initialiser, "try_initialise", recording)
    poses = straight_then_turn(30)
    for gate in (0.0, 2.0):
        run(SyntheticExtractor(poses), 30, VOConfig(init_min_median_deg=gate))
    (early, early_angle), (late, late_angle) = committed
    assert early_angle < 2.0 <= late_angle and late > early


def test_first_baseline_sets_the_unit():
    poses = straight_then_turn(30)
    vo = run(SyntheticExtractor(poses), 30, VOConfig(initial_baseline=2.0))
    first = tracked(vo)[0]
    est = np.linalg.norm(vo.results[first].pose[:3, 3] - vo.results[0].pose[:3, 3])
    assert est == pytest.approx(2.0, rel=1e-6)
    # Later steps keep that unit: step length / true step length is constant.
    true_step = 0.3 * 2.0 / np.linalg.norm(poses[first][:3, 3] - poses[0][:3, 3])
    steps = [np.linalg.norm(vo.results[i].pose[:3, 3] - vo.results[i - 1].pose[:3, 3]) for i in range(first + 1, 30)]
    np.testing.assert_allclose(steps, true_step, rtol=1e-3)


def test_pixel_noise_keeps_scale_and_accuracy():
    poses = straight_then_turn(80)
    vo = run(SyntheticExtractor(poses, noise_px=0.7, seed=3), 80)
    first = tracked(vo)[0]
    assert [r.status for r in vo.results[first:]].count(TRACKING) == 80 - first
    rmse, _ = ate([r.pose for r in vo.results[first:]], poses[first:])
    path = 0.3 * (80 - first)
    assert rmse < 0.02 * path
    # Scale drift: metres per output unit over the first and last quarters agree within 25 %.
    est = np.array([r.pose[:3, 3] for r in vo.results])
    ref = np.array([p[:3, 3] for p in poses])
    q = (80 - first) // 4
    quarters = ((first, first + q), (79 - q, 79))
    ratios = [np.linalg.norm(ref[b] - ref[a]) / np.linalg.norm(est[b] - est[a]) for a, b in quarters]
    assert ratios[1] == pytest.approx(ratios[0], rel=0.25)


def test_frame_without_features_is_skipped_and_pose_held():
    poses = straight_then_turn(40)
    vo = run(SyntheticExtractor(poses, blackout=frozenset({25})), 40)
    assert vo.results[25].status == LOST and vo.results[25].num_features == 0
    np.testing.assert_allclose(vo.results[25].pose, vo.results[24].pose, atol=1e-5)  # held (24 refined later)
    assert vo.results[26].status == TRACKING  # matched against frame 24
    first = tracked(vo)[0]
    good = [i for i in range(first, 40) if i != 25]
    rmse, _ = ate([vo.results[i].pose for i in good], [poses[i] for i in good])
    assert rmse < 1e-3


def test_unmatched_frame_loses_tracking_then_reinitialises_at_the_old_speed():
    poses = straight_then_turn(60)
    # Relocalisation and the motion model after a loss off: the only way back is a fresh initialisation (the
    # young map's discard off too: it is how a map older than young_map_frames comes back, test_vo_young_map.py).
    vo = run(SyntheticExtractor(poses, scramble=frozenset({30})), 60,
             VOConfig(relocalise_keyframes=0, lost_predict_frames=0, young_map_frames=0))
    statuses = [r.status for r in vo.results]
    assert statuses[30] == LOST
    assert REINITIALISED in statuses[31:]
    back = statuses.index(REINITIALISED, 31)
    assert all(s == TRACKING for s in statuses[back + 1:])
    # Constant speed before and after: the re-initialised part continues at the same scale.
    est = np.array([r.pose[:3, 3] for r in vo.results])
    before = np.linalg.norm(est[29] - est[28])
    after = np.linalg.norm(est[59] - est[58])
    assert after == pytest.approx(before, rel=0.05)


@pytest.mark.parametrize("speed_frames", [1, 20])
def test_reinitialisation_scale_is_the_median_speed_before_the_loss(speed_frames):
    # Frames 26-29 creep at a tenth of the speed (as a failing map's shrinking last steps look), then the
    # camera is lost at frame 30 and moves on at full speed: the new map's scale follows the median speed of
    # the last speed_frames tracked frames (20: the full speed; 1: the creep, ten times too short).
    poses = creeping_before(30, straight_then_turn(60))
    vo = run(SyntheticExtractor(poses, scramble=frozenset({30})), 60,
             VOConfig(relocalise_keyframes=0, lost_predict_frames=0, speed_frames=speed_frames, young_map_frames=0))
    statuses = [r.status for r in vo.results]
    assert REINITIALISED in statuses[31:]
    est = np.array([r.pose[:3, 3] for r in vo.results])
    before = np.linalg.norm(est[20] - est[19])   # full speed, the first map's scale
    after = np.linalg.norm(est[59] - est[58])
    assert after == pytest.approx(before if speed_frames == 20 else 0.1 * before, rel=0.1)


@pytest.mark.parametrize("bad", [{30}, {30, 31}])
def test_after_a_loss_the_motion_model_tracks_the_next_good_frame_against_the_map(bad):
    poses = straight_then_turn(60)
    # Relocalisation off, so only the prediction can bring the next good frame back into the same map.
    vo = run(SyntheticExtractor(poses, scramble=frozenset(bad)), 60, VOConfig(relocalise_keyframes=0))
    statuses = [r.status for r in vo.results]
    back = max(bad) + 1
    assert all(statuses[i] == LOST for i in bad) and statuses[back] == TRACKING
    assert REINITIALISED not in statuses and all(s == TRACKING for s in statuses[back:])
    first = tracked(vo)[0]
    good = [i for i in range(first, 60) if i not in bad]
    rmse, _ = ate([vo.results[i].pose for i in good], [poses[i] for i in good])
    assert rmse < 1e-3
    # Beyond lost_predict_frames the prediction is no longer trusted: a fresh initialisation instead.
    vo = run(SyntheticExtractor(poses, scramble=frozenset(bad)), 60,
             VOConfig(relocalise_keyframes=0, lost_predict_frames=len(bad), young_map_frames=0))
    assert REINITIALISED in [r.status for r in vo.results]


def test_unmatched_frame_is_relocalised_against_the_map_at_the_right_pose():
    poses = straight_then_turn(60)
    vo = run(SyntheticExtractor(poses, scramble=frozenset({30, 31})), 60, VOConfig(lost_predict_frames=0))
    statuses = [r.status for r in vo.results]
    assert statuses[30] == statuses[31] == LOST
    assert statuses[32] == RELOCALISED and vo.results[32].tracked_by == "relocalisation"
    assert all(s == TRACKING for s in statuses[33:])
    # Same map, same scale: the whole trajectory, loss included, is one similarity away from the truth.
    first = tracked(vo)[0]
    good = [i for i in range(first, 60) if i not in (30, 31)]
    rmse, _ = ate([vo.results[i].pose for i in good], [poses[i] for i in good])
    assert rmse < 1e-3


def test_reset_starts_a_new_origin():
    poses = straight_then_turn(20)
    extractor = SyntheticExtractor(poses)
    vo = run(extractor, 15)
    vo.reset()
    result = vo.process(BLANK)
    assert result.index == 0 and result.status == INITIALISING
    np.testing.assert_array_equal(result.pose, np.eye(4))


def test_frame_size_must_match_the_calibration():
    vo = MonoVO(SyntheticExtractor(straight_then_turn(2)), CAMERA)
    with pytest.raises(CalibrationError, match="640x480"):
        vo.process(np.zeros((100, 100), np.uint8))
    with pytest.raises(VORuntimeError):
        vo.process("not an image")


def test_config_is_validated():
    with pytest.raises(VORuntimeError):
        VOConfig(min_matches=3)
    with pytest.raises(VORuntimeError):
        VOConfig(initial_baseline=0)
    with pytest.raises(VORuntimeError):
        VOConfig(speed_frames=0)
    from vo_runtime.mapping import MappingConfig
    with pytest.raises(VORuntimeError, match="neighbour_radius_px"):
        MappingConfig(neighbour_keyframes=5, neighbour_radius_px=0)
    with pytest.raises(VORuntimeError, match="neighbour_keyframes"):
        VOConfig(mapping=MappingConfig(neighbour_keyframes=-1))


def test_result_fields():
    poses = straight_then_turn(20)
    vo = run(SyntheticExtractor(poses), 20)
    last = vo.results[-1]
    assert last.timestamp == pytest.approx(1.9)
    assert last.num_features > last.num_matches > 0 and last.num_inliers > 0 and last.num_landmarks > 0
    assert last.extract_ms >= 0 and last.track_ms > 0
    assert last.pose.shape == (4, 4)


def test_runtime_never_imports_torch():
    import subprocess
    import sys

    probe = ("import sys, vo_runtime, vo_runtime.cli, vo_runtime.odometry, vo_runtime.evaluate, vo_runtime.datasets; "
             "print('torch' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_keyframes_follow_the_gap_and_the_view_change():
    poses = straight_then_turn(60)
    periodic = run(SyntheticExtractor(poses), 60, VOConfig(keyframe_max_gap=5))
    keyframes = [r.index for r in periodic.results if r.keyframe]
    first = tracked(periodic)[0]
    assert keyframes[0] == first  # the initialisation frame is the first keyframe
    assert np.diff(keyframes).max() == 5 and np.diff(keyframes).min() >= 1
    # With the view-change trigger a keyframe comes sooner once the last keyframe's landmarks leave view.
    eager = run(SyntheticExtractor(poses), 60, VOConfig(keyframe_max_gap=50, keyframe_track_ratio=0.95))
    eager_keyframes = [r.index for r in eager.results if r.keyframe]
    assert len(eager_keyframes) > 2 and np.diff(eager_keyframes).max() < 50


def test_old_keyframes_release_their_descriptors_and_the_track_goes_on(monkeypatch):
    import vo_runtime.keyframing as keyframing

    poses = straight_then_turn(60)
    kept = run(SyntheticExtractor(poses, noise_px=0.5), 60, VOConfig(keyframe_max_gap=2))
    monkeypatch.setattr(keyframing, "MAP_HORIZON_KEYFRAMES", 4)
    released = run(SyntheticExtractor(poses, noise_px=0.5), 60, VOConfig(keyframe_max_gap=2))
    keyframes = released.map.keyframes
    assert len(keyframes) > 12
    assert all(k.descriptors is None for k in keyframes[:-4]) and all(k.descriptors is not None for k in keyframes[-4:])
    assert all(k.descriptors is not None for k in kept.map.keyframes)
    assert tracked(released) == tracked(kept)  # every frame tracked either way, and as accurately
    first = tracked(released)[0]
    error, _ = ate([r.pose for r in released.results[first:]], poses[first:])
    assert error < 0.005 * 0.3 * (60 - first)  # 0.5 % of the path (kept: 0.026 m, released: 0.032 m of 14 m)


@pytest.mark.parametrize("features", ["orb", "artefact"])  # the artefact resizes: patch alignment on
def test_mapping_thread_gives_the_same_poses_as_inline_mapping(shared_data, features):
    # The worker only runs between one frame's tracking and the next, so nothing may change but the time.
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import open_sequence
    from vo_runtime.features import FeatureExtractor, OrbExtractor
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "kitti_odom06_f000000-000050")
    frames = list(read_frames(sequence.frames[:30]))
    extractor = OrbExtractor(1000) if features == "orb" else FeatureExtractor(default_artefact())
    poses = {}
    for threaded in (False, True):
        vo = MonoVO(extractor, sequence.camera, VOConfig(mapping_thread=threaded))
        for image, stamp in zip(frames, sequence.timestamps):
            vo.process(image, stamp)
            if len(vo.results) == 12:
                vo.skip("a dropped frame")  # a skip waits for the worker too
        vo.finish()
        mapped = [r for r in vo.results if r.keyframe and r.tracked_by != "two-view"]  # not the map's first
        assert len(mapped) >= 3 and all(r.mapping_ms > 0 for r in mapped)
        poses[threaded] = np.stack([r.pose for r in vo.results])
    np.testing.assert_array_equal(poses[True], poses[False])


def test_a_failing_mapping_job_is_raised_on_the_next_frame():
    from vo_runtime.background import Background

    background = Background()

    def fail() -> None:
        raise ValueError("mapping failed")

    background.submit(fail)
    with pytest.raises(ValueError, match="mapping failed"):
        background.wait()
    assert background.wait() == 0.0  # nothing pending any more
    background.close()


def whole_track_with_mapping(poses: list[np.ndarray], **mapping) -> MonoVO:
    """A run over ``poses`` (0.5 px noise) with these `MappingConfig` fields: every frame after the first map
    tracked, the ATE within 2 % of the distance travelled."""
    from dataclasses import replace

    config = VOConfig()
    config = replace(config, mapping=replace(config.mapping, **mapping))
    vo = run(SyntheticExtractor(poses, noise_px=0.5, seed=3), len(poses), config)
    first = tracked(vo)[0]
    assert [r.status for r in vo.results[first:]].count(TRACKING) == len(poses) - first
    rmse, _ = ate([r.pose for r in vo.results[first:]], poses[first:])
    assert rmse < 0.02 * 0.3 * (len(poses) - first)
    return vo


def test_searching_neighbour_keyframes_adds_views_and_keeps_the_track():
    # `mapping.neighbour_keyframes`: landmarks the tracking did not match in older keyframes become observations.
    poses = straight_then_turn(60)
    views = {}
    for neighbours in (0, 5):
        vo = whole_track_with_mapping(poses, neighbour_keyframes=neighbours)
        alive = np.flatnonzero(vo.map.alive[: vo.map.size])
        views[neighbours] = float(vo.map.observation_counts(alive).mean())
        assert all(list(vo.map.observations[i]) == sorted(vo.map.observations[i]) for i in alive.tolist())
    assert views[5] > 1.05 * views[0], views  # 7.4 -> 8.1 views a landmark when written


def test_keyframe_epipolar_refinement_keeps_the_track_and_its_rotations():
    # `mapping.keyframe_epipolar_weight` (`keyframe_pose.py`): each keyframe after the first map's probation is
    # refined on its landmarks and its matches with the previous keyframe, and the track stays whole.
    from vo_runtime.probation import rotation_angle_deg

    poses = straight_then_turn(60)
    errors, keyframe_poses = {}, {}
    for weight in (0.0, 1.0):
        vo = whole_track_with_mapping(poses, keyframe_epipolar_weight=weight)
        keyframes = vo.map.keyframes
        errors[weight] = np.mean([rotation_angle_deg(
            (b.pose_cw[:3, :3] @ a.pose_cw[:3, :3].T).T
            @ (np.linalg.inv(poses[b.frame]) @ poses[a.frame])[:3, :3]) for a, b in zip(keyframes, keyframes[1:])])
        keyframe_poses[weight] = {k.frame: k.pose_cw for k in keyframes}
    shared = set(keyframe_poses[0.0]) & set(keyframe_poses[1.0])
    assert any(not np.allclose(keyframe_poses[0.0][f], keyframe_poses[1.0][f], atol=1e-9) for f in shared)
    # points all over the view leave no rotation to trade for a translation: no gain to find (0.031 deg either
    # way when written), and none lost
    assert errors[1.0] <= 1.1 * errors[0.0], errors
