"""Tracking one frame against the local map, with guided matching and fallbacks.

The pose predicted by the motion model places each local landmark in the frame; it is matched to a
keypoint within a small radius of that spot (`match_by_projection`), and the pose is refined on those
matches (`refine_pose`). When that explains too few landmarks the search widens (a bad prediction: a
sudden turn), then falls back to the previous frame (descriptor matching to its keypoints that carry
landmarks, PnP RANSAC, and a guided pass from that pose). Only when all fail is the frame lost.

Everything works in the normalised image plane (undistorted), so radii are pixels / focal and no
distortion model is needed to project.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from vo_runtime.geometry import camera_centre, reprojection_errors, rvec_from_pose
from vo_runtime.localmap import LocalMap
from vo_runtime.matching import match_by_projection, match_mutual_nn
from vo_runtime.pose import ransac_pose, refine_pose, second_opinion
from vo_runtime.rotation_fit import MIN_MATCHES, rotation_angle_deg, rotation_between

LOCAL_MAP, WIDE_SEARCH, PREVIOUS_FRAME, RELOCALISATION = "local map", "wide search", "previous frame", "relocalisation"
IMAGE_ROTATION = "image rotation"  # the local map searched again from a pose turned by the frames' own rotation


@dataclass
class FrameData:
    """One frame's keypoints as tracking needs them."""

    points: np.ndarray       # normalised [N, 2]
    pixels: np.ndarray       # [N, 2]
    descriptors: np.ndarray  # [N, D]
    tree: cKDTree            # over ``points``
    gray: np.ndarray | None = None  # the frame, uint8, for patch alignment (`refine.py`)
    detected: np.ndarray | None = None  # ``points`` as detected, before alignment moves some (`probation.py`)
    sigma: np.ndarray | None = None  # [N] each keypoint's expected position error, relative (None: all alike)
    image: np.ndarray | None = None  # the frame, uint8 gray, for following missed landmarks (`flow_follow.py`)

    @classmethod
    def build(cls, points: np.ndarray, pixels: np.ndarray, descriptors: np.ndarray) -> "FrameData":
        return cls(points, pixels, descriptors, cKDTree(points))


@dataclass
class TrackOutcome:
    pose_cw: np.ndarray
    landmark: np.ndarray  # [N] landmark id matched by each keypoint (pose inliers only), -1 where none
    matches: int          # guided matches before the pose gate
    inliers: int
    source: str           # which search found the pose: LOCAL_MAP, WIDE_SEARCH, PREVIOUS_FRAME, RELOCALISATION


@dataclass
class TrackingSettings:
    focal: float
    bounds: tuple[float, float, float, float]  # normalised image extent: x min, x max, y min, y max
    radius_px: float
    wide_radius_px: float
    threshold_px: float
    min_inliers: int
    max_distance: float
    ratio: float | None
    max_points: int
    pose_min_angle: float = 0.0  # degrees; landmarks triangulated from closer rays ...
    pose_min_found: int = 1      # ... and found in fewer frames only join the pose fit when too few others
    # A refined pose that moved further than check_jump x check_speed (world units) from where the refinement
    # started and explains fewer than check_share of its matches gets a second opinion (`pose.second_opinion`);
    # check_speed None: never.
    check_speed: float | None = None
    check_jump: float = 1.0
    check_share: float = 0.5
    check_floor: float = 0.0  # ... and one explaining fewer than this share gets it however far it moved
    # A landmark's own position error, as a share of a keypoint's variance: seen from n keyframes it adds
    # landmark_variance / (n - 1) to its match's variance in a weighted pose fit (0: landmarks exact).
    landmark_variance: float = 0.0
    # When the search from the predicted pose fails: the rotation since the last tracked frame measured from the
    # two frames' matches (`rotation_fit.py`) turns the prediction and the local map is searched again; a pose a
    # wider fallback finds must agree with that rotation within this many degrees (0: neither).
    image_rotation_deg: float = 0.0
    seconds: dict = field(default_factory=lambda: {"matching": 0.0, "pose": 0.0})  # time spent, for the bench


def match_weights(sigma: np.ndarray, views: np.ndarray | None, landmark_variance: float) -> np.ndarray:
    """[N] weights (1 / variance) of keypoint-to-landmark matches for a pose fit: ``sigma`` [N] each keypoint's
    relative position error, ``views`` [N] the keyframes that observed each landmark (None with
    ``landmark_variance`` 0). A landmark triangulated from n views adds ``landmark_variance`` / (n - 1)."""
    if landmark_variance < 0:
        raise ValueError("landmark_variance must be >= 0")
    variance = np.asarray(sigma, np.float64) ** 2.0
    if landmark_variance > 0:
        variance = variance + landmark_variance / np.maximum(np.asarray(views) - 1, 1)
    return 1.0 / variance


