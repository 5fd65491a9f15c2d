"""Travel check: is the map's direction of travel the one the frames' own geometry gives?

A map can break without losing a frame: on the dark EuRoC take-off (MH_05 from frame 0, noise draw 1) the
local scale fell from 1.0 to 0.18 over frames 34-38 and the direction of travel went 40-70 deg wrong, while
every frame kept 60-150 inliers and said "tracking" (docs/vo_takeoff.md). Rotation stays right (about 1 deg),
so the probation's rotation test (`probation.py`) cannot see it; the direction of travel can, and needs no
scale. Between a tracked frame and the tracked frame ``gap`` frames before it, the landmarks both observed give
correspondences that an essential matrix fits without the map's 3D points; its translation direction, put in
the world by the tracked rotation, is compared with the tracked one. Where the two frames share too few landmarks
(a car at 10 Hz turns its local map over: KITTI 07 frames ten apart share a median of 5 tracked landmarks, the
drone's 86), the two frames' keypoints matched by descriptor (mutual nearest neighbours) stand in for them.

An essential matrix over a short baseline is noise (the take-off's first 2-5 mm: 70-96 deg off the ground
truth), and a broken map's is not (2-9 deg off, while the map was 40-65 deg off). What tells them apart online
is that a well-conditioned direction stays put from one check to the next, and noise does not. So a verdict
needs ``frames`` consecutive checks whose essential directions agree with one another within
``consistency_deg`` and whose median disagreement with the map exceeds ``max_deg``. `MonoVO` then abandons
the map and initialises again at the speed it measured before the window (``VOConfig.travel_check_gap``).
"""
from __future__ import annotations

from collections import deque
from typing import Callable

import cv2
import numpy as np

from vo_runtime.geometry import camera_centre
from vo_runtime.matching import match_mutual_nn

