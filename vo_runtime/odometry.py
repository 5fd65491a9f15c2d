"""`MonoVO` / `VisualOdometry`: a monocular visual odometry on top of any keypoint extractor.

Each frame's keypoints are matched (mutual nearest neighbour on descriptors) to the previous frame's, which
extends feature tracks. Every track remembers where it began (frame and image point) and, once triangulated,
its 3D landmark. Per frame:

- before a map exists: once the tracks that began at the reference frame have moved far enough, initialise
  from a homography or an essential matrix, whichever scores better (`twoview.py`), and triangulate; the
  first baseline sets the unit of length (``VOConfig.initial_baseline``);
- once a map exists: PnP RANSAC against the tracked landmarks (constant-velocity prediction as the fallback
  seed) gives the pose, which keeps one scale along the sequence. PnP outliers lose their landmark. Tracks
  whose rays (first view vs this view) are far enough apart are triangulated; landmarks are re-triangulated
  when their ray angle has doubled since. Every tracked frame's observations join a sliding window of
  the last ``ba_window`` frames. A tracked frame becomes a keyframe when ``keyframe_max_gap`` frames have
  passed or it sees fewer than ``keyframe_track_ratio`` of the last keyframe's landmarks; each keyframe
  runs the local bundle adjustment, which refines the window's poses and points and culls points that stay
  far off (`bundle.py`);
- if PnP fails the frame is ``lost``: the pose is held, the tracks restart from this frame and the next
  initialisation is scaled by the speed measured so far (status ``reinitialised``);
- a frame that cannot be used (None, empty, of an unusable shape or dtype, NaN/inf: `check_frame`) is
  ``skipped``: the pose is held, the result says why (``problem``), and tracking goes on with the next frame
  as if the bad one had not arrived. A frame whose size contradicts the calibration (or, for a calibration
  without a size, the first frame's size) raises `CalibrationError` and changes nothing: the intrinsics
  would be wrong for it, and the caller decides (the CLI records it as skipped).

Poses are camera-to-world 4x4 matrices; the world is the first frame's camera (x right, y down, z forward),
in units of the first baseline (monocular VO cannot observe metric scale).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from vo_runtime.bundle import SlidingWindow
from vo_runtime.camera import Camera
from vo_runtime.errors import CalibrationError, FrameError, VORuntimeError
from vo_runtime.features import FeatureExtractor, Features, check_frame
from vo_runtime.geometry import (camera_centre, invert_pose, make_pose, pose_from_rvec, ray_angles,
                                 reprojection_errors, rvec_from_pose, triangulate)
from vo_runtime.matching import match_mutual_nn
from vo_runtime.tracks import Tracks
from vo_runtime.twoview import relative_pose_hypotheses

INITIALISING, TRACKING, REINITIALISED, LOST = "initialising", "tracking", "reinitialised", "lost"
SKIPPED = "skipped"  # the frame could not be used (see VOResult.problem); the pose is held


@dataclass
class VOConfig:
    """Tuning knobs. Pixel thresholds are in the frame's pixels; angles in degrees."""

    match_max_distance: float = 0.9      # L2 between unit descriptors (0..2)
    match_ratio: float | None = 0.9      # Lowe ratio on distances; None disables
    min_features: int = 30               # fewer detections: the frame is not used
    min_matches: int = 30                # correspondences an (re)initialisation needs
    min_pnp_inliers: int = 20            # PnP needs this many inliers to be trusted
    ransac_threshold_px: float = 1.0     # essential-matrix RANSAC (Sampson distance)
    pnp_threshold_px: float = 3.0        # PnP RANSAC reprojection error
    triangulation_threshold_px: float = 3.0  # largest reprojection error of a new landmark in either view
    init_min_parallax_px: float = 15.0   # median track motion before a two-view initialisation is tried
    init_min_landmarks: int = 40         # triangulated points an initialisation must produce
    min_triangulation_deg: float = 1.0   # rays closer than this give no landmark
    refresh_factor: float = 2.0          # re-triangulate a landmark when its ray angle grew by this factor
    ba_window: int = 8                   # frames in the local bundle adjustment (0: none)
    keyframe_max_gap: int = 4            # a tracked frame becomes a keyframe at least this often ...
    # ... or when it still sees fewer than this share of the last keyframe's landmarks. Off by default:
    # measured with ORB (docs/vo.md), 0.3-0.5 helped KITTI 06 (ATE 0.57 -> 0.03-0.06 m) but made the
    # scale of KITTI 07 drift (0.31 -> 1.6-5.0 m): without guided matching tracks decay fast, so the
    # trigger fires at turns, where adjusting a short window moves the scale most.
    keyframe_track_ratio: float = 0.0
    initial_baseline: float = 1.0        # length of the first baseline, in output units

    def __post_init__(self) -> None:
        if self.min_matches < 8 or self.min_pnp_inliers < 6:
            raise VORuntimeError("min_matches must be >= 8 and min_pnp_inliers >= 6")
        if self.initial_baseline <= 0:
            raise VORuntimeError("initial_baseline must be positive")