def in_view(local_map: LocalMap, ids: np.ndarray, pose_cw: np.ndarray,
            bounds: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks of ``ids`` in front of the camera and inside the image, and their projections (normalised)."""
    cam = local_map.positions[ids] @ pose_cw[:3, :3].T + pose_cw[:3, 3]
    front = cam[:, 2] > 1e-6
    ids, cam = ids[front], cam[front]
    projected = cam[:, :2] / cam[:, 2:3]
    x0, x1, y0, y1 = bounds
    inside = (projected[:, 0] >= x0) & (projected[:, 0] <= x1) & (projected[:, 1] >= y0) & (projected[:, 1] <= y1)
    return ids[inside], projected[inside]


def guided_pose(local_map: LocalMap, ids: np.ndarray, pose_cw: np.ndarray, frame: FrameData,
                settings: TrackingSettings, radius_px: float, robust: bool = False) -> TrackOutcome | None:
    """Guided matching of ``ids`` around their projections from ``pose_cw``, then the pose refined on them
    (``robust``: PnP RANSAC first, for a prediction that may be far off)."""
    start = time.perf_counter()
    visible, projected = in_view(local_map, ids, pose_cw, settings.bounds)
    if len(visible) > settings.max_points:  # bound the work: the most often found landmarks first
        keep = np.argsort(-local_map.found[visible], kind="stable")[: settings.max_points]
        visible, projected = visible[keep], projected[keep]
    pairs = match_by_projection(projected, local_map.descriptors[visible], frame.points, frame.descriptors,
                                radius_px / settings.focal, settings.max_distance, settings.ratio, tree=frame.tree)
    matched = time.perf_counter()
    settings.seconds["matching"] += matched - start
    if len(pairs) < settings.min_inliers:
        return None
    try:
        return _fit_pose(local_map, visible, pairs, pose_cw, frame, settings, robust)
    finally:
        settings.seconds["pose"] += time.perf_counter() - matched


def _fit_pose(local_map: LocalMap, visible: np.ndarray, pairs: np.ndarray, pose_cw: np.ndarray, frame: FrameData,
              settings: TrackingSettings, robust: bool) -> TrackOutcome | None:
    world, image = local_map.positions[visible[pairs[:, 0]]], frame.points[pairs[:, 1]]
    threshold = settings.threshold_px / settings.focal
    # The pose rests on proven landmarks when there are enough: those triangulated from far-apart rays, or
    # found as pose inliers in earlier frames. A new landmark may come from a wrong match along the epipolar
    # line; those that pass the parallax gate lie too close, and a pose fitted to them shrinks the map
    # (measured with the default artefact on KITTI 06: a third of the scale lost over 50 frames).
    ids = visible[pairs[:, 0]]
    reliable = (local_map.angles[ids] >= settings.pose_min_angle) | (local_map.found[ids] >= settings.pose_min_found)
    use = reliable if np.count_nonzero(reliable) >= 2 * settings.min_inliers else np.ones(len(pairs), bool)
    weights = None
    if frame.sigma is not None:
        views = local_map.observation_counts(ids[use]) if settings.landmark_variance > 0 else None
        weights = match_weights(frame.sigma[pairs[use, 1]], views, settings.landmark_variance)
    fit = refine_pose(world[use], image[use], pose_cw, threshold, settings.min_inliers, weights)
    if robust and fit is None:
        fit = ransac_pose(world[use], image[use], threshold, settings.min_inliers)
    elif fit is not None and settings.check_speed is not None:
        fit = second_opinion(world, image, pose_cw, fit, threshold, settings.min_inliers, settings.check_speed,
                             settings.check_jump, settings.check_share, settings.check_floor)
    if fit is None:
        return None
    pose = fit[0]
    inliers = reprojection_errors(world, image, *rvec_from_pose(pose)) < threshold
    if np.count_nonzero(inliers) < settings.min_inliers:
        return None
    landmark = np.full(len(frame.points), -1, np.int64)
    landmark[pairs[inliers, 1]] = visible[pairs[inliers, 0]]
    return TrackOutcome(pose, landmark, len(pairs), int(np.count_nonzero(inliers)), LOCAL_MAP)


def refit_pose(local_map: LocalMap, frame: FrameData, outcome: TrackOutcome, settings: TrackingSettings) -> None:
    """Refine ``outcome``'s pose again on its landmark matches once their keypoints moved (patch alignment,
    `refine.py`); in place, and only if the refit still has enough inliers."""
    rows = np.flatnonzero(outcome.landmark >= 0)
    pairs = np.stack([np.arange(len(rows)), rows], axis=1)
    again = _fit_pose(local_map, outcome.landmark[rows], pairs, outcome.pose_cw, frame, settings, robust=False)
    if again is not None:
        outcome.pose_cw, outcome.landmark, outcome.inliers = again.pose_cw, again.landmark, again.inliers


def track_frame(local_map: LocalMap, ids: np.ndarray, predicted_cw: np.ndarray, frame: FrameData,
                previous: tuple[FrameData, np.ndarray] | None, settings: TrackingSettings,
                previous_pose_cw: np.ndarray | None = None) -> TrackOutcome | None:
    """Local map tracking with its fallbacks (see the module docstring); ``previous`` is the last tracked
    frame and its landmark column, ``previous_pose_cw`` its pose. Counts every landmark predicted in view as
    ``visible``."""
    outcome = guided_pose(local_map, ids, predicted_cw, frame, settings, settings.radius_px)
    turn = None  # the camera's rotation since the previous frame, measured on the two frames' matches
    if outcome is None and settings.image_rotation_deg > 0 and previous is not None and previous_pose_cw is not None:
        turn = image_rotation(previous[0], frame, settings)
        if turn is not None:
            outcome = guided_pose(local_map, ids, turned(predicted_cw, previous_pose_cw, turn), frame, settings,
                                  settings.radius_px)
            if outcome is not None:
                outcome.source = IMAGE_ROTATION
    if outcome is None:
        outcome = guided_pose(local_map, ids, predicted_cw, frame, settings, settings.wide_radius_px, robust=True)
        if outcome is not None:
            outcome.source = WIDE_SEARCH
            outcome = _agrees(outcome, previous_pose_cw, turn, settings)
    if outcome is None and previous is not None:
        outcome = _agrees(_from_previous_frame(local_map, ids, frame, previous, settings), previous_pose_cw, turn,
                          settings)
    if outcome is None:
        return None
    # A second guided pass from the refined pose finds the landmarks a poor prediction missed.
    again = guided_pose(local_map, ids, outcome.pose_cw, frame, settings, settings.radius_px)
    if again is not None and again.inliers >= outcome.inliers:
        again.source = outcome.source
        outcome = again
    visible, _ = in_view(local_map, ids, outcome.pose_cw, settings.bounds)
    local_map.visible[visible] += 1
    local_map.found[outcome.landmark[outcome.landmark >= 0]] += 1
    return outcome


def image_rotation(last: FrameData, frame: FrameData, settings: TrackingSettings) -> np.ndarray | None:
    """Rotation [3, 3] from ``last``'s camera to ``frame``'s fitted to their descriptor matches as if the camera
    only turned (far points dominate its inliers); None unless `MIN_MATCHES` matches agree with it."""
    measured = rotation_between(last.points, last.descriptors, frame.points, frame.descriptors, settings.focal,
                                settings.max_distance, settings.ratio)
    return measured[0] if measured is not None and measured[1] >= MIN_MATCHES else None


def turned(predicted_cw: np.ndarray, previous_pose_cw: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """The prediction with its rotation replaced by the previous pose's turned by ``turn`` (camera centre kept)."""
    pose = np.eye(4)
    pose[:3, :3] = turn @ previous_pose_cw[:3, :3]
    pose[:3, 3] = -pose[:3, :3] @ camera_centre(predicted_cw)
    return pose


