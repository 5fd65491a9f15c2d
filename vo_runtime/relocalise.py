"""Relocalisation after a loss: find the frame's pose against the landmarks of recent keyframes.

No pose prediction can be trusted after a loss, so each candidate keyframe (newest first) is tried with
brute-force descriptor matching between its landmarks and the frame's keypoints, then PnP RANSAC. The
caller confirms a hit by tracking the local map from that pose.
"""
from __future__ import annotations

import numpy as np

from vo_runtime.localmap import LocalMap
from vo_runtime.matching import match_mutual_nn
from vo_runtime.pose import ransac_pose


def relocalise(local_map: LocalMap, points: np.ndarray, descriptors: np.ndarray, keyframes: int,
               threshold: float, min_inliers: int, max_distance: float, ratio: float | None,
               ) -> tuple[np.ndarray, int] | None:
    """Pose (world-to-camera) of a frame with normalised ``points`` and ``descriptors``, and the keyframe it
    was found against; None when none of the last ``keyframes`` keyframes gives ``min_inliers`` inliers."""
    for number in range(len(local_map.keyframes) - 1, max(-1, len(local_map.keyframes) - 1 - keyframes), -1):
        keyframe = local_map.keyframes[number]
        ids = keyframe.landmark_ids()
        ids = ids[local_map.alive[ids]]
        if len(ids) < min_inliers:
            continue
        pairs = match_mutual_nn(local_map.descriptors[ids], descriptors, max_distance, ratio)
        if len(pairs) < min_inliers:
            continue
        fit = ransac_pose(local_map.positions[ids[pairs[:, 0]]], points[pairs[:, 1]], threshold, min_inliers,
                          iterations=200)
        if fit is not None:
            return fit[0], number
    return None