MIN_POINTS = 12      # fewer shared landmarks: no check on this frame
TRACE_CHECKS = 1000  # checks kept in `TravelCheck.last_angles`


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two 3-vectors, degrees."""
    cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def essential_direction(points_a: np.ndarray, points_b: np.ndarray, threshold: float,
                        min_inliers: int) -> np.ndarray | None:
    """Unit direction of b's camera centre from a's, in a's camera frame, from an essential matrix fitted to
    normalised correspondences [N, 2] (RANSAC gate ``threshold``, normalised units); None when fewer than
    ``min_inliers`` agree."""
    if len(points_a) < max(MIN_POINTS, min_inliers):
        return None
    essential, mask = cv2.findEssentialMat(points_a, points_b, np.eye(3), method=cv2.USAC_DEFAULT, prob=0.999,
                                           threshold=threshold)
    if essential is None or essential.shape != (3, 3) or int(mask.sum()) < min_inliers:
        return None
    # recoverPose counts only the correspondences in front of both cameras and nearer than 50 baselines: points
    # with too little parallax to say anything about the direction do not make the essential matrix trusted.
    inliers, rotation, translation, _ = cv2.recoverPose(essential, points_a, points_b, np.eye(3), mask=mask.copy())
    if inliers < min_inliers:
        return None
    # x_b = R x_a + t: b's centre in a's frame is -R^T t
    centre = -rotation.T @ translation.ravel()
    return centre / max(float(np.linalg.norm(centre)), 1e-12)


class TravelCheck:
    """Remembers the last ``gap`` tracked frames' landmark observations and judges each new tracked frame.

    Args:
        gap: frames between the two views of a check (0: off).
        max_deg: median disagreement between the map's and the essential direction that breaks the map.
        consistency_deg: largest change of the essential direction between consecutive checks of a verdict.
        frames: consecutive checks a verdict needs.
        min_inliers: essential-matrix inliers a check needs.
        match: (max L2 distance, Lowe ratio or None) for descriptor-matched correspondences where the shared
            landmarks give no direction; None: landmarks only.
    """

    def __init__(self, gap: int, max_deg: float, consistency_deg: float, frames: int, min_inliers: int,
                 match: tuple[float, float | None] | None = None) -> None:
        self.gap, self.max_deg, self.consistency_deg = int(gap), float(max_deg), float(consistency_deg)
        self.frames, self.min_inliers, self.match = int(frames), int(min_inliers), match
        # frame -> (landmark ids [N], points [N, 2], descriptors [N, D] or None, pose_cw as tracked, what the
        # caller kept with it for `frame_at`)
        self._views: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, object]] = {}
        self._checks: deque[tuple[int, float, np.ndarray]] = deque(maxlen=max(self.frames, 1))
        # (frame, degrees) of the latest checks, for traces; bounded, as a drone flies for hours
        self.last_angles: deque[tuple[int, float]] = deque(maxlen=TRACE_CHECKS)
        self.matched_checks = 0  # checks whose correspondences came from descriptor matching

    @property
    def active(self) -> bool:
        return self.gap > 0

    def clear(self) -> None:
        """A new map (or none): views of the old one say nothing about it."""
        self._views.clear()
        self._checks.clear()

    def frame_at(self, index: int):
        """What `judge` was given as ``keep`` for a frame still in the window (None: none)."""
        view = self._views.get(index)
        return None if view is None else view[4]

    def judge(self, index: int, landmark: np.ndarray, points: np.ndarray, pose_cw: np.ndarray,
              threshold: float, keep: object = None, pose_of: Callable[[int], np.ndarray] | None = None,
              descriptors: np.ndarray | None = None) -> float | None:
        """Add a tracked frame (its keypoints' landmark ids, -1 for none; normalised points; world-to-camera
        pose; anything to keep with it for `frame_at`; its keypoints' unit descriptors for matching when the
        shared landmarks are too few) and return the verdict's median disagreement in degrees
        when the map is broken, else None. ``pose_of(frame)``, when given, is an earlier frame's pose now: the
        bundle adjustment moves the poses of the frames after a new map, and the pose they were tracked at
        disagreed with the frames' geometry by 66-77 deg on a healthy ORB take-off (EuRoC from 10) that the
        adjustment then set right."""
        if not self.active:
            return None
        # snapshots, as the frame was judged: the caller's arrays are its own to change later
        self._views[index] = (landmark.copy(), points.copy(), descriptors if self.match else None, pose_cw, keep)
        for old in [number for number in self._views if number < index - self.gap]:
            del self._views[old]
        earlier = self._views.get(index - self.gap)
        if earlier is None:
            return None
        pose_a = earlier[3] if pose_of is None else pose_of(index - self.gap)
        direction = self._direction(earlier, self._views[index], threshold)
        if direction is None:
            return None
        world = pose_a[:3, :3].T @ direction                    # essential travel direction in the world
        travel = pose_a[:3, :3] @ (camera_centre(pose_cw) - camera_centre(pose_a))  # the map's, in a's frame
        disagreement = angle_deg(direction, travel)
        self.last_angles.append((index, disagreement))
        if self._checks and self._checks[-1][0] != index - 1:
            self._checks.clear()  # consecutive checks only
        self._checks.append((index, disagreement, world))
        if len(self._checks) < self.frames:
            return None
        worlds = [check[2] for check in self._checks]
        if max(angle_deg(a, b) for a, b in zip(worlds, worlds[1:])) > self.consistency_deg:
            return None
        median = float(np.median([check[1] for check in self._checks]))
        return median if median > self.max_deg else None

    def _direction(self, view_a: tuple, view_b: tuple, threshold: float) -> np.ndarray | None:
        """The essential direction between two views: on the landmarks both observed, else (``match``) on
        their keypoints matched by descriptor."""
        (ids_a, points_a, desc_a, *_), (ids_b, points_b, desc_b, *_) = view_a, view_b
        seen_a, seen_b = np.flatnonzero(ids_a >= 0), np.flatnonzero(ids_b >= 0)
        _, rows_a, rows_b = np.intersect1d(ids_a[seen_a], ids_b[seen_b], return_indices=True)
        direction = essential_direction(points_a[seen_a[rows_a]], points_b[seen_b[rows_b]], threshold,
                                        self.min_inliers)
        if direction is not None or desc_a is None or desc_b is None:
            return direction
        pairs = match_mutual_nn(desc_a, desc_b, *self.match)
        direction = essential_direction(points_a[pairs[:, 0]], points_b[pairs[:, 1]], threshold, self.min_inliers)
        self.matched_checks += direction is not None
        return direction

