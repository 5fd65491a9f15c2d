"""A re-initialised map found in the map it replaced: the similarity between the two, so the new map can take
the lost map's frame and scale.

After a loss that relocalisation could not bridge, the VO starts a new map whose scale is only a guess (the
speed before the loss, `MonoVO._speed`), and a drone that turned or slowed while lost carries the wrong guess for
the rest of its flight (the 100 s dark flight's run that ended at 1.18 m: docs/vo.md, "A long flight"). Once the
new map sees what the lost map saw, one frame holds both scales: its keypoints match the lost map's landmarks
(PnP RANSAC: the frame's pose in the lost map) and its own map's landmarks (its tracked pose). The depths of
the landmarks both maps give the same keypoint fix the ratio of the scales; the two poses fix the rest.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_runtime.localmap import LocalMap
from vo_runtime.matching import match_mutual_nn
from vo_runtime.pose import ransac_pose


@dataclass
class Similarity:
    """``x_lost = scale * rotation @ x_new + translation``: a point of the new map's world in the lost map's."""

    scale: float
    rotation: np.ndarray     # [3, 3]
    translation: np.ndarray  # [3]
    pairs: int               # landmarks of both maps that fixed the scale
    spread: float            # their depth ratios' median absolute deviation over the median (0: one scale)

    def point(self, positions: np.ndarray) -> np.ndarray:
        """[N, 3] points of the new world in the lost one."""
        return self.scale * positions @ self.rotation.T + self.translation

    def pose(self, pose_cw: np.ndarray) -> np.ndarray:
        """A world-to-camera pose in the new world, as one in the lost world (its translation rescaled)."""
        rotation = pose_cw[:3, :3] @ self.rotation.T
        out = np.eye(4)
        out[:3, :3] = rotation
        out[:3, 3] = self.scale * pose_cw[:3, 3] - rotation @ self.translation
        return out

    def relative(self, step: np.ndarray) -> np.ndarray:
        """A camera-to-camera transform (a motion, an anchor): the same rotation, its translation rescaled."""
        out = step.copy()
        out[:3, 3] *= self.scale
        return out


def similarity_from_views(pose_lost: np.ndarray, pose_new: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of the similarity that maps a camera's pose ``pose_new`` (world-to-camera, new
    world) onto ``pose_lost`` (the same camera in the lost world), given the ratio of the worlds' ``scale``."""
    rotation = pose_lost[:3, :3].T @ pose_new[:3, :3]
    translation = pose_lost[:3, :3].T @ (scale * pose_new[:3, 3] - pose_lost[:3, 3])
    return rotation, translation


def find_in_lost_map(lost: LocalMap, keyframes: list[int], points: np.ndarray, descriptors: np.ndarray,
                     new_positions: np.ndarray, pose_new: np.ndarray, threshold: float, min_pairs: int,
                     max_spread: float, max_distance: float, ratio: float | None) -> Similarity | None:
    """The similarity from a tracked frame's map to the ``lost`` one, or None.

    ``points`` [N, 2] normalised keypoints and ``descriptors`` [N, D] of a frame tracked on the new map at
    ``pose_new`` (world-to-camera), ``new_positions`` [N, 3] the new map's landmark at each keypoint (NaN: none).
    The landmarks of the lost map's ``keyframes`` together are matched to the frame and its pose in the lost map
    found by PnP RANSAC; it fixes the similarity when ``min_pairs`` of its inliers are landmarks of both maps, in
    front of both cameras, with depth ratios that agree to ``max_spread``. One search over all the keyframes'
    landmarks, not one a keyframe: in the dark each keyframe alone keeps too few (ORB: 4-9 such pairs).
    """
    ids = np.unique(np.concatenate([np.zeros(0, np.int64)] + [lost.keyframes[n].landmark_ids() for n in keyframes]))
    ids = ids[lost.alive[ids]]
    if len(ids) < min_pairs:
        return None
    matches = match_mutual_nn(lost.descriptors[ids], descriptors, max_distance, ratio)
    if len(matches) < min_pairs:
        return None
    world = lost.positions[ids[matches[:, 0]]]
    fit = ransac_pose(world, points[matches[:, 1]], threshold, min_pairs, iterations=200)
    if fit is None:
        return None
    pose_lost, inliers = fit
    rows = matches[inliers, 1]
    both = np.isfinite(new_positions[rows, 0])
    depth_lost = world[inliers][both] @ pose_lost[2, :3] + pose_lost[2, 3]
    depth_new = new_positions[rows[both]] @ pose_new[2, :3] + pose_new[2, 3]
    front = (depth_lost > 0) & (depth_new > 0)
    if np.count_nonzero(front) < min_pairs:
        return None
    ratios = depth_lost[front] / depth_new[front]
    scale = float(np.median(ratios))
    spread = float(np.median(np.abs(ratios - scale)) / scale)
    if spread > max_spread:
        return None
    rotation, translation = similarity_from_views(pose_lost, pose_new, scale)
    return Similarity(scale, rotation, translation, int(np.count_nonzero(front)), spread)
