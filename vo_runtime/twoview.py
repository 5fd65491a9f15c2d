"""Two-view relative pose for initialisation, choosing between a homography and an essential matrix.

As in ORB-SLAM: both models are fitted with RANSAC and scored by their truncated symmetric transfer
errors; the homography wins when ``S_H / (S_H + S_E) > 0.45`` (a plane, or too little translation for
the epipolar geometry to be stable). A homography gives up to four (R, t) hypotheses; the caller keeps
the one that triangulates most points in front of both cameras.
All points are undistorted normalised image coordinates [N, 2]; ``sigma`` is one pixel in those units.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

CHI2_1DOF, CHI2_2DOF = 3.841, 5.991  # 95 % gates for a line distance (E) and a point distance (H)
HOMOGRAPHY_RATIO = 0.45
FAR_POINT_BASELINES = 1e4  # cv2.recoverPose's cheirality test keeps points up to this many baselines away


@dataclass
class Hypothesis:
    """Relative pose of view b from view a: x_b ~ R x_a + t, with |t| = 1; ``inliers`` masks the points."""

    model: str
    rotation: np.ndarray
    translation: np.ndarray
    inliers: np.ndarray


def _homogeneous(points: np.ndarray) -> np.ndarray:
    return np.concatenate([points, np.ones((len(points), 1))], axis=1)


def homography_score(h: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray, sigma: float) -> tuple[float, np.ndarray]:
    """Truncated score of a homography a -> b over both transfer directions, and its inlier mask."""
    score, inliers = np.zeros(len(pts_a)), np.ones(len(pts_a), bool)
    for mat, src, dst in ((h, pts_a, pts_b), (np.linalg.inv(h), pts_b, pts_a)):
        proj = _homogeneous(src) @ mat.T
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.sum((proj[:, :2] / proj[:, 2:] - dst) ** 2, axis=1) / sigma**2
        err = np.nan_to_num(err, nan=np.inf)
        inliers &= err < CHI2_2DOF
        score += np.where(err < CHI2_2DOF, CHI2_2DOF - err, 0.0)
    return float(np.sum(score * inliers)), inliers


def essential_score(e: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray, sigma: float) -> tuple[float, np.ndarray]:
    """Truncated score of an essential matrix from point-to-epipolar-line distances in both views."""
    xa, xb = _homogeneous(pts_a), _homogeneous(pts_b)
    score, inliers = np.zeros(len(pts_a)), np.ones(len(pts_a), bool)
    for lines, pts in ((xa @ e.T, xb), (xb @ e, xa)):
        err = np.sum(lines * pts, axis=1) ** 2 / (lines[:, 0] ** 2 + lines[:, 1] ** 2 + 1e-30) / sigma**2
        inliers &= err < CHI2_1DOF
        score += np.where(err < CHI2_1DOF, CHI2_2DOF - err, 0.0)
    return float(np.sum(score * inliers)), inliers


def relative_pose_hypotheses(pts_a: np.ndarray, pts_b: np.ndarray, sigma: float) -> list[Hypothesis]:
    """Fit both models, pick one by score ratio, and return its pose hypotheses (empty if neither fits)."""
    if len(pts_a) < 8:
        return []
    essential, mask_e = cv2.findEssentialMat(pts_a, pts_b, np.eye(3), cv2.RANSAC, 0.999, sigma)
    homography, _ = cv2.findHomography(pts_a, pts_b, cv2.RANSAC, 2.0 * sigma)
    score_e = score_h = 0.0
    if essential is not None and essential.shape[0] >= 3:
        essential = essential[:3]
        score_e, _ = essential_score(essential, pts_a, pts_b, sigma)
    if homography is not None and abs(np.linalg.det(homography)) > 1e-12:
        score_h, inliers_h = homography_score(homography, pts_a, pts_b, sigma)
    if score_e == 0.0 and score_h == 0.0:
        return []
    if score_h / (score_h + score_e) > HOMOGRAPHY_RATIO:
        _, rotations, translations, _ = cv2.decomposeHomographyMat(homography, np.eye(3))
        return [Hypothesis("homography", r, t.ravel() / np.linalg.norm(t), inliers_h)
                for r, t in zip(rotations, translations) if np.linalg.norm(t) > 1e-9]
    # distanceThresh: OpenCV's default (50) drops every point further than 50 baselines as "at infinity"; a
    # drone creeping through a hall sees most points that far early on (EuRoC MH_05: depths of 3-8 m over a
    # 5-10 cm baseline), so the essential matrix's inliers all but vanished (5 % of the tracks). Far points
    # still obey the epipolar constraint; the triangulation's ray-angle gate rejects them as landmarks.
    _, rotation, translation, mask, _ = cv2.recoverPose(essential, pts_a, pts_b, np.eye(3),
                                                        distanceThresh=FAR_POINT_BASELINES, mask=mask_e)
    return [Hypothesis("essential", rotation, translation.ravel(), mask.ravel() > 0)]
