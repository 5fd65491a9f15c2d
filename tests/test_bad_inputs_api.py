"""Bad frames through the embedding API: `FeatureExtractor` raises a typed `FrameError` (never a crash inside
OpenCV or onnxruntime), and `VisualOdometry` skips and flags a frame it cannot use, raises `CalibrationError`
for one of another size without changing anything, and keeps tracking afterwards."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from bad_inputs_support import KITTI_06
from test_vo_odometry import BLANK, CAMERA, SyntheticExtractor, straight_then_turn
from vo_runtime import (CalibrationError, Camera, FeatureExtractor, FrameError, OrbExtractor, VisualOdometry,
                        VORuntimeError)
from vo_runtime.features import to_gray_u8
from vo_runtime.odometry import LOST, SKIPPED, TRACKING

# Frames a camera driver or a decoder could hand over, and why each is unusable.
BAD_FRAMES: dict[str, object] = {
    "none": None,
    "empty": np.zeros((0, 0), np.uint8),
    "one-dimensional": np.zeros(640, np.uint8),
    "two-channels": np.zeros((480, 640, 2), np.uint8),
    "four-dimensional": np.zeros((1, 480, 640, 1), np.uint8),
    "tiny": np.zeros((4, 4), np.uint8),
    "nan": np.full((480, 640), np.nan, np.float32),
    "inf": np.full((480, 640), np.inf, np.float64),
    "bool": np.zeros((480, 640), bool),
    "complex": np.zeros((480, 640), np.complex64),
    "negative-int": np.full((480, 640), -5, np.int16),
}


@pytest.mark.parametrize("name", BAD_FRAMES)
def test_extractors_raise_a_typed_error_for_bad_frames(name, bad_input_assets):
    for extractor in (FeatureExtractor(bad_input_assets.artefact), OrbExtractor(500)):
        with pytest.raises(FrameError):
            extractor(BAD_FRAMES[name])


def test_black_and_16_bit_frames_are_usable(bad_input_assets):
    extractor = FeatureExtractor(bad_input_assets.artefact)
    black = np.zeros((480, 640), np.uint8)
    assert len(extractor(black)) >= 0 and len(OrbExtractor(500)(black)) == 0  # no error, no texture
    frame = cv2.imread(str(sorted((KITTI_06 / "image_0").iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    wide = frame.astype(np.uint16) * 256 + 255  # 16-bit, the same high byte
    np.testing.assert_array_equal(to_gray_u8(wide), frame)
    np.testing.assert_array_equal(extractor(wide).keypoints, extractor(frame).keypoints)
    orb = OrbExtractor(500)
    assert len(orb(wide)) == len(orb(frame)) > 100  # was clipped to white: no features at all


def test_16_bit_png_reads_as_label_reads_it(tmp_path):
    path = tmp_path / "wide.png"
    cv2.imwrite(str(path), np.arange(256 * 256, dtype=np.uint32).reshape(256, 256).astype(np.uint16))
    label_view = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)  # what toolkit label decodes
    np.testing.assert_array_equal(to_gray_u8(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)), label_view)


def test_tracking_resumes_after_bad_frames():
    poses = straight_then_turn(40)
    vo = VisualOdometry(SyntheticExtractor(poses, blackout=frozenset({18})), CAMERA)
    bad_at = {12: "none", 14: "nan", 16: "two-channels", 22: "empty"}
    statuses = []
    for step in range(44):
        if step in bad_at:
            result = vo.track(BAD_FRAMES[bad_at[step]], timestamp=float(step))
            assert result.status == SKIPPED and result.problem
            np.testing.assert_array_equal(result.pose, vo.results[-2].pose)  # the pose is held
        elif step == 20:  # another size: a typed error, and nothing recorded
            count = len(vo.results)
            with pytest.raises(CalibrationError, match="640x480"):
                vo.track(np.zeros((240, 320), np.uint8))
            assert len(vo.results) == count
            continue
        else:
            result = vo.track(BLANK, timestamp=float(step))
        statuses.append(result.status)
    assert len(vo.results) == 43 and [r.index for r in vo.results] == list(range(43))
    assert statuses[11] == TRACKING  # initialised before the first bad frame
    assert statuses[13] == statuses[15] == statuses[17] == TRACKING  # the frame after each bad one is tracked
    assert LOST in statuses[18:]  # the black frame (no features) is lost, as before ...
    assert statuses[-10:] == [TRACKING] * 10  # ... and tracking goes on after it too


def test_a_sizeless_calibration_is_bound_to_the_first_frame():
    camera = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5)  # like a KITTI calib.txt: no image size
    vo = VisualOdometry(SyntheticExtractor(straight_then_turn(5)), camera)
    vo.track(BLANK)
    with pytest.raises(CalibrationError, match="this sequence's frames are 640x480"):
        vo.track(np.zeros((240, 320), np.uint8))
    assert vo.track(BLANK).index == 1
    vo.reset()  # a new sequence may have another size
    assert vo.track(np.zeros((240, 320), np.uint8)).index == 0


def test_wrong_argument_types_are_typed_errors(bad_input_assets):
    vo = VisualOdometry(OrbExtractor(500), CAMERA)
    with pytest.raises(FrameError):
        vo.track("frame.png")
    with pytest.raises(VORuntimeError, match="threads"):
        FeatureExtractor(bad_input_assets.artefact, threads=-1)
