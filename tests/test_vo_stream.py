"""`MonoVO.stream`: extraction on a worker thread ahead of the tracking gives the poses, states and skips of
frame-by-frame `process`, in order, on real KITTI frames."""
from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from vo_runtime import CalibrationError, FrameError, MonoVO, OrbExtractor, StreamFrame, VOConfig, VORuntimeError
from vo_runtime.odometry import SKIPPED, TRACKED_STATES


@pytest.fixture(scope="module")
def kitti(shared_data):
    from vo_runtime.datasets import open_sequence
    from vo_runtime.sequence import read_frames

    sequence = open_sequence(shared_data / "kitti_odom06_f000000-000050")
    return sequence, list(read_frames(sequence.frames[:24]))


def _unreadable() -> np.ndarray:
    raise FrameError("cannot decode image")


@pytest.mark.parametrize("features", ["orb", "artefact"])
def test_stream_tracks_like_process_with_the_network_ahead(kitti, features):
    from vo_runtime.artefact import default_artefact
    from vo_runtime.features import FeatureExtractor

    sequence, frames = kitti
    extractor = OrbExtractor(1000) if features == "orb" else FeatureExtractor(default_artefact())
    reference = MonoVO(extractor, sequence.camera)
    for image, stamp in zip(frames, sequence.timestamps):
        reference.process(image, stamp)
    assert sum(r.status in TRACKED_STATES for r in reference.results) >= 12
    for ahead, mapping_thread in ((0, False), (1, False), (3, True)):
        vo = MonoVO(extractor, sequence.camera, VOConfig(mapping_thread=mapping_thread))
        yielded = [r.index for r in vo.stream(zip(frames, sequence.timestamps), ahead=ahead)]
        vo.finish()
        assert yielded == list(range(len(frames)))  # every frame, in order
        np.testing.assert_array_equal(np.stack([r.pose for r in vo.results]),
                                      np.stack([r.pose for r in reference.results]))
        assert [r.status for r in vo.results] == [r.status for r in reference.results]
        assert all(r.extract_ms > 0 for r in vo.results)  # measured on the worker, per frame


def test_stream_skips_bad_frames_as_process_does_and_names_them(kitti):
    sequence, frames = kitti
    small = cv2.resize(frames[16], (320, 96))
    bad = {8: None, 11: _unreadable, 16: small}  # no frame, an unreadable file, another size
    stream = [StreamFrame(bad.get(i, image), sequence.timestamps[i], f"{i:06d}.png") for i, image in enumerate(frames)]

    reference = MonoVO(OrbExtractor(1000), sequence.camera)
    for i, image in enumerate(frames):
        if i == 11:
            reference.skip("unreadable", sequence.timestamps[i])
        elif i == 16:
            with pytest.raises(CalibrationError):
                reference.process(small)
            reference.skip("another size", sequence.timestamps[i])
        else:
            reference.process(bad.get(i, image), sequence.timestamps[i])

    vo = MonoVO(OrbExtractor(1000), sequence.camera)
    results = list(vo.stream(stream, ahead=2, skip_wrong_size=True))
    assert [r.status for r in results] == [r.status for r in reference.results]
    assert [r.index for r in results if r.status == SKIPPED] == [8, 11, 16]
    assert results[11].problem == "000011.png: cannot decode image"
    assert results[16].problem.startswith("000016.png: frame is 320x96")
    np.testing.assert_array_equal(np.stack([r.pose for r in results]), np.stack([r.pose for r in reference.results]))
    assert results[-1].status in TRACKED_STATES

    # Without skip_wrong_size the wrong size is raised where it stands, after the frames before it.
    vo = MonoVO(OrbExtractor(1000), sequence.camera)
    seen = []
    with pytest.raises(CalibrationError):
        for result in vo.stream(stream, ahead=2):
            seen.append(result.index)
    assert seen == list(range(16))


def test_a_consumer_that_stops_early_leaves_no_thread_and_the_vo_usable(kitti):
    sequence, frames = kitti
    before = threading.active_count()
    vo = MonoVO(OrbExtractor(1000), sequence.camera)
    for result in vo.stream(zip(frames, sequence.timestamps), ahead=4):
        if result.index == 5:
            break
    assert threading.active_count() == before
    assert len(vo.results) == 6  # the frames extracted ahead were dropped, not tracked
    assert vo.process(frames[6], sequence.timestamps[6]).index == 6
    with pytest.raises(VORuntimeError, match="ahead"):
        vo.stream(zip(frames, sequence.timestamps), ahead=-1)  # refused at the call, before any frame
