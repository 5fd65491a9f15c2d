"""Two-view initialisation of `MonoVO`: frame-to-frame tracks from a reference frame (broken ones found
again while the chains die) until they moved far enough, then the relative pose (`twoview.py`) and the
first landmarks.

The tracks (`tracks.py`) only serve this phase: once a map exists, frames are tracked against it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from vo_runtime.features import Features
from vo_runtime.geometry import make_pose, ray_angles, triangulate
from vo_runtime.matching import match_mutual_nn
from vo_runtime.probation import rotation_angle_deg
from vo_runtime.tracking import FrameData
from vo_runtime.tracks import Tracks
from vo_runtime.twoview import relative_pose_hypotheses

ROW_MASK = (1 << 20) - 1  # track id -> keypoint row in the frame the track began (see tracks.track_ids)


@dataclass
class Initialisation:
    """A committed two-view initialisation: both views and the landmarks triangulated between them."""

    reference_index: int
    reference: FrameData
    current: FrameData
    reference_rows: np.ndarray  # keypoint rows of the landmarks in the reference frame
    current_rows: np.ndarray    # ... and in the current frame
    world: np.ndarray           # [M, 3] landmark positions
    angles: np.ndarray          # [M] ray angles between the two views, degrees
    inliers: int                # correspondences consistent with the chosen model
    speed: float                # world units per frame over the baseline


class Initialiser:
    def __init__(self, config, focal: float) -> None:
        self.config, self.focal = config, focal  # focal: pixels per normalised unit, for the thresholds
        self.model: str | None = None     # essential or homography, of the last initialisation
        self.reference = -1               # frame the next initialisation measures from
        self._reference_frame: FrameData | None = None
        self._previous: tuple[FrameData, Tracks] | None = None
        # align(source, target, source_rows, target_rows): patch alignment (`refine.py`) of the current
        # frame's track ends onto the reference frame before the two-view fit; None: off.
        self.align: Callable | None = None

    def restart(self, index: int, frame: FrameData, features: Features | None = None) -> None:
        """Measure the next initialisation from this frame."""
        self.reference, self._reference_frame = index, frame
        self._previous = (frame, Tracks(index, frame.points, frame.pixels))

    def _measure_from(self, index: int, frame: FrameData, poses_cw: list[np.ndarray]) -> None:
        """Give up the reference: this frame, at the reference's pose, is the next one."""
        poses_cw[index] = poses_cw[self.reference].copy()
        self.restart(index, frame)

    def add(self, index: int, frame: FrameData, features: Features | None = None) -> int:
        """Extend the tracks with this frame; returns the frame-to-frame matches."""
        if self._previous is None:
            self.restart(index, frame)
            return 0
        last, last_tracks = self._previous
        matches = match_mutual_nn(last.descriptors, frame.descriptors, self.config.match_max_distance,
                                  self.config.match_ratio)
        tracks = Tracks(index, frame.points, frame.pixels)
        tracks.extend(last_tracks, matches)
        self._refind(tracks, frame)
        self._previous = (frame, tracks)
        return len(matches)

    def _refind(self, tracks: Tracks, frame: FrameData) -> None:
        """Match the reference keypoints whose track broke directly to this frame's keypoints that carry no
        track from the reference (mutual nearest neighbours with the ratio test), and resume those tracks.

        A chain of frame-to-frame matches breaks at its weakest link: in simulated low light (KITTI 07) 25 %
        of the tracks died per frame, and seven frames on, direct matches against the reference gave 137
        essential-matrix inliers against 64 for the surviving chains; the two-view fit had too few points
        and the first map waited until frame 43."""
        reference = self._reference_frame
        alive = tracks.first_frame == self.reference
        if np.count_nonzero(alive & ~tracks.resumed) >= 3 * self.config.min_matches:
            return  # the chains are not dying (as `try_initialise` counts them): left alone
        lost = np.setdiff1d(np.arange(len(reference.points)), tracks.ids[alive] & ROW_MASK)
        free = np.flatnonzero(~alive)
        if len(lost) == 0 or len(free) == 0:
            return
        pairs = match_mutual_nn(reference.descriptors[lost], frame.descriptors[free], self.config.match_max_distance,
                                self.config.match_ratio)
        rows, found = lost[pairs[:, 0]], free[pairs[:, 1]]
        tracks.resume(found, self.reference, rows, reference.points[rows], reference.pixels[rows])

    def try_initialise(self, index: int, poses_cw: list[np.ndarray], speed: float | None) -> Initialisation | None:
        """Two-view initialisation from the reference frame; on success sets ``poses_cw[index]``.

        ``speed`` (world units per frame before a loss) scales a re-initialisation; None for the first one,
        whose baseline is ``initial_baseline``.
        """
        cfg = self.config
        if self._previous is None or self.reference == index:
            return None
        frame, tracks = self._previous
        rows = np.flatnonzero(tracks.first_frame == self.reference)
        # Survival is judged on the unbroken chains: resumed tracks (`_refind`) add points to the fit, but
        # never keep an old reference alive, nor its short-baseline gate in force.
        chained = int(np.count_nonzero(~tracks.resumed[rows]))
        if chained < cfg.min_matches:
            self._measure_from(index, frame, poses_cw)  # too few tracks survive from the reference
            return None
        motion = np.median(np.linalg.norm(tracks.pixels[rows] - tracks.first_pixels[rows], axis=1))
        # Tracks from the reference die off, and the survivors are the slow, distant points: when few are
        # left, try with less motion rather than lose the reference. The ray-angle gate below still applies:
        # waiving it too let the dark EuRoC take-off build its first map on a few frames of little motion
        # (from frames 20 and 30: 0.097 and 0.176 m, with the gate 0.022 and 0.026; docs/vo_euroc.md).
        dying = chained < 3 * cfg.min_matches
        if motion < (cfg.init_min_parallax_px / 3 if dying else cfg.init_min_parallax_px):
            return None
        if self.align is not None:
            self.align(self._reference_frame, frame, tracks.ids[rows] & ROW_MASK, rows)
        pts_ref, pts_cur = tracks.first_points[rows], tracks.points[rows]
        frames = index - self.reference
        scale = (speed or cfg.initial_baseline) * frames if speed is not None else cfg.initial_baseline
        ref_pose = poses_cw[self.reference]
        # Keep the hypothesis that triangulates the most points (in front, small error, enough parallax).
        best = []
        for hypothesis in relative_pose_hypotheses(pts_ref, pts_cur, cfg.ransac_threshold_px / self.focal):
            explained = np.count_nonzero(hypothesis.inliers)
            if explained < cfg.init_min_landmarks or explained < cfg.init_min_inlier_share * len(rows):
                continue
            pose = make_pose(hypothesis.rotation, scale * hypothesis.translation) @ ref_pose
            inliers = rows[hypothesis.inliers]
            world, error = triangulate(ref_pose, pose, pts_ref[hypothesis.inliers], pts_cur[hypothesis.inliers])
            angles = ray_angles(ref_pose, pose, pts_ref[hypothesis.inliers], pts_cur[hypothesis.inliers])
            good = (error < cfg.triangulation_threshold_px / self.focal) & (angles >= cfg.min_triangulation_deg)
            best.append((int(np.count_nonzero(good)), hypothesis.model, pose, inliers, world, angles, good))
        best.sort(key=lambda item: -item[0])
        if not best or best[0][0] < cfg.init_min_landmarks:
            if best and speed is not None and 0 < cfg.reinit_max_turn_deg < \
                    rotation_angle_deg(best[0][2][:3, :3] @ ref_pose[:3, :3].T):
                # A re-initialisation's reference the camera has turned away from: its tracks still match,
                # but few of them triangulate well, and they only get fewer.
                self._measure_from(index, frame, poses_cw)
            return None
        if best[0][0] < cfg.init_wanted_landmarks and not dying:
            return None  # a richer first map may come with a few more frames of motion
        if len(best) > 1 and best[1][0] > 0.75 * best[0][0]:
            return None  # ambiguous homography decomposition: wait for more motion
        _, self.model, pose, inliers, world, angles, good = best[0]
        if np.median(angles[good]) < (cfg.init_min_median_deg if speed is None else cfg.reinit_min_median_deg):
            return None  # a short baseline: depths from it would set a poor first scale and map
        poses_cw[index] = pose
        landmark_rows = inliers[good]
        result = Initialisation(self.reference, self._reference_frame, frame,
                                tracks.ids[landmark_rows] & ROW_MASK, landmark_rows, world[good], angles[good],
                                len(inliers), scale / frames)
        self._previous = None  # the map takes over; a later loss restarts the tracks
        return result