def _agrees(outcome: TrackOutcome | None, previous_pose_cw: np.ndarray | None, turn: np.ndarray | None,
            settings: TrackingSettings) -> TrackOutcome | None:
    """``outcome`` unless its rotation since the previous frame is further than ``image_rotation_deg`` from the
    measured ``turn`` (a fallback's PnP on a few wide matches can lock onto a wrong pose)."""
    if outcome is None or turn is None:
        return outcome
    step = outcome.pose_cw[:3, :3] @ previous_pose_cw[:3, :3].T
    return outcome if rotation_angle_deg(turn.T @ step) <= settings.image_rotation_deg else None


def _from_previous_frame(local_map: LocalMap, ids: np.ndarray, frame: FrameData,
                         previous: tuple[FrameData, np.ndarray], settings: TrackingSettings) -> TrackOutcome | None:
    last, last_landmark = previous
    rows = np.flatnonzero((last_landmark >= 0) & local_map.alive[np.maximum(last_landmark, 0)])
    pairs = match_mutual_nn(last.descriptors[rows], frame.descriptors, settings.max_distance, settings.ratio)
    if len(pairs) < settings.min_inliers:
        return None
    world = local_map.positions[last_landmark[rows[pairs[:, 0]]]]
    fit = ransac_pose(world, frame.points[pairs[:, 1]], settings.threshold_px / settings.focal, settings.min_inliers)
    if fit is None:
        return None
    pose, inliers = fit
    landmark = np.full(len(frame.points), -1, np.int64)
    landmark[pairs[inliers, 1]] = last_landmark[rows[pairs[inliers, 0]]]
    return TrackOutcome(pose, landmark, len(pairs), int(np.count_nonzero(inliers)), PREVIOUS_FRAME)
