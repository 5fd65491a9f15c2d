"""Patch alignment (`vo_runtime/refine.py`): sub-pixel keypoints from image patches, on images with a
known shift and on a real sequence against its ground truth."""
from __future__ import annotations

import cv2
import numpy as np

from vo_runtime.refine import PatchAligner, contrast_normalise

SHIFT = np.array([2.3, -1.7])  # the target image is the source moved by this many pixels (x, y)


def textured_pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A blurred-noise image and the same image moved by SHIFT (bilinear warp, border replicated)."""
    rng = np.random.default_rng(seed)
    source = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 2.0)
    source = cv2.normalize(source, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    move = np.float32([[1, 0, SHIFT[0]], [0, 1, SHIFT[1]]])
    target = cv2.warpAffine(source, move, (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return source, target


def grid_points() -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(40, 281, 20), np.arange(40, 201, 20))
    return np.c_[xs.ravel(), ys.ravel()].astype(np.float64)


def test_alignment_recovers_a_subpixel_shift_from_noisy_detections():
    source, target = textured_pair()
    points = grid_points()
    truth = points + SHIFT
    rng = np.random.default_rng(1)
    detected = truth + rng.uniform(-1.5, 1.5, truth.shape)  # detector noise, as a coarse detector has
    positions, aligned = PatchAligner(window_px=15, max_shift_px=3.0).align(source, target, points, detected)
    assert aligned.mean() > 0.95
    error_before = np.linalg.norm(detected - truth, axis=1)
    error_after = np.linalg.norm(positions[aligned] - truth[aligned], axis=1)
    assert np.median(error_before) > 0.7 and np.median(error_after) < 0.05


def test_a_point_that_would_move_too_far_keeps_its_detection():
    source, target = textured_pair()
    points = grid_points()
    detected = points.copy()  # 2.9 px from where the patch really is
    positions, aligned = PatchAligner(window_px=15, max_shift_px=1.0).align(source, target, points, detected)
    assert not aligned.any()
    np.testing.assert_array_equal(positions, detected)
    positions, aligned = PatchAligner(window_px=15, max_shift_px=4.0).align(source, target, points, detected)
    assert aligned.mean() > 0.95  # the same points with room to move
    assert np.median(np.linalg.norm(positions[aligned] - (points[aligned] + SHIFT), axis=1)) < 0.05


def test_flat_patches_are_not_aligned():
    flat = np.full((240, 320), 90, np.uint8)
    points = grid_points()
    positions, aligned = PatchAligner(window_px=15, max_shift_px=3.0).align(flat, flat, points, points + 0.7)
    assert not aligned.any()
    np.testing.assert_array_equal(positions, points + 0.7)


def test_no_points_is_not_an_error():
    source, target = textured_pair()
    positions, aligned = PatchAligner(15, 3.0).align(source, target, np.zeros((0, 2)), np.zeros((0, 2)))
    assert positions.shape == (0, 2) and aligned.shape == (0,)


def keyframe_epipolar_errors(vo, groundtruth: np.ndarray, camera) -> np.ndarray:
    """Distance (frame pixels) of each landmark's observation in one keyframe from the epipolar line of its
    observation in the next keyframe that sees it, under the ground-truth relative pose."""
    from vo_runtime.mapping import essential_between

    k_inv = np.linalg.inv(camera.matrix)
    errors = []
    for landmark in np.flatnonzero(vo.map.alive[: vo.map.size]).tolist():
        seen = sorted(vo.map.observations[landmark].items())
        for (ka, row_a), (kb, row_b) in zip(seen, seen[1:]):
            frame_a, frame_b = vo.map.keyframes[ka], vo.map.keyframes[kb]
            pose_a = np.linalg.inv(np.vstack([groundtruth[frame_a.frame], [0, 0, 0, 1]]))
            pose_b = np.linalg.inv(np.vstack([groundtruth[frame_b.frame], [0, 0, 0, 1]]))
            fundamental = k_inv.T @ essential_between(pose_a, pose_b) @ k_inv
            line = fundamental @ np.r_[frame_a.pixels[row_a], 1.0]
            errors.append(abs(line @ np.r_[frame_b.pixels[row_b], 1.0]) / np.hypot(line[0], line[1]))
    return np.array(errors)


def test_alignment_makes_the_shipped_artefacts_observations_agree_with_ground_truth(shared_data):
    # KITTI's 1226x370 frames squeezed into the 240x320 artefact: one detector pixel is 3.8 frame pixels wide.
    from vo_runtime import MonoVO, VOConfig
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import open_sequence
    from vo_runtime.features import FeatureExtractor
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "kitti_odom06_f000000-000050")
    groundtruth = np.loadtxt(sequence.groundtruth).reshape(-1, 3, 4)
    frames = list(read_frames(sequence.frames[:25]))
    extractor = FeatureExtractor(default_artefact())
    medians = {}
    for window, normalise in ((0, False), (15, False), (15, True)):
        vo = MonoVO(extractor, sequence.camera, VOConfig(align_window_px=window, align_normalise=normalise))
        for image, stamp in zip(frames, sequence.timestamps):
            vo.process(image, stamp)
        assert vo.results[-1].status == "tracking" and sum(r.keyframe for r in vo.results) >= 4
        medians[window, normalise] = float(np.median(keyframe_epipolar_errors(vo, groundtruth, sequence.camera)))
    assert medians[15, False] < 0.7 * medians[0, False], medians
    assert medians[15, True] < 0.7 * medians[0, False], medians  # contrast-normalised frames align as well


def lit_by_a_moving_light(image: np.ndarray) -> np.ndarray:
    """``image`` under a light that dims across it (gain 1.0 at the left edge to 0.25 at the right, a spot
    seen off-centre) plus a dark offset, as a point crossing the frame of a camera carrying its own light."""
    gain = np.linspace(1.0, 0.25, image.shape[1], dtype=np.float32)[None, :]
    return np.clip(image.astype(np.float32) * gain + 12.0, 0, 255).astype(np.uint8)


def test_contrast_normalisation_removes_gain_and_offset():
    source, _ = textured_pair()
    window = 15
    plain = contrast_normalise(source, window).astype(np.float32)
    dimmed = contrast_normalise(np.clip(0.4 * source.astype(np.float32) + 30, 0, 255).astype(np.uint8), window)
    inner = (slice(window, -window), slice(window, -window))
    difference = np.abs(plain[inner] - dimmed.astype(np.float32)[inner])
    assert np.median(difference) <= 2 and np.percentile(difference, 99) <= 12  # 8-bit rounding of the dimmed one
    assert plain[inner].std() > 25  # the structure is kept: not a flat image


def test_normalised_frames_align_under_a_light_that_moves_with_the_camera():
    source, target = textured_pair()
    target = lit_by_a_moving_light(target)
    points = grid_points()
    truth = points + SHIFT
    detected = truth + np.random.default_rng(1).uniform(-1.5, 1.5, truth.shape)
    aligner = PatchAligner(window_px=15, max_shift_px=3.0)

    def median_error(source_image: np.ndarray, target_image: np.ndarray) -> float:
        positions, aligned = aligner.align(source_image, target_image, points, detected)
        return float(np.median(np.linalg.norm(np.where(aligned[:, None], positions, detected) - truth, axis=1)))

    raw = median_error(source, target)
    normalised = median_error(contrast_normalise(source, 15), contrast_normalise(target, 15))
    assert normalised < 0.1 and raw > 2 * normalised


def test_with_alignment_new_landmarks_pass_the_aligned_parallax_gate(shared_data):
    # The shipped 240x320 artefact on KITTI aligns its keypoints, so mapping gates new landmarks by
    # aligned_min_parallax_px; without alignment the same run gates by min_parallax_px.
    from vo_runtime import MonoVO, VOConfig
    from vo_runtime.artefact import default_artefact
    from vo_runtime.datasets import open_sequence
    from vo_runtime.features import FeatureExtractor
    from vo_runtime.mapping import MappingConfig
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "kitti_odom06_f000000-000050")
    frames = list(read_frames(sequence.frames[:16]))
    extractor = FeatureExtractor(default_artefact())

    def landmarks_after_initialisation(window: int, mapping: MappingConfig) -> int:
        vo = MonoVO(extractor, sequence.camera, VOConfig(align_window_px=window, mapping=mapping))
        counts = []
        for image, stamp in zip(frames, sequence.timestamps):
            vo.process(image, stamp)
            counts.append(vo.map.size if vo.map is not None else 0)
        first = next(c for c in counts if c > 0)
        assert sum(r.keyframe for r in vo.results) >= 3
        return max(counts) - first  # culling only shrinks the map: growth is new landmarks

    closed = MappingConfig(aligned_min_parallax_px=1e9)  # no ray pair is that far apart
    assert landmarks_after_initialisation(15, closed) == 0
    assert landmarks_after_initialisation(15, MappingConfig()) > 100
    assert landmarks_after_initialisation(0, closed) > 100  # not aligned: the other gate