@dataclass
class VOResult:
    """Outcome of one frame. ``pose`` is camera-to-world (4x4)."""

    index: int
    timestamp: float | None
    pose: np.ndarray
    status: str
    num_features: int
    num_matches: int      # matched to the previous frame
    num_inliers: int      # PnP or essential-matrix inliers
    num_landmarks: int    # tracked keypoints of this frame that carry a landmark
    extract_ms: float
    track_ms: float
    keyframe: bool = False  # ran the local bundle adjustment
    problem: str | None = None  # why a skipped frame could not be used


class MonoVO:
    """Monocular VO over a stream of frames.

    Args:
        extractor: callable image -> `Features` (e.g. `FeatureExtractor` on an artefact, or `OrbExtractor`).
        camera: intrinsics of the frames passed to `process`.
        config: `VOConfig`; the defaults suit 10 Hz driving and hand-held indoor sequences.
    """

    def __init__(self, extractor: Callable[[np.ndarray], Features], camera: Camera, config: VOConfig | None = None):
        self.extractor = extractor
        self.camera = camera
        self.config = config or VOConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the map and the trajectory; the next frame becomes the origin."""
        self.results: list[VOResult] = []
        self._poses_cw: list[np.ndarray] = []  # world-to-camera, one per processed frame
        self._previous: tuple[Features, Tracks] | None = None
        self._reference = 0                    # frame the next initialisation measures from
        self._initialised = False             # a scale has been fixed (first initialisation done)
        self._mapped = False                  # landmarks exist to track against (false again after a loss)
        self._speed: float | None = None       # world units per frame, from the last PnP step
        self._window = SlidingWindow(self.config.ba_window)
        self.init_model: str | None = None     # model of the last (re)initialisation: essential or homography
        self._keyframe = -1                    # index of the last keyframe
        self._keyframe_ids = np.zeros(0, np.int64)  # track ids of the landmarks that keyframe saw
        self._frame_size: tuple[int, int] | None = None  # (height, width) of the frames, fixed by the first one

    # ------------------------------------------------------------------ public
    def process(self, image: np.ndarray | None, timestamp: float | None = None) -> VOResult:
        """Track one frame (HxW gray or HxWx3 BGR) and return its pose and statistics.

        An unusable frame (see `check_frame`; None included) is skipped and flagged, never raised. Raises
        `CalibrationError` for a frame of another size than the calibration's (or the first frame's), and
        `FrameError` for an argument that is not an image array at all (a programming error).
        """
        if image is not None and not isinstance(image, np.ndarray):
            raise FrameError(f"expected an HxW or HxWx3 image array, got {type(image).__name__}")
        try:
            check_frame(image)
        except FrameError as exc:
            return self.skip(str(exc), timestamp)
        self._check_size(*image.shape[:2])
        index = len(self.results)
        start = time.perf_counter()
        try:
            features = self.extractor(image)
        except FrameError as exc:  # e.g. an extractor whose resize policy rejects this size
            return self.skip(str(exc), timestamp)
        if self._frame_size is None:
            self._frame_size = image.shape[:2]
        extracted = time.perf_counter()
        tracks = Tracks(index, self.camera.normalise(features.keypoints), np.asarray(features.keypoints, np.float64))
        status, matches, inliers = self._track(index, features, tracks)
        result = VOResult(
            index=index, timestamp=timestamp, pose=invert_pose(self._poses_cw[index]), status=status,
            num_features=len(features), num_matches=matches, num_inliers=inliers,
            num_landmarks=int(np.count_nonzero(tracks.has_landmark)), keyframe=self._keyframe == index,
            extract_ms=1e3 * (extracted - start), track_ms=1e3 * (time.perf_counter() - extracted),
        )
        self.results.append(result)
        return result

    def skip(self, problem: str, timestamp: float | None = None) -> VOResult:
        """Record a frame that could not be used (status ``skipped``, pose held) and say why; the map and the
        tracks are untouched, so the next good frame is matched to the last good one."""
        index = len(self.results)
        self._poses_cw.append(self._poses_cw[-1].copy() if self._poses_cw else np.eye(4))
        result = VOResult(index=index, timestamp=timestamp, pose=invert_pose(self._poses_cw[index]), status=SKIPPED,
                          num_features=0, num_matches=0, num_inliers=0, num_landmarks=0, extract_ms=0.0,
                          track_ms=0.0, problem=problem)
        self.results.append(result)
        return result

    def _check_size(self, height: int, width: int) -> None:
        """Intrinsics fit one frame size: the calibration's, or when it names none, the first frame's."""
        self.camera.check_frame(height, width)
        if self._frame_size is not None and (height, width) != self._frame_size:
            raise CalibrationError(f"frame is {width}x{height} but this sequence's frames are "
                                   f"{self._frame_size[1]}x{self._frame_size[0]} (the intrinsics fit one size)")

    # ------------------------------------------------------------------ tracking
    def _track(self, index: int, features: Features, tracks: Tracks) -> tuple[str, int, int]:
        """Set this frame's pose (held until something better is known); return (status, matches, inliers)."""
        cfg = self.config
        self._poses_cw.append(self._poses_cw[-1].copy() if self._poses_cw else np.eye(4))
        failed = LOST if self._initialised else INITIALISING
        if self._previous is None:
            self._reference = index
            self._previous = (features, tracks)
            return INITIALISING, 0, 0
        if len(features) < cfg.min_features:
            return failed, 0, 0  # skip the frame: the next one is matched to the previous good frame
        prev_features, prev_tracks = self._previous
        self._previous = (features, tracks)
        matches = match_mutual_nn(prev_features.descriptors, features.descriptors, cfg.match_max_distance,
                                  cfg.match_ratio)
        tracks.extend(prev_tracks, matches)
        if self._mapped:
            inliers = self._track_pnp(index, tracks)
            if inliers is not None:
                self._triangulate(index, tracks)
                # Every tracked frame's observations enter the window (more views per point steadied the
                # scale on KITTI); keyframes decide when the window is adjusted and culled.
                self._window_add(index, tracks.ids, tracks.points, tracks.landmarks, tracks.has_landmark)
                if self._needs_keyframe(index, tracks):
                    self._local_bundle_adjustment(tracks)
                    self._mark_keyframe(index, tracks)
                return TRACKING, len(matches), inliers
            # Lost: hold the pose and measure the next initialisation from here.
            self._mapped = False
            self._window.clear()
            self._reference = index
            tracks.restart(np.arange(len(tracks.points)), index)
            return LOST, len(matches), 0
        count = self._initialise(index, tracks)
        if count is None:
            return failed, len(matches), 0
        status = REINITIALISED if self._initialised else TRACKING
        self._initialised = self._mapped = True
        return status, len(matches), count

    def _track_pnp(self, index: int, tracks: Tracks) -> int | None:
        """PnP against the tracked landmarks; on success set this frame's pose and return the inlier count."""
        cfg = self.config
        rows = np.flatnonzero(tracks.has_landmark)
        if len(rows) < cfg.min_pnp_inliers:
            return None
        world = tracks.landmarks[rows]
        image = tracks.points[rows]
        threshold = cfg.pnp_threshold_px / self.camera.focal
        # No extrinsic guess for RANSAC: OpenCV 5.0's RANSAC with SOLVEPNP_ITERATIVE + useExtrinsicGuess
        # returned the guess with every point flagged inlier (median error ~90 px on noise-free data).
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            world, image, np.eye(3), None, iterationsCount=200, reprojectionError=threshold, confidence=0.999,
            flags=cv2.SOLVEPNP_SQPNP,
        )
        if not ok or inl is None or len(inl) < cfg.min_pnp_inliers:
            # RANSAC found no consensus (few or noisy landmarks): start from the constant-velocity
            # prediction instead, keep what it explains within twice the threshold, refine, and re-gate.
            last = self._poses_cw[index - 1]
            before = self._poses_cw[index - 2] if index >= 2 else last
            rvec, tvec = rvec_from_pose(last @ invert_pose(before) @ last)
            inl = np.flatnonzero(reprojection_errors(world, image, rvec, tvec) < 2 * threshold)
            if len(inl) < cfg.min_pnp_inliers:
                return None
            rvec, tvec = cv2.solvePnPRefineLM(world[inl], image[inl], np.eye(3), None, rvec, tvec)
            inl = np.flatnonzero(reprojection_errors(world, image, rvec, tvec) < threshold)
            if len(inl) < cfg.min_pnp_inliers:
                return None
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(world[inl], image[inl], np.eye(3), None, rvec, tvec)
        pose = pose_from_rvec(rvec, tvec)
        self._speed = float(np.linalg.norm(camera_centre(pose) - camera_centre(self._poses_cw[index - 1])))
        self._poses_cw[index] = pose
        outliers = np.setdiff1d(rows, rows[inl])
        tracks.landmarks[outliers] = np.nan
        tracks.angles[outliers] = 0.0
        return len(inl)

    def _initialise(self, index: int, tracks: Tracks) -> int | None:
        """Two-view initialisation from the reference frame. Returns the inlier count, or None (not yet)."""
        cfg = self.config
        rows = np.flatnonzero(tracks.first_frame == self._reference)
        if len(rows) < cfg.min_matches:
            # Too few tracks survive from the reference: measure from this frame instead.
            self._poses_cw[index] = self._poses_cw[self._reference].copy()
            self._reference = index
            tracks.restart(np.arange(len(tracks.points)), index)
            return None
        motion = np.median(np.linalg.norm(tracks.pixels[rows] - tracks.first_pixels[rows], axis=1))
        # Tracks from the reference die off, and the survivors are the slow, distant points: when few are
        # left, try with less motion rather than lose the reference (the landmark checks below still apply).
        dying = len(rows) < 3 * cfg.min_matches
        if motion < (cfg.init_min_parallax_px / 3 if dying else cfg.init_min_parallax_px):
            return None
        pts_ref, pts_cur = tracks.first_points[rows], tracks.points[rows]
        if self._initialised:  # re-initialisation after a loss: keep the speed measured before it
            scale = (self._speed or cfg.initial_baseline) * (index - self._reference)
        else:
            scale = cfg.initial_baseline
        ref_pose = self._poses_cw[self._reference]
        # Keep the hypothesis that triangulates the most points (in front, small error, enough parallax).
        best = []
        for hypothesis in relative_pose_hypotheses(pts_ref, pts_cur, cfg.ransac_threshold_px / self.camera.focal):
            if np.count_nonzero(hypothesis.inliers) < cfg.init_min_landmarks:
                continue
            pose = make_pose(hypothesis.rotation, scale * hypothesis.translation) @ ref_pose
            inliers = rows[hypothesis.inliers]
            world, error = triangulate(ref_pose, pose, pts_ref[hypothesis.inliers], pts_cur[hypothesis.inliers])
            angles = ray_angles(ref_pose, pose, tracks.first_points[inliers], tracks.points[inliers])
            good = (error < cfg.triangulation_threshold_px / self.camera.focal) & (angles >= cfg.min_triangulation_deg)
            best.append((int(np.count_nonzero(good)), hypothesis.model, pose, inliers, world, angles, good))
        best.sort(key=lambda item: -item[0])
        if not best or best[0][0] < cfg.init_min_landmarks:
            return None
        if len(best) > 1 and best[1][0] > 0.75 * best[0][0]:
            return None  # ambiguous homography decomposition: wait for more motion
        _, self.init_model, pose, inliers, world, angles, good = best[0]
        self._poses_cw[index] = pose
        # Tracks that began after the reference frame began at a held (unknown) pose: restart them here.
        tracks.restart(np.flatnonzero(tracks.first_frame != self._reference), index)
        tracks.landmarks[inliers[good]] = world[good]
        tracks.angles[inliers[good]] = angles[good]
        # The window starts with the two views of the initialisation (both held fixed in adjustment).
        self._window.clear()
        seen = tracks.has_landmark
        self._window_add(self._reference, tracks.ids, tracks.first_points, tracks.landmarks, seen)
        self._window_add(index, tracks.ids, tracks.points, tracks.landmarks, seen)
        self._mark_keyframe(index, tracks)
        self._speed = scale / (index - self._reference)
        return len(inliers)

    def _needs_keyframe(self, index: int, tracks: Tracks) -> bool:
        """ORB-SLAM's two reasons, simplified: the view has moved on, or too long since the last keyframe."""
        cfg = self.config
        if index - self._keyframe >= cfg.keyframe_max_gap:
            return True
        still_seen = np.isin(tracks.ids[tracks.has_landmark], self._keyframe_ids).sum()
        return still_seen < cfg.keyframe_track_ratio * len(self._keyframe_ids)

    def _mark_keyframe(self, index: int, tracks: Tracks) -> None:
        self._keyframe = index
        self._keyframe_ids = tracks.ids[tracks.has_landmark].copy()

    def _window_add(self, index: int, ids: np.ndarray, points: np.ndarray, landmarks: np.ndarray,
                    rows: np.ndarray) -> None:
        if self.config.ba_window:
            self._window.add(index, ids[rows], points[rows], landmarks[rows])

    def _local_bundle_adjustment(self, tracks: Tracks) -> None:
        """Refine the window's poses and points; update this frame's landmarks and drop the bad ones."""
        cfg = self.config
        if not cfg.ba_window:
            return
        seen = np.flatnonzero(tracks.has_landmark)
        outcome = self._window.adjust(self._poses_cw, self.camera.focal, gate_px=4 * cfg.pnp_threshold_px,
                                      cull_px=cfg.triangulation_threshold_px,
                                      current=(tracks.ids[seen], tracks.landmarks[seen]))
        if outcome is None:
            return
        poses, points, culled = outcome
        for frame, pose in poses.items():
            self._poses_cw[frame] = pose
            if frame < len(self.results):  # frames already reported get the refined pose too
                self.results[frame].pose = invert_pose(pose)
        for row in seen:
            landmark_id = int(tracks.ids[row])
            if landmark_id in points:
                tracks.landmarks[row] = points[landmark_id]
            elif landmark_id in culled:
                tracks.landmarks[row] = np.nan
                tracks.angles[row] = 0.0

    def _triangulate(self, index: int, tracks: Tracks) -> None:
        """Triangulate tracks whose rays are far enough apart, and refresh landmarks whose angle doubled."""
        cfg = self.config
        candidates = np.flatnonzero(tracks.first_frame < index)
        if len(candidates) == 0:
            return
        pose = self._poses_cw[index]
        first_poses = np.stack([self._poses_cw[f] for f in tracks.first_frame[candidates]])
        angles = ray_angles(first_poses, pose, tracks.first_points[candidates], tracks.points[candidates])
        due = (angles >= cfg.min_triangulation_deg) & (angles >= cfg.refresh_factor * tracks.angles[candidates])
        for first in np.unique(tracks.first_frame[candidates[due]]):
            pick = due & (tracks.first_frame[candidates] == first)
            rows = candidates[pick]
            world, error = triangulate(self._poses_cw[first], pose, tracks.first_points[rows], tracks.points[rows])
            good = error < cfg.triangulation_threshold_px / self.camera.focal
            tracks.landmarks[rows[good]] = world[good]
            tracks.angles[rows[good]] = angles[pick][good]


class VisualOdometry(MonoVO):
    """The embedding API: ``vo = VisualOdometry(artefact, camera)``, then ``vo.track(image, timestamp)``.

    ``artefact`` is an artefact directory (run by `FeatureExtractor` with ``threads`` onnxruntime threads) or
    any callable image -> `Features` (e.g. `OrbExtractor`).
    """

    def __init__(self, artefact: str | Path | Callable[[np.ndarray], Features], camera: Camera,
                 config: VOConfig | None = None, threads: int = 1) -> None:
        extractor = artefact if callable(artefact) else FeatureExtractor(artefact, threads=threads)
        super().__init__(extractor, camera, config)

    def track(self, image: np.ndarray, timestamp: float | None = None) -> VOResult:
        """Pose (camera-to-world), state and counts for one frame; see `MonoVO.process`."""
        return self.process(image, timestamp)
