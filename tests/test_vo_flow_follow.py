"""Landmarks the detector missed, followed from the previous frame by optical flow (`flow_follow.py`,
``VOConfig.flow_window_px``): the flow on a texture moved by a known sub-pixel shift, what is and is not added to
a tracked frame, and the VO on the drone clip in the dark."""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from vo_runtime import VOConfig, VORuntimeError
from vo_runtime.flow_follow import FlowFollow, flow, follow_missed_landmarks
from vo_runtime.geometry import make_pose
from vo_runtime.localmap import Keyframe, LocalMap
from vo_runtime.tracking import FrameData, TrackOutcome

FOCAL, CENTRE, DEPTH = 400.0, np.array([160.0, 120.0]), 5.0
SHIFT = np.array([2.3, -1.6])  # frame pixels the scene moves from the previous frame to this one


def texture(seed: int = 0, size=(240, 320)) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0, 255, size).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3.0 - 255.0, 0, 255).astype(np.uint8)


def shifted(image: np.ndarray, shift: np.ndarray) -> np.ndarray:
    move = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(image, move, image.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def normalise(pixels: np.ndarray) -> np.ndarray:
    return (np.asarray(pixels, np.float64) - CENTRE) / FOCAL


def test_flow_finds_a_texture_moved_by_a_sub_pixel_shift():
    before = texture()
    after = shifted(before, SHIFT)
    start = np.random.default_rng(1).uniform([20, 20], [300, 220], size=(60, 2))
    positions, found = flow(before, after, start, 15, 0.5)
    assert found.all()
    error = np.linalg.norm(positions - (start + SHIFT), axis=1)
    assert error.max() < 0.1  # a tenth of a pixel: far below the pose gate


def test_flow_refuses_flat_patches_and_points_leaving_the_frame():
    before = texture()
    before[:, :100] = 90  # no structure to follow
    after = shifted(before, np.array([6.0, 0.0]))
    start = np.array([[50.0, 120.0], [317.0, 120.0], [200.0, 120.0]])  # flat; leaves the frame; textured
    positions, found = flow(before, after, start, 15, 0.5)
    assert found.tolist() == [False, False, True]
    np.testing.assert_allclose(positions[2], [206.0, 120.0], atol=0.1)
    assert flow(before, after, np.zeros((0, 2)), 15, 0.5)[1].shape == (0,)


def scene(count: int = 40, seed: int = 2):
    """Landmarks on a wall at DEPTH seen by the previous frame (at the origin) and by this frame, whose camera
    moved so that the wall's image moves by SHIFT. Returns the map, the previous frame and its landmark column,
    this frame's pose and the landmarks' pixels in this frame."""
    rng = np.random.default_rng(seed)
    previous_px = rng.uniform([30, 30], [290, 210], size=(count, 2))
    world = np.c_[normalise(previous_px) * DEPTH, np.full(count, DEPTH)]
    pose_cw = make_pose(np.eye(3), np.r_[SHIFT / FOCAL * DEPTH, 0.0])
    local_map = LocalMap(8)
    descriptors = rng.normal(size=(count, 8)).astype(np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    local_map.add_keyframe(Keyframe(0, np.eye(4), normalise(previous_px), previous_px, descriptors,
                                    np.full(count, -1, np.int64)))
    local_map.add_landmarks(world, [(0, np.arange(count))], np.full(count, 5.0))
    previous = FrameData.build(normalise(previous_px), previous_px, descriptors)
    return local_map, previous, np.arange(count), pose_cw, previous_px + SHIFT


def test_missed_landmarks_are_added_where_the_flow_and_the_pose_agree():
    local_map, previous, previous_landmark, pose_cw, truth_px = scene()
    before = texture()
    after = shifted(before, SHIFT)
    # This frame's detector found the even landmarks (a little off); landmark 1 was culled, and landmark 3's
    # position is wrong by 12 px in this frame's view: the pose does not explain the flow there.
    found_px = truth_px[::2] + 0.3
    frame = FrameData.build(normalise(found_px), found_px, previous.descriptors[::2] * 1.0)
    frame.sigma = np.ones(len(found_px))
    outcome = TrackOutcome(pose_cw, np.arange(0, 40, 2), 20, 20, "local map")
    local_map.kill(np.array([1]))
    local_map.positions[3] += [12.0 / FOCAL * DEPTH, 0.0, 0.0]
    found_before = local_map.found[:40].copy()
    settings = FlowFollow(window_px=15, check_px=0.5, threshold_px=3.0, sigma=1.5)
    added = follow_missed_landmarks(local_map, previous, previous_landmark, before, frame, after, outcome,
                                    normalise, FOCAL, settings)
    expected = [i for i in range(1, 40, 2) if i not in (1, 3)]
    assert added == len(expected)
    assert outcome.landmark[20:].tolist() == expected
    np.testing.assert_allclose(frame.pixels[20:], truth_px[expected], atol=0.1)
    np.testing.assert_allclose(frame.points, normalise(frame.pixels))
    np.testing.assert_array_equal(frame.descriptors[20:], local_map.descriptors[expected])
    assert frame.sigma[20:].tolist() == [1.5] * added and frame.tree.n == 20 + added
    assert (local_map.found[expected] == found_before[expected] + 1).all() and local_map.found[3] == found_before[3]
    # a second call finds nothing more to follow: every live landmark the previous frame saw is matched now
    assert follow_missed_landmarks(local_map, previous, previous_landmark, before, frame, after, outcome,
                                   normalise, FOCAL, settings) == 0


def test_flow_settings_are_checked():
    assert VOConfig().flow_window_px == 0  # off by default: its cost breaks the drone camera's 30 FPS on one core
    for bad in (dict(flow_window_px=-1), dict(flow_check_px=0.0), dict(flow_sigma=0.0)):
        with pytest.raises(VORuntimeError):
            VOConfig(**bad)


def test_the_dark_drone_clip_keeps_more_landmarks_with_the_flow_once_the_first_map_is_not_young(shared_data):
    """Frames 100-199 of the drone clip in the global dark preset. While the first map is young (within
    `young_map_lost_frames` of its first keyframe) the flow stays off, so both runs are identical there; after it
    each tracked frame carries more landmarks (the dark keypoints come and go), nothing is lost, and the run stays
    on the ground truth."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/ is a folder of scripts
    from bench.eval_vo import lit_frame
    from vo_runtime import VisualOdometry
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import frame_size, open_sequence
    from vo_runtime.evaluate import evaluate, sequence_groundtruth
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "euroc_mh05_f000000-000199")
    height, width = frame_size(sequence.camera, sequence.frames)
    images = [lit_frame(image, "low", 100, i) for i, image in enumerate(read_frames(sequence.frames[100:200]))]
    runs = {}
    for window in (0, 15):
        vo = VisualOdometry(default_artefact(width, height), sequence.camera, VOConfig(flow_window_px=window))
        for i, image in enumerate(images):
            vo.track(image, sequence.timestamps[100 + i])
        vo.finish()
        assert all(r.status in ("initialising", "tracking") for r in vo.results)
        runs[window] = vo
    young = VOConfig().young_map_lost_frames  # the first map's first keyframe is at or after frame 0
    assert runs[0].results[young].status == "tracking"
    for off, on in zip(runs[0].results[:young], runs[15].results[:young]):  # (poses move later with the map)
        assert (off.status, off.num_landmarks, off.num_inliers, off.keyframe) == \
            (on.status, on.num_landmarks, on.num_inliers, on.keyframe)
    landmarks = {w: np.mean([r.num_landmarks for r in vo.results[2 * young:]]) for w, vo in runs.items()}
    assert landmarks[15] > 1.3 * landmarks[0]
    report = evaluate(runs[15].results, sequence_groundtruth(sequence), sequence.layout, sequence.timestamps[100:])
    assert report["ate_rmse_m"] < 0.03


def test_a_keyframe_is_due_when_the_detector_finds_too_little_of_the_map_whatever_the_flow_follows():
    """`keyframe_min_tracked` counts the landmarks at detections: followed ones cannot found new landmarks, and on
    the car a map tracked mostly by the flow went without the keyframes its forward motion needs."""
    from types import SimpleNamespace

    from vo_runtime.keyframing import KeyframeUpkeep

    local_map = LocalMap(8)
    for number in range(2):  # the reference keyframe holds no established landmarks: only the count can speak
        local_map.add_keyframe(Keyframe(number, np.eye(4), np.zeros((0, 2)), np.zeros((0, 2)),
                                        np.zeros((0, 8), np.float32), np.zeros(0, np.int64)))
    upkeep = SimpleNamespace(config=VOConfig(), map=local_map, _reference_kf=1)
    due = lambda tracked, detected=None: KeyframeUpkeep._needs_keyframe(upkeep, 2, tracked, detected)  # noqa: E731
    assert not due(200) and not due(200, 100)
    assert due(200, 50) and due(50)
    assert KeyframeUpkeep._needs_keyframe(upkeep, 5, 200, 100)  # keyframe_max_gap still counts


def test_the_travel_check_still_finds_a_broken_first_map_the_flow_follows(shared_data):
    """The onboard take-off from frame 0, noise draw 5: its first map goes wrong in the turn and the travel check
    discards it (frame 71). When the check also judged the flow's points, which sit where the broken map said to
    look, it sided with the map: nothing was discarded and the run ended 1.7 m off. The run is chaotic in the
    CPU's arithmetic: on an AVX2 core (onnxruntime computes otherwise than on the AVX-512 core it was found on)
    draw 5's map is lost young instead, and draw 2's is the one the check discards (frame 46)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/ is a folder of scripts
    from bench.eval_vo import lit_frame
    from vo_runtime import VisualOdometry
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import frame_size, open_sequence
    from vo_runtime.evaluate import evaluate, sequence_groundtruth
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "euroc_mh05_f000000-000199")
    height, width = frame_size(sequence.camera, sequence.frames)
    images = list(read_frames(sequence.frames))
    for draw in (5, 2):
        vo = VisualOdometry(default_artefact(width, height), sequence.camera, VOConfig(flow_window_px=15))
        for i, image in enumerate(images):
            vo.track(lit_frame(image, "onboard", 0, i, draw), sequence.timestamps[i])
        vo.finish()
        dropped = [r.index for r in vo.results if r.map_dropped]
        if any(vo.results[i].problem.startswith("map discarded: its direction of travel") for i in dropped):
            break
    assert len(dropped) == 1 and 40 < dropped[0] < 120
    assert vo.results[dropped[0]].problem.startswith("map discarded: its direction of travel")
    report = evaluate(vo.results, sequence_groundtruth(sequence), sequence.layout, sequence.timestamps)
    assert report["ate_rmse_m"] < 0.1
