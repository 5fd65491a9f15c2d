"""Metrics of `toolkit eval` on cases with a known answer, plus the readers and the resize convention."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from toolkit.errors import ToolkitError
from toolkit.evaluation.datasets import (parse_homography_file, read_hpatches, resize_with_matrix,
                                         scale_homography)
from toolkit.evaluation.detectors import DetectorConfig, orb_detector, sift_detector
from toolkit.evaluation.metrics import (average_precision, corner_error, descriptor_distances,
                                        evaluate_detections, mutual_nearest_neighbours, warp_points)
from toolkit.evaluation.runner import summarise

SHAPE = (240, 320)


def textured_image(shape: tuple[int, int] = (300, 400), seed: int = 0) -> np.ndarray:
    """Smoothed noise stretched to 0..255: plenty of corners for ORB and SIFT."""
    noise = np.random.RandomState(seed).rand(*shape).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return cv2.normalize(blurred, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def grid_keypoints(spacing: int = 20, margin: int = 30) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(margin, SHAPE[1] - margin, spacing), np.arange(margin, SHAPE[0] - margin, spacing))
    return np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)


def unit_descriptors(count: int, dim: int = 64, seed: int = 1) -> np.ndarray:
    vectors = np.random.RandomState(seed).randn(count, dim).astype(np.float32)
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def test_identical_keypoints_and_descriptors_score_perfectly():
    keypoints = grid_keypoints()
    descriptors = unit_descriptors(len(keypoints))
    metrics, matches = evaluate_detections(keypoints, descriptors, keypoints, descriptors, np.eye(3), SHAPE, SHAPE)
    assert metrics.repeatability == 1.0
    assert metrics.localisation_error == 0.0
    assert metrics.nn_map == pytest.approx(1.0)
    assert metrics.matching_score == pytest.approx(1.0)
    assert metrics.corner_error < 1e-6
    assert len(matches) == len(keypoints)


@pytest.mark.parametrize("make_detector", [orb_detector, sift_detector])
def test_identical_real_images_give_repeatability_one_and_exact_homography(make_detector):
    image = textured_image()[:240, :320]
    detector = make_detector(DetectorConfig(max_keypoints=500))
    detection = detector(image)
    assert len(detection) > 100
    metrics, _ = evaluate_detections(detection.keypoints, detection.descriptors, detection.keypoints,
                                     detection.descriptors, np.eye(3), image.shape, image.shape)
    assert metrics.repeatability == 1.0
    assert metrics.localisation_error == 0.0
    assert metrics.corner_error < 1e-3


def test_known_shift_with_perturbed_keypoints_gives_exact_repeatability_and_mle():
    keypoints_a = grid_keypoints()
    homography = translation(7.0, -5.0)
    keypoints_b = warp_points(keypoints_a, homography)
    # Every other keypoint moves 2 px (still repeated at 3 px), the rest 4 px (not repeated).
    offsets = np.where(np.arange(len(keypoints_b))[:, None] % 2 == 0, [[2.0, 0.0]], [[0.0, 4.0]])
    metrics, _ = evaluate_detections(keypoints_a, unit_descriptors(len(keypoints_a)), keypoints_b + offsets,
                                     unit_descriptors(len(keypoints_a)), homography, SHAPE, SHAPE)
    expected = np.ceil(len(keypoints_a) / 2) / len(keypoints_a)
    assert metrics.repeatability == pytest.approx(expected)
    assert metrics.localisation_error == pytest.approx(2.0)


def test_keypoints_outside_the_shared_view_do_not_count():
    keypoints_a = grid_keypoints()
    homography = translation(25.0, 0.0)   # the grid (x <= 270) stays inside image B
    outside = np.array([[315.0, 100.0], [310.0, 50.0]])   # these land at x >= 335: outside image B
    keypoints_a = np.concatenate([keypoints_a, outside])
    keypoints_b = warp_points(keypoints_a[:-2], homography)
    descriptors = unit_descriptors(len(keypoints_a))
    metrics, _ = evaluate_detections(keypoints_a, descriptors, keypoints_b, descriptors[:-2], homography, SHAPE, SHAPE)
    assert metrics.repeatability == 1.0
    assert metrics.matching_score == pytest.approx(1.0)


def test_real_image_shift_recovers_the_translation(shared_data):
    image = cv2.imread(str(shared_data / "hpatches_v_dogman" / "v_dogman" / "1.ppm"), cv2.IMREAD_GRAYSCALE)
    image_a, image_b = image[100:340, 200:520], image[105:345, 207:527]   # b(x, y) = a(x + 7, y + 5)
    truth = translation(-7.0, -5.0)
    sift = sift_detector(DetectorConfig(max_keypoints=500))
    detection_a, detection_b = sift(image_a), sift(image_b)
    args = (detection_a.keypoints, detection_a.descriptors, detection_b.keypoints, detection_b.descriptors)
    right, _ = evaluate_detections(*args, truth, image_a.shape, image_b.shape)
    wrong, _ = evaluate_detections(*args, np.eye(3), image_a.shape, image_b.shape)
    assert right.repeatability > 0.9 and right.localisation_error < 0.5
    assert right.corner_error < 1.0 and right.matching_score > 0.5
    assert wrong.repeatability < 0.5 * right.repeatability


def test_image_without_keypoints_gives_zeros_not_a_crash():
    flat = np.full(SHAPE, 128, dtype=np.uint8)
    orb = orb_detector(DetectorConfig(max_keypoints=500))
    empty, full = orb(flat), orb(textured_image()[:240, :320])
    assert len(empty) == 0 and len(full) > 0
    for a, b in ((empty, empty), (empty, full), (full, empty)):
        metrics, matches = evaluate_detections(a.keypoints, a.descriptors, b.keypoints, b.descriptors,
                                               np.eye(3), SHAPE, SHAPE)
        assert (metrics.repeatability, metrics.nn_map, metrics.matching_score) == (0.0, 0.0, 0.0)
        assert math.isinf(metrics.corner_error) and math.isnan(metrics.localisation_error)
        assert len(matches) == 0
    summary = summarise([metrics])
    assert summary["homography_5px"] == 0.0 and summary["localisation_error"] is None


def test_hamming_and_l2_distances_match_opencv():
    rng = np.random.RandomState(3)
    binary_a, binary_b = rng.randint(0, 256, (7, 32), dtype=np.uint8), rng.randint(0, 256, (5, 32), dtype=np.uint8)
    hamming = descriptor_distances(binary_a, binary_b)
    expected = [[cv2.norm(a, b, cv2.NORM_HAMMING) for b in binary_b] for a in binary_a]
    np.testing.assert_array_equal(hamming, expected)
    float_a, float_b = rng.randn(7, 128).astype(np.float32), rng.randn(5, 128).astype(np.float32)
    l2 = descriptor_distances(float_a, float_b)
    np.testing.assert_allclose(l2, np.linalg.norm(float_a[:, None] - float_b[None], axis=2), rtol=1e-4)


def test_mutual_nearest_neighbours_keeps_only_mutual_pairs():
    distances = np.array([[0.1, 0.9, 0.8],
                          [0.2, 0.7, 0.9],    # row 1's nearest is column 0, but column 0 prefers row 0
                          [0.9, 0.8, 0.3]])
    np.testing.assert_array_equal(mutual_nearest_neighbours(distances), [[0, 0], [2, 2]])
    assert mutual_nearest_neighbours(np.zeros((0, 4))).shape == (0, 2)


def test_average_precision_by_hand():
    # ranks 1 (hit), 2 (miss), 3 (hit); 3 positives exist: (1/1 + 2/3) / 3
    assert average_precision(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), 3) == pytest.approx(5 / 9)
    assert average_precision(np.array([0.5]), np.array([True]), 0) == 0.0


def test_nn_map_with_some_descriptors_swapped():
    keypoints = grid_keypoints(spacing=40)
    descriptors_a = unit_descriptors(len(keypoints))
    descriptors_b = descriptors_a.copy()
    swapped = 6
    # Keypoints 0..5 trade descriptors in pairs (mostly the partner's): their NN lands 40 px away.
    for i in range(0, swapped, 2):
        descriptors_b[[i, i + 1]] = 0.9 * descriptors_a[[i + 1, i]] + 0.1 * descriptors_a[[i, i + 1]]
    descriptors_b /= np.linalg.norm(descriptors_b, axis=1, keepdims=True)
    metrics, _ = evaluate_detections(keypoints, descriptors_a, keypoints, descriptors_b, np.eye(3), SHAPE, SHAPE)
    # Correct matches have distance 0 and rank first, so AP = #correct / #positives (all keypoints repeat).
    assert metrics.nn_map == pytest.approx((len(keypoints) - swapped) / len(keypoints))
    assert metrics.repeatability == 1.0


def test_corner_error_is_zero_for_the_truth_and_infinite_without_estimate():
    truth = np.array([[1.1, 0.05, 3.0], [0.02, 0.95, -4.0], [1e-4, 0.0, 1.0]])
    assert corner_error(truth, truth, SHAPE) == pytest.approx(0.0)
    assert corner_error(translation(1.0, 0.0) @ truth, truth, SHAPE) == pytest.approx(1.0)
    assert math.isinf(corner_error(None, truth, SHAPE))


def test_resize_matrix_follows_opencv_pixel_centres():
    image = np.zeros((64, 96), dtype=np.float32)
    centre = np.array([37.0, 21.0])
    ys, xs = np.mgrid[:64, :96]
    image[:] = np.exp(-((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / (2 * 3.0 ** 2))
    resized, matrix = resize_with_matrix(image, (32, 48))
    ys, xs = np.mgrid[:32, :48]
    centroid = np.array([(resized * xs).sum(), (resized * ys).sum()]) / resized.sum()
    np.testing.assert_allclose(centroid, warp_points(centre[None], matrix)[0], atol=0.02)
    kept, identity = resize_with_matrix(image, None)
    assert kept is image and np.array_equal(identity, np.eye(3))


def test_scaled_homography_maps_resized_points():
    homography = np.array([[0.9, 0.1, 20.0], [-0.05, 1.1, 5.0], [1e-4, -2e-4, 1.0]])
    _, scale_a = resize_with_matrix(np.zeros((522, 788), np.uint8), SHAPE)
    _, scale_b = resize_with_matrix(np.zeros((400, 600), np.uint8), SHAPE)
    points = np.array([[10.0, 20.0], [700.0, 500.0]])
    expected = warp_points(warp_points(points, homography), scale_b)
    got = warp_points(warp_points(points, scale_a), scale_homography(homography, scale_a, scale_b))
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_homography_files_parse_and_malformed_ones_fail(tmp_path):
    good = tmp_path / "H_good"
    good.write_text("2 0 1\n0 2 3\n0 0 2\n")
    np.testing.assert_allclose(parse_homography_file(good), [[1, 0, 0.5], [0, 1, 1.5], [0, 0, 1]])
    for name, text in (("short", "1 0 0\n0 1 0\n"), ("words", "1 0 0\n0 one 0\n0 0 1\n"), ("singular", "0 0 0\n" * 3)):
        (tmp_path / name).write_text(text)
        with pytest.raises(ToolkitError, match="malformed homography"):
            parse_homography_file(tmp_path / name)
    with pytest.raises(ToolkitError, match="not found"):
        parse_homography_file(tmp_path / "absent")


def test_read_hpatches_on_dogman(shared_data):
    pairs = read_hpatches(shared_data / "hpatches_v_dogman")
    assert [p.name for p in pairs] == [f"v_dogman/1-{k}" for k in range(2, 7)]
    assert {p.group for p in pairs} == {"v"}
    raw = np.loadtxt(shared_data / "hpatches_v_dogman" / "v_dogman" / "H_1_4")
    np.testing.assert_allclose(pairs[2].homography, raw / raw[2, 2])
