"""The second opinion on a refined pose (`vo_runtime/pose.py` `second_opinion`): PnP RANSAC on every match when
the refinement jumped away from the prediction and explains few matches, and nothing otherwise."""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from vo_runtime.config import VOConfig
from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import camera_centre
from vo_runtime.mapping import MappingConfig
from vo_runtime.pose import ransac_pose, refine_pose, second_opinion

FOCAL = 450.0
THRESHOLD = 3.0 / FOCAL


def pose_at(centre, yaw_deg: float) -> np.ndarray:
    rotation = cv2.Rodrigues(np.array([0.0, np.radians(yaw_deg), 0.0]))[0]
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, -rotation @ np.asarray(centre, float)
    return pose


def project(world: np.ndarray, pose: np.ndarray, noise_px: float, rng: np.random.Generator) -> np.ndarray:
    cam = world @ pose[:3, :3].T + pose[:3, 3]
    return cam[:, :2] / cam[:, 2:3] + rng.normal(0.0, noise_px / FOCAL, (len(world), 2))


@pytest.fixture
def scene():
    """70 matches of a frame 0.25 units (one frame's travel) from the last: 46 agree with the true pose, 24 with a
    pose that barely moved (wrong matches that happen to agree, as in the dark EuRoC frame this models)."""
    rng = np.random.default_rng(0)
    z = rng.uniform(3.0, 9.0, 70)
    world = np.c_[rng.uniform(-0.5, 0.5, 70) * z, rng.uniform(-0.3, 0.3, 70) * z, z]
    truth, wrong = pose_at([0.25, 0.0, 0.0], 1.2), pose_at([0.01, 0.0, 0.0], 2.9)
    image = np.r_[project(world[:46], truth, 0.5, rng), project(world[46:], wrong, 0.5, rng)]
    return world, image, truth, wrong


def explained(world, image, pose) -> int:
    cam = world @ pose[:3, :3].T + pose[:3, 3]
    return int(np.count_nonzero(np.linalg.norm(cam[:, :2] / cam[:, 2:3] - image, axis=1) < THRESHOLD))


def test_a_refinement_in_the_wrong_basin_is_replaced_by_the_pose_most_matches_agree_with(scene):
    world, image, truth, wrong = scene
    prediction = pose_at([0.25, 0.0, 0.0], 1.0)
    fit = refine_pose(world[46:], image[46:], wrong, THRESHOLD, 20)  # what the gated refinement slid to
    assert fit is not None and explained(world, image, fit[0]) < 0.6 * 70
    checked = second_opinion(world, image, prediction, fit, THRESHOLD, 20, speed=0.25, max_jump=0.75, min_share=0.6)
    assert checked is not fit
    assert explained(world, image, checked[0]) >= 45
    assert np.linalg.norm(camera_centre(checked[0]) - camera_centre(truth)) < 0.05


@pytest.mark.parametrize("speed, min_share", [(1.0, 0.6), (0.25, 0.3)])
def test_a_fit_near_its_start_or_explaining_enough_is_kept_as_it_is(scene, speed, min_share):
    # A jump of 0.24 is under 0.75 x a speed of 1.0; 24 of 70 explained is above a 0.3 share.
    world, image, truth, wrong = scene
    prediction = pose_at([0.25, 0.0, 0.0], 1.0)
    fit = refine_pose(world[46:], image[46:], wrong, THRESHOLD, 20)
    assert second_opinion(world, image, prediction, fit, THRESHOLD, 20, speed=speed, max_jump=0.75,
                          min_share=min_share) is fit


@pytest.mark.parametrize("floor, replaced", [(0.0, False), (0.3, False), (0.4, True)])
def test_a_fit_that_stayed_near_its_start_is_checked_only_below_the_floor(scene, floor, replaced):
    # The refinement started at the wrong pose itself (no jump) and explains 24 of 70 matches (0.34): the
    # jump rule leaves it; a floor above that share asks RANSAC, which finds the 46 the true pose explains.
    world, image, truth, wrong = scene
    fit = refine_pose(world[46:], image[46:], wrong, THRESHOLD, 20)
    checked = second_opinion(world, image, wrong, fit, THRESHOLD, 20, speed=0.25, max_jump=0.75, min_share=0.6,
                             floor_share=floor)
    assert (checked is not fit) == replaced
    if replaced:
        assert explained(world, image, checked[0]) >= 45
        assert np.linalg.norm(camera_centre(checked[0]) - camera_centre(truth)) < 0.05


def test_no_better_pose_keeps_the_fit(scene):
    world, _, _, wrong = scene
    rng = np.random.default_rng(1)
    image = project(world, wrong, 0.5, rng)
    image[:40] = rng.uniform(-0.5, 0.5, (40, 2))  # 40 wrong matches, scattered: nothing explains more than 30
    fit = refine_pose(world[40:], image[40:], wrong, THRESHOLD, 20)
    checked = second_opinion(world, image, pose_at([0.25, 0.0, 0.0], 1.0), fit, THRESHOLD, 20, speed=0.25,
                             max_jump=0.75, min_share=0.6)
    assert checked is fit


def test_the_check_settings_are_validated():
    with pytest.raises(VORuntimeError, match="pose_check"):
        VOConfig(pose_check_share=1.5)
    with pytest.raises(VORuntimeError, match="pose_check"):
        VOConfig(pose_check_jump=0.0)
    with pytest.raises(VORuntimeError, match="pose_check"):
        VOConfig(pose_check_floor=0.6)  # above pose_check_share
    with pytest.raises(VORuntimeError, match="pose_check"):
        VOConfig(pose_check_floor=-0.1)


