"""Landmarks the detector missed, followed from the previous frame by optical flow.

A landmark is only found again where the detector fires on it again. In the dark the network's keypoints
come and go from frame to frame (the drone clip's dark landmarks are seen by 2.3 keyframes before they are
culled, 3.6 in normal light), so the map is rebuilt from short-lived points and its scale wanders. After a
frame is tracked, each landmark that the previous frame matched and this one did not is followed by pyramidal
Lucas-Kanade from its position there (`follow_missed_landmarks`): a point the flow finds, that the flow back
returns to where it started, and that the tracked pose projects within the pose gate becomes an extra keypoint
of this frame carrying that landmark, weighted as a keypoint of relative error ``sigma``. The pose is then
refined once more on all matches (the caller's `tracking.refit_pose`).

The followed point carries the landmark's descriptor, so a keyframe made from the frame observes the landmark
there like any match; it never founds a new landmark (every followed point has one). ``frame.detected`` keeps
the detections only: the map's probation judges the map against the frames' own matches, and a point found
where the map said to look is no evidence of its own. `FlowFollowing` is `MonoVO`'s gate: which frames are
followed at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vo_runtime.geometry import reprojection_errors, rvec_from_pose
from vo_runtime.localmap import LocalMap
from vo_runtime.states import TRACKING
from vo_runtime.tracking import FrameData, TrackOutcome

PYRAMID_LEVELS = 2  # a landmark moves a few pixels a frame; two coarser levels carry 4x that
_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 0.01)


@dataclass(frozen=True)
class FlowFollow:
    """window_px: Lucas-Kanade patch side in frame pixels (odd); check_px: the flow back from the followed
    point must land within this many frame pixels of the start; threshold_px: the pose gate, in the units of
    ``focal`` (the tracked pose must project the landmark this close); sigma: the followed point's relative
    position error in a weighted pose fit (a keypoint at the frame's median score has 1)."""

    window_px: int
    check_px: float
    threshold_px: float
    sigma: float


def flow(previous_gray: np.ndarray, gray: np.ndarray, start_px: np.ndarray, window_px: int,
         check_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Follow ``start_px`` [N, 2] of ``previous_gray`` into ``gray`` (both HxW uint8), forwards and back.

    Returns (positions [N, 2] float64 in ``gray``, found [N] bool): found where both directions converged,
    the flow back lands within ``check_px`` of the start, and the point lies inside the frame.
    """
    if len(start_px) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    start = np.ascontiguousarray(start_px, np.float32).reshape(-1, 1, 2)
    window = (int(window_px) | 1, int(window_px) | 1)
    ahead, status, _ = cv2.calcOpticalFlowPyrLK(previous_gray, gray, start, None, winSize=window,
                                                maxLevel=PYRAMID_LEVELS, criteria=_CRITERIA)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(gray, previous_gray, ahead, None, winSize=window,
                                                    maxLevel=PYRAMID_LEVELS, criteria=_CRITERIA)
    positions = ahead.reshape(-1, 2).astype(np.float64)
    height, width = gray.shape[:2]
    found = (status.reshape(-1) == 1) & (status_back.reshape(-1) == 1) & np.all(np.isfinite(positions), axis=1)
    found &= np.linalg.norm((back - start).reshape(-1, 2), axis=1) <= check_px
    found &= (positions[:, 0] >= 0) & (positions[:, 0] <= width - 1)
    found &= (positions[:, 1] >= 0) & (positions[:, 1] <= height - 1)
    return positions, found


def follow_missed_landmarks(local_map: LocalMap, previous: FrameData, previous_landmark: np.ndarray,
                            previous_gray: np.ndarray, frame: FrameData, gray: np.ndarray, outcome: TrackOutcome,
                            normalise, focal: float, settings: FlowFollow) -> int:
    """Append to ``frame`` (and ``outcome.landmark``) the landmarks ``previous`` matched (``previous_landmark``
    [M] ids, -1 where none) that ``outcome`` did not, where the flow finds them consistent with
    ``outcome.pose_cw``; ``normalise`` maps frame pixels [K, 2] to the normalised image plane, ``focal`` is
    pixels (of ``settings.threshold_px``) per normalised unit. In place; returns how many were added."""
    matched = np.zeros(local_map.size, bool)
    matched[outcome.landmark[outcome.landmark >= 0]] = True
    rows = np.flatnonzero(previous_landmark >= 0)
    ids = previous_landmark[rows]
    keep = local_map.alive[ids] & ~matched[ids]
    rows, ids = rows[keep], ids[keep]
    if len(rows) == 0:
        return 0
    pixels, found = flow(previous_gray, gray, previous.pixels[rows], settings.window_px, settings.check_px)
    pixels, ids = pixels[found], ids[found]
    if len(ids) == 0:
        return 0
    points = normalise(pixels)
    errors = reprojection_errors(local_map.positions[ids], points, *rvec_from_pose(outcome.pose_cw)) * focal
    near = errors < settings.threshold_px
    pixels, points, ids = pixels[near], points[near], ids[near]
    if len(ids) == 0:
        return 0
    frame.pixels = np.vstack([frame.pixels, pixels])
    frame.points = np.vstack([frame.points, points])
    frame.descriptors = np.vstack([frame.descriptors, local_map.descriptors[ids].astype(frame.descriptors.dtype)])
    if frame.sigma is not None:
        frame.sigma = np.concatenate([frame.sigma, np.full(len(ids), settings.sigma)])
    frame.tree = cKDTree(frame.points)
    outcome.landmark = np.concatenate([outcome.landmark, ids])
    local_map.found[ids] += 1
    return int(len(ids))


class FlowFollowing:
    """When `MonoVO` follows missed landmarks: a base class of `MonoVO` only, over its state (``self.map``,
    ``self._previous``, ``self._last_tracked``, ...), as `MapLifecycle` is."""

    def _follow(self, index: int, frame: FrameData, outcome: TrackOutcome, status: str) -> int:
        """The landmarks the previous frame matched and this one missed, followed by optical flow
        (``VOConfig.flow_window_px``); only from a frame tracked just before. Returns how many were added."""
        cfg = self.config
        previous = self._previous[0] if self._previous is not None else None
        if cfg.flow_window_px <= 0 or status != TRACKING or self._last_tracked != index - 1 \
                or previous is None or previous.image is None or frame.image is None:
            return 0
        # A young first map earns its keep on its own detections: a broken one is discarded when it loses its way
        # (`_young_map_lost`), and points followed where it says to look would carry it along instead.
        if self._young(index, min(cfg.young_map_lost_frames, cfg.young_map_frames)):
            return 0
        settings = FlowFollow(cfg.flow_window_px, cfg.flow_check_px, cfg.pnp_threshold_px, cfg.flow_sigma)
        return follow_missed_landmarks(self.map, previous, self._previous[1], previous.image, frame, frame.image,
                                       outcome, self.camera.normalise, self._focal, settings)
