"""`MonoVO` / `VisualOdometry`: a monocular visual odometry on top of any keypoint extractor.

States of a frame (``VOResult.status``), and what moves between them:

- ``initialising``: no map yet. Keypoints are matched frame to frame into tracks (`tracks.py`); once the
  tracks from the reference frame have moved far enough, a homography or an essential matrix (whichever
  scores better, `twoview.py`) gives the relative pose, and the triangulated points become the first
  landmarks, observed by two keyframes, once their rays are far enough apart (median
  ``VOConfig.init_min_median_deg``). The first baseline sets the unit (``VOConfig.initial_baseline``).
  The first map is on probation for ``VOConfig.probation_frames`` tracked frames (`probation.py`): when the
  rotations it tracks disagree with the rotations the frames' own matches give, it is discarded, its frames
  go back to ``initialising`` (``problem`` says why on the frame that discarded it), and a new map is built.
  With ``VOConfig.travel_check_gap``, a map whose direction of travel the frames' own geometry contradicts
  (`travel_check.py`) is abandoned: that frame is ``lost`` and a new map is built as after a loss (a young first
  map, with ``VOConfig.young_map_travel``, is discarded instead, as after a young map's loss below).
- ``tracking``: the pose predicted by a constant-velocity model projects the local map (landmarks of the
  reference keyframe and its covisible keyframes) into the frame; guided matching and a robust refinement
  give the pose, with a wider search and then the previous frame as fallbacks (`tracking.py`;
  ``VOResult.tracked_by`` says which). A frame becomes a keyframe when it tracks too small a share of the
  reference keyframe's landmarks, or after ``keyframe_max_gap`` frames; a keyframe adds landmarks,
  runs the local bundle adjustment over keyframes and culls bad landmarks (`mapping.py`), inline or, with
  ``VOConfig.mapping_thread``, on a worker thread while the next frame is extracted (`background.py`).
- ``lost``: every search failed (or the frame had too few features). The pose is held; the next frames
  are tracked against the local map from the motion model while the last tracked frame is at most
  ``lost_predict_frames`` back (-> ``tracking``), then try to relocalise against recent keyframes
  (`relocalise.py`) -> ``relocalised``, and after
  ``relocalise_frames`` failed tries also start a fresh two-view initialisation, scaled by the speed
  measured before the loss -> ``reinitialised`` (a new map; the old one is dropped). A first map lost within
  ``VOConfig.young_map_lost_frames`` of its first keyframe is instead discarded as a failed probation is: its frames
  go back to ``initialising`` and the next map is a first map (`map_lifecycle.py`).
- ``skipped``: the frame could not be used (None, empty, an unusable shape or dtype, NaN/inf:
  `check_frame`); the pose is held, ``problem`` says why, and the next frame is tracked as if it had not
  arrived. A frame whose size contradicts the calibration (or, for a calibration without a size, the first
  frame's size) raises `CalibrationError` and changes nothing.

Poses are camera-to-world 4x4 matrices; the world is the first frame's camera (x right, y down, z forward),
in units of the first baseline (monocular VO cannot observe metric scale). A frame's pose is stored
relative to its reference keyframe, so frames reported earlier follow when bundle adjustment moves it.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from vo_runtime.background import Background
from vo_runtime.camera import Camera
from vo_runtime.config import Extraction, VOConfig, VOResult
from vo_runtime.errors import CalibrationError, VORuntimeError
from vo_runtime.features import FeatureExtractor, Features, detector_pixel, keypoint_sigma, to_gray_u8
from vo_runtime.flow_follow import FlowFollowing
from vo_runtime.frame_intake import FrameIntake
from vo_runtime.geometry import camera_centre, invert_pose
from vo_runtime.initialiser import Initialiser
from vo_runtime.keyframing import KeyframeUpkeep
from vo_runtime.localmap import LocalMap
from vo_runtime.map_lifecycle import MapLifecycle
from vo_runtime.probation import MapProbation
from vo_runtime.refine import PatchAligner, align_to_map, contrast_normalise
from vo_runtime.relocalise import relocalise
from vo_runtime.single_caller import SingleCaller, single_caller
from vo_runtime.states import (INITIALISING, LOST, REINITIALISED, RELOCALISED, SKIPPED,  # noqa: F401 (public names)
                               TRACKED_STATES, TRACKING)
from vo_runtime.tracking import RELOCALISATION, FrameData, TrackingSettings, guided_pose, refit_pose, track_frame
from vo_runtime.travel_check import TravelCheck



class MonoVO(FrameIntake, MapLifecycle, KeyframeUpkeep, FlowFollowing):
    """Monocular VO over a stream of frames.

    Args:
        extractor: callable image -> `Features` (e.g. `FeatureExtractor` on an artefact, or `OrbExtractor`).
        camera: intrinsics of the frames passed to `process`.
        config: `VOConfig`; the defaults suit 10 Hz driving and hand-held indoor sequences.
    """

    def __init__(self, extractor: Callable[[np.ndarray], Features], camera: Camera, config: VOConfig | None = None):
        if not callable(extractor):
            raise VORuntimeError(f"the extractor must be callable (image -> Features), got {type(extractor).__name__}")
        if not isinstance(camera, Camera):
            raise CalibrationError(f"camera must be a vo_runtime.Camera (see load_camera), got {type(camera).__name__}")
        if config is not None and not isinstance(config, VOConfig):
            raise VORuntimeError(f"config must be a VOConfig, got {type(config).__name__}")
        self.extractor = extractor
        self.camera = camera
        self.config = config or VOConfig()
        self._background = Background()
        self._caller = SingleCaller(type(self).__name__)  # one thread at a time in the state-changing calls
        self.reset()

    @single_caller
    def reset(self) -> None:
        """Forget the map and the trajectory; the next frame becomes the origin."""
        self._background.wait()
        self._mapping_job: Callable[[], None] | None = None  # a keyframe's mapping, for the worker thread
        self.results: list[VOResult] = []
        self._poses_cw: list[np.ndarray] = []        # world-to-camera, one per processed frame
        cfg = self.config
        match = (cfg.travel_check_match_distance, cfg.match_ratio) if cfg.travel_check_match_distance > 0 else None
        self._travel = TravelCheck(cfg.travel_check_gap, cfg.travel_check_max_deg, cfg.travel_check_consistency_deg,
                                   cfg.travel_check_frames, cfg.travel_check_min_inliers, match)
        self._forget_map()
        self._lost_tries = 0
        self._focal = self.camera.focal              # pixels per normalised unit, in the detector's pixels
        self._initialiser = Initialiser(self.config, self._focal)
        self._probation = MapProbation(cfg.probation_frames, cfg.probation_max_deg, cfg.probation_max_discards,
                                       cfg.match_max_distance, cfg.match_ratio)
        self._frame_size: tuple[int, int] | None = None  # (height, width) of the frames, fixed by the first one
        self._aligner: PatchAligner | None = None    # patch alignment, set up on the first frame
        self._detection_scale = 1.0                  # threshold pixels per raw detection's pixel (alignment)
        self._mapping_config = cfg.mapping           # the mapping's gates; aligned runs swap the parallax gate
        self.last_observations: tuple[np.ndarray, np.ndarray | None] | None = None  # see `observations`

    def _forget_map(self) -> None:
        """No map, no motion: the state before the first initialisation (`reset`, and a map that failed its
        probation)."""
        self._anchors: dict[int, list[tuple[int, np.ndarray]]] = {}  # keyframe -> (frame, frame-from-keyframe)
        self.map: LocalMap | None = None
        self._map_is_first = False                   # the map is the run's first (not a re-initialisation)
        self._reference_kf = -1                      # keyframe the current frames are tracked from
        self._local_ids = np.zeros(0, np.int64)      # landmarks of the local map (cached per reference)
        self._previous: tuple[FrameData, np.ndarray] | None = None  # last tracked frame and its landmarks
        self._last_tracked = -1
        self._lost_since = -1                        # first frame of the current loss (-1: not lost)
        self._velocity = np.eye(4)                   # last inter-frame motion (world-to-camera increment)
        # World units per frame of the latest `speed_frames` tracked frames (or the first map's baseline):
        # the scale of a re-initialisation (`_speed`); empty before any map.
        self._speeds: deque[float] = deque(maxlen=self.config.speed_frames)
        # (frame, speed) of the latest tracked frames: a re-initialisation after an abandoned map takes its scale
        # from the frames before those that judged it broken (`_abandon_map`).
        self._speed_log: deque[tuple[int, float]] = deque(maxlen=3 * self.config.speed_frames)
        self._travel.clear()
        self._lost_map: LocalMap | None = None       # the map a re-initialisation replaced (`_merge_lost_map`)
        self._merge_tries = 0                        # keyframes of the new map left to look for it
        self._lost_keyframes: list[int] = []         # the lost map's keyframes it looks for, newest first
        self._merge_candidate: float | None = None   # the scale the last keyframe found it at (None: not found)

    @property
    def _speed(self) -> float | None:
        """Median speed over `VOConfig.speed_frames` (world units per frame), None before the first map; asked for
        by a re-initialisation and by each frame's pose check (`VOConfig.pose_check`): a median of <= 20 values."""
        return float(np.median(self._speeds)) if self._speeds else None

    @property
    def observations(self) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The last processed frame's keypoints [N, 2] (frame pixels) and, when it was tracked, the landmark id
        each one matched (-1: none; inliers of the pose only); None when it had no features. For pictures of
        the run (`viz.py`): read it right after the frame's result."""
        return self.last_observations

    @property
    def init_model(self) -> str | None:
        """Model of the last (re)initialisation: essential or homography."""
        return self._initialiser.model

    # ------------------------------------------------------------------ public
    @single_caller
    def process(self, image: np.ndarray | None, timestamp: float | None = None) -> VOResult:
        """Track one frame (HxW gray or HxWx3 BGR) and return its pose and statistics.

        An unusable frame (see `check_frame`; None included) is skipped and flagged, never raised. Raises
        `CalibrationError` for a frame of another size than the calibration's (or the first frame's), and
        `FrameError` for an argument that is not an image array at all (a programming error).
        """
        unusable = self._unusable(image)
        if unusable is not None:
            return self.process_extraction(unusable, timestamp)
        self._check_size(*image.shape[:2])  # a frame of the wrong size raises before the extractor sees it
        return self.process_extraction(self._run_extractor(image), timestamp)

    def stream(self, frames: Iterable, ahead: int = 2, skip_wrong_size: bool = False) -> Iterator[VOResult]:
        """Track a stream of frames, extracting up to ``ahead`` frames ahead on a worker thread while this
        one tracks (`pipeline.py`; 0: one after the other, as `process`). Items are ``(image, timestamp)``
        pairs or `StreamFrame`s (whose image may be a loader run on the worker). Yields each frame's result
        in order; the poses are those of `process`. With ``skip_wrong_size`` a frame of another size is
        skipped instead of raising `CalibrationError`."""
        from vo_runtime.pipeline import track_stream

        return track_stream(self, frames, ahead, skip_wrong_size)

    @single_caller
    def process_extraction(self, extraction: Extraction, timestamp: float | None = None) -> VOResult:
        """Track a frame whose features `extract` found (see `process`)."""
        timestamp = self._checked_timestamp(timestamp)
        image, features = extraction.image, extraction.features
        if not extraction.usable:
            return self.skip(extraction.problem, timestamp)
        self._check_size(*image.shape[:2])
        if features is None:
            return self.skip(extraction.problem, timestamp)
        index = len(self.results)
        if self._frame_size is None:
            self._frame_size = image.shape[:2]
            self._set_pixel_unit(detector_pixel(self.extractor, *image.shape[:2]))
        start = time.perf_counter()
        self._background.wait()  # the last keyframe's mapping, when it runs on the worker thread
        result = VOResult(index=index, timestamp=timestamp, pose=np.eye(4), status=INITIALISING,
                          num_features=len(features), num_matches=0, num_inliers=0, num_landmarks=0,
                          extract_ms=1e3 * extraction.seconds, track_ms=0.0)
        self._poses_cw.append(self._poses_cw[-1].copy() if self._poses_cw else np.eye(4))
        self._track(index, features, result, image)
        result.pose = invert_pose(self._poses_cw[index])
        result.track_ms = 1e3 * (time.perf_counter() - start)
        self.results.append(result)
        if self._mapping_job is not None:  # started only now, so it sees this frame's result
            job, self._mapping_job = self._mapping_job, None
            self._background.submit(job)
        return result

    def finish(self) -> None:
        """Wait for a keyframe's mapping still running on the worker thread (``mapping_thread``) and stop the
        thread; call it before reading the final trajectory. A later `process` carries on as before."""
        self._background.close()

    @single_caller
    def skip(self, problem: str, timestamp: float | None = None) -> VOResult:
        """Record a frame that could not be used (status ``skipped``, pose held) and say why; the map and the
        tracks are untouched, so the next good frame is matched to the last good one."""
        timestamp = self._checked_timestamp(timestamp)
        self._background.wait()
        self.last_observations = None
        index = len(self.results)
        self._poses_cw.append(self._poses_cw[-1].copy() if self._poses_cw else np.eye(4))
        result = VOResult(index=index, timestamp=timestamp, pose=invert_pose(self._poses_cw[index]), status=SKIPPED,
                          num_features=0, num_matches=0, num_inliers=0, num_landmarks=0, extract_ms=0.0,
                          track_ms=0.0, problem=problem)
        self.results.append(result)
        return result

    def _set_pixel_unit(self, pixel: float) -> None:
        """Pixel thresholds are in detector pixels (``pixel`` frame pixels each); with patch alignment the
        keypoints are ``align_gain`` times more precise, and the thresholds tighten with them."""
        cfg = self.config
        if cfg.align_window_px > 0 and pixel >= cfg.align_min_detector_pixel:
            self._aligner = PatchAligner(int(cfg.align_window_px) | 1, cfg.align_max_shift * pixel)
            self._initialiser.align = self._align
            aligned = max(1.0, pixel / cfg.align_gain)
            self._detection_scale, pixel = pixel / aligned, aligned
            self._mapping_config = replace(cfg.mapping, min_parallax_px=cfg.mapping.aligned_min_parallax_px)
        self._focal = self.camera.focal / pixel
        self._initialiser.focal = self._focal

    # ------------------------------------------------------------------ states
    def _track(self, index: int, features: Features, result: VOResult, image: np.ndarray) -> None:
        """Set this frame's pose (held until something better is known) and fill in ``result``."""
        cfg = self.config
        mapped = self.map is not None
        result.status = LOST if (mapped or self._speeds) else INITIALISING
        pixels = np.asarray(features.keypoints, np.float64)
        self.last_observations = (pixels, None)
        if len(features) < cfg.min_features:
            return  # the next frame is matched to the last good one
        frame = FrameData.build(self.camera.normalise(pixels), pixels, features.descriptors)
        if features.scores_predict_error and self._aligner is None:  # aligned keypoints are no longer detections
            frame.sigma = keypoint_sigma(features.scores, cfg.score_sigma_power, cfg.score_sigma_limit)
        if cfg.flow_window_px > 0:
            frame.image = to_gray_u8(image)
        if self._aligner is not None:
            frame.gray = frame.image if frame.image is not None else to_gray_u8(image)
            if cfg.align_normalise:
                frame.gray = contrast_normalise(frame.gray, self._aligner.window_px)
        if self._probation.active or self.map is None:  # the map-free rotation: on detections, not aligned points
            frame.detected = frame.points.copy()
        lost = self._lost_since >= 0
        if mapped and self._last_tracked >= 0 and (not lost or index - self._last_tracked <= cfg.lost_predict_frames):
            settings = self._settings(frame)
            outcome = track_frame(self.map, self._local_ids, self._predict(index), frame, self._previous, settings,
                                  self._poses_cw[self._last_tracked])
            result.match_ms = 1e3 * settings.seconds["matching"]
            result.pose_ms = 1e3 * settings.seconds["pose"]
            if outcome is not None:
                self._accept(index, frame, outcome, TRACKING, result)
                return
            if not lost:  # lost: relocalise from the next frame on (the motion model is still tried first)
                self._lost_since = index
                self._lost_tries = 0
                self._initialiser.restart(index, frame, features)
                return
        if mapped and cfg.relocalise_keyframes > 0:
            outcome = self._relocalise(frame)
            if outcome is not None:
                self._accept(index, frame, outcome, RELOCALISED, result)
                return
            self._lost_tries += 1
        matches = self._initialiser.add(index, frame, features)
        result.num_matches = matches
        if mapped and cfg.relocalise_keyframes > 0 and self._lost_tries < cfg.relocalise_frames:
            return  # give relocalisation a few frames before a new map (and a guessed scale) replaces the old
        if mapped and self._young_map_lost(index):  # the next map is a first map, not one at a guessed scale
            self._discard_young_map(index, result, f"lost {self._lost_since - self.map.keyframes[0].frame} frames "
                                                   f"after its first keyframe (a young map)")
        outcome = self._initialiser.try_initialise(index, self._poses_cw, self._speed)
        if outcome is None:
            return
        self._start_map(index, outcome, result)

    def _predict(self, index: int) -> np.ndarray:
        """Constant velocity: the last motion repeated once per frame since the last tracked frame."""
        pose = self._poses_cw[self._last_tracked]
        for _ in range(index - self._last_tracked):
            pose = self._velocity @ pose
        return pose

    def _settings(self, frame: FrameData) -> TrackingSettings:
        cfg = self.config
        low, high = frame.points.min(axis=0), frame.points.max(axis=0)
        return TrackingSettings(self._focal, (low[0], high[0], low[1], high[1]), cfg.search_radius_px,
                                cfg.wide_search_radius_px, cfg.pnp_threshold_px, cfg.min_pnp_inliers,
                                cfg.match_max_distance, cfg.match_ratio, cfg.max_local_points,
                                float(np.degrees(cfg.mapping.pose_min_parallax_px / self._focal)),
                                cfg.mapping.pose_min_found, check_speed=self._speed if cfg.pose_check else None,
                                check_jump=cfg.pose_check_jump, check_share=cfg.pose_check_share,
                                check_floor=cfg.pose_check_floor,
                                landmark_variance=cfg.landmark_variance, image_rotation_deg=cfg.image_rotation_deg)

    def _relocalise(self, frame: FrameData):
        cfg = self.config
        found = relocalise(self.map, frame.points, frame.descriptors, cfg.relocalise_keyframes,
                           cfg.pnp_threshold_px / self._focal, cfg.min_pnp_inliers, cfg.match_max_distance,
                           cfg.match_ratio)
        if found is None:
            return None
        pose, number = found
        self._set_reference(number)
        outcome = guided_pose(self.map, self._local_ids, pose, frame, self._settings(frame), cfg.search_radius_px)
        if outcome is not None:
            outcome.source = RELOCALISATION
        return outcome

    def _accept(self, index: int, frame: FrameData, outcome, status: str, result: VOResult) -> None:
        """A tracked frame: store its pose, the motion model, and make it a keyframe if needed."""
        detections = len(frame.points)  # rows past these are landmarks the flow followed
        followed = self._follow(index, frame, outcome, status)
        aligned = self._aligner is not None and align_to_map(self._aligner, self.map, frame, outcome.landmark,
                                                             self.camera.normalise)
        if followed or aligned:
            refit_pose(self.map, frame, outcome, self._settings(frame))
        pose = outcome.pose_cw
        previous = self._previous[0]
        if self._probation.active and status == TRACKING and self._last_tracked == index - 1 \
                and previous.detected is not None:
            # detections only: a landmark the flow followed (rows past them) was found where the map said to look
            value = self._probation.disagreement(previous.detected, previous.descriptors[:len(previous.detected)],
                                                 frame.detected, frame.descriptors[:len(frame.detected)],
                                                 pose[:3, :3] @ self._poses_cw[index - 1][:3, :3].T, self._focal)
            if self._probation.judge(value):
                self._discard_map(index, frame, result)
                return
        if status == TRACKING and self._travel_broken(index, frame, outcome.landmark, pose, result, detections):
            return
        if self._last_tracked >= 0 and (self._lost_since < 0 or status == TRACKING):
            gap = index - self._last_tracked
            step = pose @ invert_pose(self._poses_cw[self._last_tracked])
            self._velocity = step if gap == 1 else self._velocity
            travel = float(np.linalg.norm(camera_centre(pose) - camera_centre(self._poses_cw[self._last_tracked]))) / gap
            self._speeds.append(travel)
            self._speed_log.append((index, travel))
        else:
            self._velocity = np.eye(4)  # after a relocalisation the motion is unknown
        self._poses_cw[index] = pose
        self._last_tracked = index
        self._lost_since = -1
        self._previous = (frame, outcome.landmark)
        result.status, result.tracked_by = status, outcome.source
        result.num_matches, result.num_inliers = outcome.matches, outcome.inliers
        result.num_landmarks = int(np.count_nonzero(outcome.landmark >= 0))
        self.last_observations = (frame.pixels, outcome.landmark)
        detected = int(np.count_nonzero(outcome.landmark[:detections] >= 0))
        if self._needs_keyframe(index, result.num_landmarks, detected) or status == RELOCALISED:
            if self._lost_map is not None and status == TRACKING:
                self._merge_lost_map(index, frame, outcome.landmark, result)
            self._insert_keyframe(index, frame, outcome.landmark, result)
            result.keyframe = True
        else:
            keyframe = self.map.keyframes[self._reference_kf]
            self._anchors[self._reference_kf].append((index, pose @ invert_pose(keyframe.pose_cw)))


class VisualOdometry(MonoVO):
    """The embedding API: ``vo = VisualOdometry(artefact, camera)``, then ``vo.track(image, timestamp)``.

    ``artefact`` is an artefact directory (run by `FeatureExtractor` with ``threads`` onnxruntime threads) or
    any callable image -> `Features` (e.g. `OrbExtractor`).

    Threads: one instance tracks one stream, from one thread at a time. A call that enters `track` (or
    `process`, `stream`, `reset`) while another thread is inside raises `ConcurrentUseError` and changes
    nothing; use one instance per camera thread, or serialise the calls. Timestamps, when given, are finite
    and increase from frame to frame (`TimestampError` otherwise, nothing changed).
    """

    def __init__(self, artefact: str | Path | Callable[[np.ndarray], Features], camera: Camera,
                 config: VOConfig | None = None, threads: int = 1) -> None:
        extractor = artefact if callable(artefact) else FeatureExtractor(artefact, threads=threads)
        super().__init__(extractor, camera, config)

    def track(self, image: np.ndarray, timestamp: float | None = None) -> VOResult:
        """Pose (camera-to-world), state and counts for one frame; see `MonoVO.process`."""
        return self.process(image, timestamp)