@pytest.fixture(scope="module")
def centroid3_artefact(tmp_path_factory) -> Path:
    """The drone camera's artefact as it was when the case below was found: the same weights, each peak placed by
    its 3x3 centroid (the shipped one uses 5x5, and no longer meets the wrong basin there)."""
    from toolkit.cli import main

    directory = tmp_path_factory.mktemp("centroid3") / "artefact"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", "slim-relu", "--input-size", "480x752",
                 "--max-keypoints", "512", "--refine", "centroid", "-o", str(directory)]) == 0
    return directory


@pytest.mark.parametrize("artefact, check", [("3x3", True), ("3x3", False), ("shipped", True), ("shipped", False)])
def test_the_dark_mid_flight_start_keeps_its_direction_only_with_the_check(shared_data, centroid3_artefact,
                                                                            artefact, check):
    """The real case (docs/vo_takeoff.md, "Mid-flight, found"): the drone clip from frame 100 in the dark. Over its
    first 20 tracked frames the travel direction stays within 25 deg of the ground truth's with the check; without
    it, with the 3x3-centroid artefact it was found with, the first tracked frame slides into the wrong basin and
    the direction is off by 60-90 deg. The shipped artefact kept the direction without the check too (6 deg) until
    young landmarks were weighted down (`VOConfig.landmark_variance`): every landmark of a first map is young, which
    flattens the score weights there, and without the check it now slides part way (33 deg)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/ is a folder of scripts
    from bench.eval_vo import LIGHTS
    from vo_runtime import VisualOdometry
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import frame_size, open_sequence
    from vo_runtime.evaluate import sequence_groundtruth
    from vo_runtime.features import to_gray_u8
    from vo_runtime.sequence import read_frames
    from vo_runtime.states import TRACKING

    start, count = 100, 30
    sequence = open_sequence(shared_data / "euroc_mh05_f000000-000199")
    truth = sequence_groundtruth(sequence).poses_se3[start:start + count]
    height, width = frame_size(sequence.camera, sequence.frames)
    # the travel check off: it would notice the wrong basin too, later (this test is the pose check's); and the
    # baseline rule off, as when the case was found: its first map's fewer young landmarks keep the 3x3 run in
    # the right basin without the check too (5 deg)
    config = VOConfig(pose_check=check, travel_check_gap=0, mapping=MappingConfig(min_baseline_depth=0.0))
    vo = VisualOdometry(centroid3_artefact if artefact == "3x3" else default_artefact(width, height), sequence.camera,
                        config)
    for i, image in enumerate(read_frames(sequence.frames[start:start + count])):
        vo.track(LIGHTS["low"](to_gray_u8(image), seed=start + i), sequence.timestamps[start + i])
    vo.finish()
    tracked = [r.index for r in vo.results if r.status == TRACKING]
    first, last = tracked[0], tracked[min(20, len(tracked) - 1)]
    estimated = vo.results[last].pose[:3, 3] - vo.results[first].pose[:3, 3]  # camera-to-world poses
    true = truth[last][:3, 3] - truth[first][:3, 3]
    # Directions in the first tracked frame's camera, where both trajectories start.
    estimated = vo.results[first].pose[:3, :3].T @ estimated
    true = truth[first][:3, :3].T @ true
    cos = estimated @ true / (np.linalg.norm(estimated) * np.linalg.norm(true))
    error_deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    if check:
        assert error_deg < 25.0
    else:
        assert error_deg > (45.0 if artefact == "3x3" else 25.0)


def test_ransac_on_a_collapsed_cloud_is_no_pose_not_a_crash():
    """A map whose scale collapsed holds its landmarks within a hundred-thousandth of the view's extent; OpenCV's
    SQPnP asserts on such a cloud (it crashed the VO on a long dark flight). The fit is then simply missing."""
    rng = np.random.default_rng(0)
    scene = np.c_[rng.uniform(-2, 2, 46), rng.uniform(-1.5, 1.5, 46), rng.uniform(4, 10, 46)]
    image = scene[:, :2] / scene[:, 2:]
    collapsed = np.array([-1.9, 0.2, -0.12]) + 1e-5 * (scene - scene.mean(axis=0))
    with pytest.raises(cv2.error):  # what OpenCV does with it, so this test keeps checking the guard
        cv2.solvePnPRansac(collapsed, image, np.eye(3), None, iterationsCount=100, reprojectionError=THRESHOLD,
                           confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    assert ransac_pose(collapsed, image, THRESHOLD, 20) is None
    fit = ransac_pose(scene, image, THRESHOLD, 20)  # the same views of the scene at its size: found
    assert fit is not None and fit[1].all()
    np.testing.assert_allclose(fit[0], np.eye(4), atol=1e-6)


def test_tums_dark_draws_keep_no_pose_that_explains_under_a_fifth_of_its_matches(shared_data):
    """The floor on real frames (docs/vo_euroc.md, "A fifth of the matches"): TUM fr2 desk in the dark preset,
    noise draws 2 and 5, where the refinement alone left frame 7 explaining 34 of 226 and 24 of 266 guided matches
    (on the 2-core AVX2 dev machine; draw 5's map then ran at half scale). With the floor every pose tracked on
    the local map explains at least a fifth of its matches, and draw 5 ends within 2 cm."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/ is a folder of scripts
    from bench.eval_vo import run_one
    from vo_runtime.artefact import default_artefact

    sequence = shared_data / "tum_fr2_desk_snippet"
    for draw in (2, 5):
        row = run_one(sequence, "artefact", "low", 2000, VOConfig(), default_artefact(640, 480), None, seed=draw)
        on_the_map = [r for r in row["_results"] if r.tracked_by in ("local map", "wide search")]
        assert len(on_the_map) >= 15
        assert all(r.num_inliers >= 0.2 * r.num_matches for r in on_the_map), draw
        if draw == 5:
            assert row["ate"] < 0.02
