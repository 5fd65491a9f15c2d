"""`KeyframeUpkeep`: the keyframe half of `MonoVO` (when a tracked frame becomes a keyframe, and the mapping a
keyframe runs: new landmarks, local bundle adjustment, culling; frames anchored to a keyframe follow it).

A base class of `MonoVO` only, over its state (``self.map``, ``self.config``, ``self._anchors``, ...): split from
odometry.py to keep the frame-by-frame states readable there.
"""
from __future__ import annotations

import time

import numpy as np

from vo_runtime.config import VOResult
from vo_runtime.geometry import invert_pose
from vo_runtime.keyframe_pose import epipolar_matches, refine_with_epipolar
from vo_runtime.localmap import Keyframe
from vo_runtime.mapping import (consolidate_map, cull_landmarks, local_bundle_adjustment, observe_in_neighbours,
                                refresh_landmarks, triangulate_new_landmarks)
from vo_runtime.refine import align_rows
from vo_runtime.tracking import LOCAL_MAP, FrameData

ALIGN_KEYFRAMES = 12  # keyframes that keep their image for patch alignment (the local map's 8 and some)
# The map's horizon, in keyframes: tracking's local map and the mapping's partners and windows are covisible
# keyframes at most 30 back (`LocalMap.covisible`), a relocalisation tries the last 5. A keyframe this far back
# releases its descriptors, the landmarks only it and older ones observe die, and the ids of landmarks dead
# this long are reused, so a long flight's memory stops growing with the keyframes' descriptors (0.5 MB each)
# and the landmarks' arrays (docs/vo.md, "A long flight").
MAP_HORIZON_KEYFRAMES = 100


class KeyframeUpkeep:
    def _needs_keyframe(self, index: int, tracked: int, detected: int | None = None) -> bool:
        """ORB-SLAM's two reasons, simplified: the view has moved on, or too long since the last keyframe.
        ``tracked``: landmarks the frame tracked; ``detected``: those of them at the detector's keypoints
        (None: all), which alone can found new landmarks."""
        cfg = self.config
        reference = self.map.keyframes[self._reference_kf]
        since = index - self.map.keyframes[-1].frame
        if since >= cfg.keyframe_max_gap:
            return True
        if since >= cfg.keyframe_min_gap and (tracked if detected is None else detected) < cfg.keyframe_min_tracked:
            return True  # tracking is thinning out: new landmarks now, before it is lost
        # The reference keyframe's established landmarks (seen by 3+ keyframes; by 2 while the map is young):
        # a frame that tracks too small a share of them sees a view the map does not cover well.
        ids = reference.landmark_ids()
        established = np.count_nonzero(self.map.observation_counts(ids) >= min(3, len(self.map.keyframes)))
        return since >= cfg.keyframe_min_gap and tracked < cfg.keyframe_track_ratio * established

    def _insert_keyframe(self, index: int, frame: FrameData, landmark: np.ndarray, result: VOResult) -> None:
        keyframe = Keyframe(index, self._poses_cw[index].copy(), frame.points, frame.pixels, frame.descriptors,
                            landmark.copy(), frame.gray, frame.sigma)
        number = self.map.add_keyframe(keyframe)
        if number >= ALIGN_KEYFRAMES:  # bounded memory: older keyframes are rarely a landmark's latest view
            self.map.keyframes[number - ALIGN_KEYFRAMES].gray = None
        if number >= MAP_HORIZON_KEYFRAMES:
            behind = number - MAP_HORIZON_KEYFRAMES
            self.map.release_descriptors(behind)
            self.map.retire(behind)
            self.map.recycle(behind)
        self._anchors[number] = [(index, np.eye(4))]
        job = lambda: self._map_keyframe(number, frame, keyframe, result)  # noqa: E731
        if self.config.mapping_thread:
            self._mapping_job = job
        else:
            job()

    def _map_keyframe(self, number: int, frame: FrameData, keyframe: Keyframe, result: VOResult) -> None:
        """New landmarks, local bundle adjustment and culling for keyframe ``number``."""
        cfg, mapping, focal = self.config, self._mapping_config, self._focal
        start = time.perf_counter()
        # Not while the first map is on probation: the probation judges the map that tracking built, and a
        # broken map whose keyframes were corrected passed it and then failed in the turn (docs/vo_takeoff.md).
        if mapping.keyframe_epipolar_weight > 0 and number > 0 and not self._probation.active:
            self._refine_keyframe_pose(number)
        refresh_landmarks(self.map, number, mapping, focal)
        triangulate_new_landmarks(self.map, number, mapping, focal, cfg.match_max_distance, cfg.match_ratio,
                                  self._align if self._aligner is not None else None, self._detection_scale,
                                  wide_partner=result.tracked_by == LOCAL_MAP,
                                  baseline_rule=self._young(keyframe.frame))
        observe_in_neighbours(self.map, number, mapping, focal, cfg.match_max_distance, cfg.match_ratio,
                              self._align if self._aligner is not None else None)
        for moved in local_bundle_adjustment(self.map, number, mapping, focal):
            self._follow_keyframe(moved)
        if number + 1 == mapping.consolidate_keyframes:
            for moved in consolidate_map(self.map, mapping, focal):
                self._follow_keyframe(moved)
        cull_landmarks(self.map, number, mapping)
        self._previous = (frame, keyframe.landmark)  # the adjustment may have dropped observations
        self._set_reference(number)
        result.mapping_ms = 1e3 * (time.perf_counter() - start)

    def _refine_keyframe_pose(self, number: int) -> None:
        """The new keyframe's pose on its landmarks and its epipolar geometry to the previous keyframe
        (`keyframe_pose.py`); frames anchored to it follow."""
        cfg, mapping, focal = self.config, self._mapping_config, self._focal
        new, previous = self.map.keyframes[number], self.map.keyframes[number - 1]
        rows = np.flatnonzero(new.landmark >= 0)
        if len(rows) < cfg.min_pnp_inliers:
            return  # too few landmarks to hold the translation: no matching spent on it
        points_a, points_b = epipolar_matches(previous.points, previous.descriptors, new.points, new.descriptors,
                                              previous.pose_cw, new.pose_cw, mapping.keyframe_epipolar_gate_px / focal,
                                              cfg.match_max_distance, cfg.match_ratio)
        if len(points_a) < cfg.min_pnp_inliers:
            return
        new.pose_cw = refine_with_epipolar(new.pose_cw, self.map.positions[new.landmark[rows]], new.points[rows],
                                           previous.pose_cw, points_a, points_b,
                                           mapping.keyframe_epipolar_scale_px / focal, mapping.keyframe_epipolar_weight)
        self._follow_keyframe(number)

    def _align(self, source, target, source_rows: np.ndarray, target_rows: np.ndarray) -> None:
        align_rows(self._aligner, source, target, source_rows, target_rows, self.camera.normalise)

    def _follow_keyframe(self, number: int) -> None:
        """Frames anchored to a keyframe the adjustment moved move with it (results included)."""
        keyframe_pose = self.map.keyframes[number].pose_cw
        for frame, relative in self._anchors.get(number, []):
            self._poses_cw[frame] = relative @ keyframe_pose
            if frame < len(self.results):
                self.results[frame].pose = invert_pose(self._poses_cw[frame])

    def _set_reference(self, number: int) -> None:
        self._reference_kf = number
        local = [number] + self.map.covisible(number, self.config.local_keyframes - 1)
        self._local_ids = self.map.landmarks_of(local)
