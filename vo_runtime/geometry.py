"""Small pose helpers (4x4 homogeneous transforms, float64)."""
from __future__ import annotations

import cv2
import numpy as np


LARGEST = np.finfo(np.float64).max


IDENTITY_POSE = np.eye(4)


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    pose = IDENTITY_POSE.copy()  # a copy of one identity: np.eye costs more than the rest (5,000 calls a clip)
    pose[:3, :3] = rotation
    pose[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    rotation = pose[:3, :3]
    return make_pose(rotation.T, -rotation.T @ pose[:3, 3])


def pose_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_pose(cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0], tvec)



def left_increment(pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``pose`` [4, 4] (world-to-camera) moved by a left increment ``delta`` = (rotation vector, translation) [6]:
    cam = Exp(w) (R X + t) + tau, the update the bundle adjustments and `keyframe_pose` solve for."""
    step = cv2.Rodrigues(np.asarray(delta[:3], np.float64).reshape(3, 1))[0]
    return make_pose(step @ pose[:3, :3], step @ pose[:3, 3] + delta[3:])


def projection_jacobian(cam: np.ndarray) -> np.ndarray:
    """d(x/z, y/z) / d(rotation vector, translation) of a left increment cam = Exp(w) cam + tau, for camera
    points ``cam`` [N, 3]: [2N, 6], rows (u, v) per point, as `keyframe_pose` and `pose.weighted_pose_fit` use."""
    inverse_depth = 1.0 / cam[:, 2]
    u, v = cam[:, 0] * inverse_depth, cam[:, 1] * inverse_depth
    # Entries written in place (a third of the time of stacking the columns; the same values)
    jacobian = np.zeros((len(cam), 2, 6))
    row_u, row_v = jacobian[:, 0], jacobian[:, 1]
    row_u[:, 0], row_u[:, 1], row_u[:, 2], row_u[:, 3], row_u[:, 5] = -u * v, 1 + u * u, -v, inverse_depth, -u * inverse_depth
    row_v[:, 0], row_v[:, 1], row_v[:, 2], row_v[:, 4], row_v[:, 5] = -1 - v * v, u * v, u, inverse_depth, -v * inverse_depth
    return jacobian.reshape(-1, 6)


def rvec_from_pose(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 world-to-camera pose -> OpenCV (rvec [3, 1], tvec [3, 1])."""
    return cv2.Rodrigues(pose[:3, :3])[0], pose[:3, 3].reshape(3, 1).copy()


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def triangulate(
    pose_a: np.ndarray, pose_b: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate normalised points seen from two world-to-camera poses.

    Returns world points [N, 3] and, per point, the largest reprojection error in the two views (normalised
    units; infinite where the point lies behind either camera).
    """
    if len(pts_a) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    homog = cv2.triangulatePoints(pose_a[:3], pose_b[:3], pts_a.T.astype(np.float64), pts_b.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        world = (homog[:3] / homog[3]).T
    error = np.zeros(len(world))
    for pose, pts in ((pose_a, pts_a), (pose_b, pts_b)):
        cam = world @ pose[:3, :3].T + pose[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = cam[:, :2] / cam[:, 2:3]
            err = np.linalg.norm(proj - pts, axis=1)
        err[~(cam[:, 2] > 0)] = np.inf
        error = np.maximum(error, np.where(np.isnan(err), np.inf, err))
    return world, error


def reprojection_errors(world: np.ndarray, image: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Normalised-plane reprojection errors [N] of world points [N, 3] against observations [N, 2]."""
    cam = world @ cv2.Rodrigues(rvec)[0].T + tvec.reshape(3)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        offset = cam[:, :2] / cam[:, 2:] - image
        err = np.sqrt(offset[:, 0] * offset[:, 0] + offset[:, 1] * offset[:, 1])  # np.linalg.norm's sum, in its order
    # As np.nan_to_num(err, nan=inf) (an infinite error becomes the largest float), a fifth of its time: the pose
    # fit calls this a dozen times a frame.
    return np.where(cam[:, 2] > 0, np.where(np.isnan(err), np.inf, np.minimum(err, LARGEST)), np.inf)


def camera_centre(pose_cw: np.ndarray) -> np.ndarray:
    return -pose_cw[:3, :3].T @ pose_cw[:3, 3]


def ray_angles(poses_a: np.ndarray, pose_b: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between the world-frame viewing rays of normalised points seen from two poses.

    ``poses_a`` is one world-to-camera pose or one per point ([N, 4, 4]).
    """
    rays_a = np.concatenate([pts_a, np.ones((len(pts_a), 1))], axis=1)
    rays_b = np.concatenate([pts_b, np.ones((len(pts_b), 1))], axis=1)
    rot_a = np.asarray(poses_a)[..., :3, :3]
    world_a = np.einsum("...ji,...j->...i", rot_a, rays_a) if rot_a.ndim == 3 else rays_a @ rot_a
    world_b = rays_b @ pose_b[:3, :3]
    cos = np.sum(world_a * world_b, axis=1) / (np.linalg.norm(world_a, axis=1) * np.linalg.norm(world_b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def per_frame_motion(motion: np.ndarray, frames: int) -> np.ndarray:
    """The constant per-frame motion that adds up to ``motion`` over ``frames`` frames (rotation angle and
    translation divided evenly; close enough to seed the motion model)."""
    rvec = cv2.Rodrigues(motion[:3, :3])[0] / frames
    return make_pose(cv2.Rodrigues(rvec)[0], motion[:3, 3] / frames)
