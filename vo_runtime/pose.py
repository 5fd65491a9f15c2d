"""Camera pose from 3D-2D correspondences: robust refinement from a predicted pose, and PnP RANSAC.

All image points are undistorted normalised coordinates; thresholds are in those units (pixels / focal).
"""
from __future__ import annotations

import cv2
import numpy as np

from vo_runtime.geometry import (camera_centre, left_increment, pose_from_rvec, projection_jacobian, reprojection_errors,
                                 rvec_from_pose)

# Refinement rounds as in mature feature-based VO: start with a loose gate (the prediction may be a few
# pixels off) and tighten it, re-fitting on the inliers of the previous round each time.
REFINE_GATES = (2.0, 1.0, 1.0)


def refine_pose(world: np.ndarray, image: np.ndarray, pose_cw: np.ndarray, threshold: float,
                min_inliers: int, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Levenberg-Marquardt refinement of ``pose_cw`` (world-to-camera) on the correspondences it explains.

    ``weights`` [N]: each correspondence's information (1 / its keypoint's variance, relative), None for equal
    weights (the inlier gates stay in pixels: a keypoint's expected error only weighs its residual). Returns
    (pose, inlier mask at ``threshold``), or None when fewer than ``min_inliers`` remain.
    """
    rvec, tvec = rvec_from_pose(pose_cw)
    inliers = np.ones(len(world), bool)
    for gate in REFINE_GATES:
        inliers = reprojection_errors(world, image, rvec, tvec) < gate * threshold
        if np.count_nonzero(inliers) < min_inliers:
            return None
        if weights is None:
            rvec, tvec = cv2.solvePnPRefineLM(world[inliers], image[inliers], np.eye(3), None, rvec, tvec,
                                              (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 10, 1e-10))
        else:
            pose = weighted_pose_fit(world[inliers], image[inliers], pose_from_rvec(rvec, tvec), weights[inliers])
            rvec, tvec = rvec_from_pose(pose)
    inliers = reprojection_errors(world, image, rvec, tvec) < threshold
    if np.count_nonzero(inliers) < min_inliers:
        return None
    return pose_from_rvec(rvec, tvec), inliers


def weighted_pose_fit(world: np.ndarray, image: np.ndarray, pose_cw: np.ndarray, weights: np.ndarray,
                      iterations: int = 10, min_decrease: float = 1e-6) -> np.ndarray:
    """Weighted least squares of the normalised reprojection errors by Levenberg-Marquardt from ``pose_cw``;
    world [N, 3], image [N, 2] normalised, weights [N]. Left increments, as the bundle adjustments'; stops when a
    step lowers the cost by less than ``min_decrease`` (relative)."""
    rows = np.repeat(weights, 2)

    def residuals(pose):
        cam = world @ pose[:3, :3].T + pose[:3, 3]
        return cam, (cam[:, :2] / cam[:, 2:3] - image).ravel()

    pose, damping = pose_cw, 1e-4
    cam, res = residuals(pose)
    cost = float(rows @ res ** 2)
    for _ in range(iterations):
        jac = projection_jacobian(cam)
        weighted = jac * rows[:, None]
        hessian, gradient = weighted.T @ jac, -(weighted.T @ res)
        improved = done = False
        while not improved and damping < 1e6:
            try:
                step = np.linalg.solve(hessian + damping * np.diag(np.diag(hessian) + 1e-12), gradient)
            except np.linalg.LinAlgError:
                damping *= 10
                continue
            trial = left_increment(pose, step)
            trial_cam, trial_res = residuals(trial)
            trial_cost = float(rows @ trial_res ** 2)
            if trial_cost < cost:
                improved, done = True, cost - trial_cost < min_decrease * cost
                pose, cam, res, cost, damping = trial, trial_cam, trial_res, trial_cost, max(damping / 10, 1e-9)
            else:
                damping *= 10
        if not improved or done:
            break
    return pose


def ransac_pose(world: np.ndarray, image: np.ndarray, threshold: float, min_inliers: int,
                iterations: int = 100) -> tuple[np.ndarray, np.ndarray] | None:
    """PnP RANSAC (SQPnP minimal solver) followed by `refine_pose`; for when no prediction can be trusted.

    No extrinsic guess goes to RANSAC: OpenCV 5.0's RANSAC with SOLVEPNP_ITERATIVE + useExtrinsicGuess
    returned the guess with every point flagged inlier (median error ~90 px on noise-free data).
    """
    if len(world) < max(min_inliers, 6):
        return None
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(world, image, np.eye(3), None, iterationsCount=iterations,
                                                 reprojectionError=threshold, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        # SQPnP asserts on a degenerate cloud: landmarks of a map whose scale collapsed, a hundred-thousandth
        # of the view's extent (ORB in the onboard light, 1,400 frames into the drone clip flown there and back
        # five times, crashed the VO here). No pose is the answer: the frame falls to the next fallback.
        return None
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    return refine_pose(world, image, pose_from_rvec(rvec, tvec), threshold, min_inliers)


def second_opinion(world: np.ndarray, image: np.ndarray, start_cw: np.ndarray, fit: tuple[np.ndarray, np.ndarray],
                   threshold: float, min_inliers: int, speed: float, max_jump: float,
                   min_share: float, floor_share: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``fit`` (a pose refined from ``start_cw``, the motion model's prediction), or the pose of PnP RANSAC on every
    match when ``fit`` shows both signs of a refinement that slid into the wrong basin and RANSAC explains more;
    or when ``fit`` explains fewer than ``floor_share`` of the matches, wherever it lies (0: never so).

    The signs: the camera centre jumped more than ``max_jump`` x ``speed`` (world units per frame) from the
    start, and fewer than ``min_share`` of the matches lie within ``threshold`` of their landmarks' projections.
    Measured on the dark EuRoC start at frame 100 (docs/vo_takeoff.md): the first frame after the first map was
    refined to a step 17 times too short that explained 36 of 70 matches, where the true pose explains 46; the
    keyframes made from it broke the map (0.515 m ATE). RANSAC finds a pose explaining 50. Its pose is refined on
    every match: refined on the proven landmarks alone (tracking's rule) it slid back to the wrong basin.
    """
    explained = int(np.count_nonzero(reprojection_errors(world, image, *rvec_from_pose(fit[0])) < threshold))
    if explained >= min_share * len(world):
        return fit
    jump = float(np.linalg.norm(camera_centre(fit[0]) - camera_centre(start_cw)))
    if jump <= max_jump * speed and explained >= floor_share * len(world):
        return fit
    other = ransac_pose(world, image, threshold, min_inliers)
    if other is None or np.count_nonzero(other[1]) <= explained:
        return fit
    return other
