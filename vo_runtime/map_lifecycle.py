"""`MapLifecycle`: how `MonoVO` starts a map (a two-view initialisation that succeeded) and throws one away (a
first map that failed its probation, `probation.py`, or was lost while young, ``VOConfig.young_map_lost_frames``; a map
the travel check found broken, `travel_check.py`).

A base class of `MonoVO` only, over its state (``self.map``, ``self._poses_cw``, ``self._probation``, ...), as
`KeyframeUpkeep` is: split from odometry.py so that file keeps the frame-by-frame states.
"""
from __future__ import annotations

import numpy as np

from vo_runtime.config import VOResult
from vo_runtime.geometry import invert_pose, per_frame_motion
from vo_runtime.localmap import Keyframe, LocalMap
from vo_runtime.map_merge import find_in_lost_map
from vo_runtime.states import INITIALISING, LOST, REINITIALISED, TRACKING
from vo_runtime.tracking import FrameData


class MapLifecycle:
    def _discard_map(self, index: int, frame: FrameData, result: VOResult) -> None:
        """The first map failed its probation: forget it as if it had never been built. Its frames go back to
        ``initialising`` with the reference frame's pose, and the next initialisation measures from this frame."""
        median = float(np.median(self._probation.values))
        self._retract_map(index, result)
        self._initialiser.restart(index, frame)
        result.problem = (f"map discarded: its frame-to-frame rotations disagreed with the frames' own by {median:.2f} "
                          f"deg (median of {len(self._probation.values)} frames)")

    def _young(self, frame_number: int, limit: int | None = None) -> bool:
        """The current map is the run's first map, ``frame_number`` is at most ``limit`` frames
        (``VOConfig.young_map_frames``) after its first keyframe, and the run may still discard a map."""
        limit = self.config.young_map_frames if limit is None else limit
        return (limit > 0 and self.map is not None and self._map_is_first
                and frame_number - self.map.keyframes[0].frame <= limit
                and self._probation.discards < self._probation.max_discards)

    def _young_map_lost(self, index: int) -> bool:
        """A young first map (`_young`, judged at the frame of the loss over the shorter of
        ``young_map_lost_frames`` and ``young_map_frames``) that the motion model no longer searches for
        (``lost_predict_frames``)."""
        limit = min(self.config.young_map_lost_frames, self.config.young_map_frames)
        return (self._lost_since >= 0 and index - self._last_tracked > self.config.lost_predict_frames
                and self._young(self._lost_since, limit))

    def _discard_young_map(self, index: int, result: VOResult, problem: str) -> None:
        """A young first map was lost or found broken: forget it as a failed probation would (from the same budget),
        so that the next map is a first one. The initialiser keeps whatever tracks it holds."""
        self._probation.discards += 1
        self._retract_map(index, result)
        result.problem = f"map discarded: {problem}"

    def _retract_map(self, index: int, result: VOResult) -> None:
        """Forget the map as if it had never been built: its frames up to ``index`` go back to ``initialising``
        with the map's reference frame's pose, and no speed is kept (the next map is a first map)."""
        first = self.map.keyframes[0].frame  # the map's reference frame
        held = self._poses_cw[first].copy()
        for number in range(first + 1, index + 1):
            self._poses_cw[number] = held.copy()
            if number < len(self.results):
                earlier = self.results[number]
                earlier.pose, earlier.status, earlier.tracked_by, earlier.keyframe = invert_pose(held), INITIALISING, None, False
        self._forget_map()
        self._probation.end()
        result.status, result.tracked_by, result.map_dropped = INITIALISING, None, True

    def _travel_broken(self, index: int, frame: FrameData, landmark: np.ndarray, pose_cw: np.ndarray,
                       result: VOResult, detections: int | None = None) -> bool:
        """The travel check's verdict on a tracked frame; a map judged broken is abandoned (True). It judges the
        first ``detections`` rows only (None: all): a landmark the flow followed (`flow_follow.py`) was found
        where the map said to look, so it would side with the map against the frames' own geometry."""
        if not self._travel.active:
            return False
        rows = slice(None, detections)
        degrees = self._travel.judge(index, landmark[rows], frame.points[rows], pose_cw,
                                     self.config.ransac_threshold_px / self._focal, keep=frame,
                                     pose_of=self._poses_cw.__getitem__, descriptors=frame.descriptors[rows])
        if degrees is None:
            return False
        self._abandon_map(index, frame, result, degrees)
        return True

    def _abandon_map(self, index: int, frame: FrameData, result: VOResult, degrees: float) -> None:
        """The travel check (`travel_check.py`) found the map's direction of travel broken: drop the map as a
        loss would, and initialise again from this frame at the median speed measured before the frames that
        judged it (a broken map shrinks its scale while it breaks). This frame is lost, its pose held. With
        ``VOConfig.young_map_travel`` a young first map is discarded instead (`_retract_map`), and the map built
        on the check's baseline is a first map."""
        check, frames = self._travel, self.config.speed_frames
        before = index - check.gap - check.frames
        speeds = [speed for number, speed in self._speed_log if number <= before][-frames:] or list(self._speeds)
        start = index - check.gap
        earlier = check.frame_at(start)  # before forgetting the map clears the check
        why = (f"its direction of travel disagreed with the frames' own geometry by {degrees:.0f} deg (median of "
               f"{check.frames} checks over {check.gap} frames)")
        if self.config.young_map_travel and self._young(index):
            self._discard_young_map(index, result, why)
        else:
            lost = self.map
            self._forget_map()
            self._keep_lost_map(lost, before)  # its keyframes before the frames that judged it broken
            self._speeds.extend(speeds)
            self._probation.end()
            result.status, result.tracked_by, result.map_dropped = LOST, None, True
            result.problem = f"map abandoned: {why}"
        # The check's first frame and this one are a baseline the essential matrix just found well
        # conditioned: initialise on it at once rather than wait for new parallax from here.
        if earlier is None:
            self._initialiser.restart(index, frame)
            return
        self._initialiser.restart(start, earlier)
        result.num_matches = self._initialiser.add(index, frame)
        outcome = self._initialiser.try_initialise(index, self._poses_cw, self._speed)
        if outcome is not None:
            self._start_map(index, outcome, result)
            result.problem += "; initialised again on it"

    def _start_map(self, index: int, outcome, result: VOResult) -> None:
        """A (re)initialisation succeeded: a new map of two keyframes."""
        reinitialised = self.map is not None or bool(self._speeds)
        if self.map is not None:  # lost, not thrown away: look for it again
            self._keep_lost_map(self.map, self.map.keyframes[-1].frame)
        self.map = LocalMap(outcome.current.descriptors.shape[1])
        self._anchors = {}
        reference, current = outcome.reference, outcome.current
        for frame_index, data in ((outcome.reference_index, reference), (index, current)):
            keyframe = Keyframe(frame_index, self._poses_cw[frame_index].copy(), data.points, data.pixels,
                                data.descriptors, np.full(len(data.points), -1, np.int64), data.gray, data.sigma)
            self._anchors[self.map.add_keyframe(keyframe)] = [(frame_index, np.eye(4))]
        self.map.add_landmarks(outcome.world, [(0, outcome.reference_rows), (1, outcome.current_rows)], outcome.angles)
        self._set_reference(1)
        self._previous = (current, self.map.keyframes[1].landmark)
        self.last_observations = (current.pixels, self.map.keyframes[1].landmark)
        self._last_tracked = index
        self._lost_since = -1
        self._velocity = per_frame_motion(self._poses_cw[index] @ invert_pose(self._poses_cw[outcome.reference_index]),
                                          index - outcome.reference_index)
        self._map_is_first = not reinitialised
        self._speeds.clear()
        self._speeds.append(outcome.speed)
        self._travel.clear()
        if reinitialised:
            self._probation.end()
        else:
            self._probation.begin()
        result.status = REINITIALISED if reinitialised else TRACKING
        result.tracked_by = "two-view"
        result.keyframe = True
        result.num_inliers = outcome.inliers
        result.num_landmarks = len(outcome.world)

    def _keep_lost_map(self, lost: LocalMap, until: int) -> None:
        """A map replaced after a loss is looked for by the next map (`_merge_lost_map`): its last
        ``relocalise_keyframes`` keyframes made at most at frame ``until``."""
        numbers = [number for number, keyframe in enumerate(lost.keyframes) if keyframe.frame <= until]
        if self.config.merge_keyframes > 0 and self.config.relocalise_keyframes > 0 and numbers:
            self._lost_map, self._merge_tries, self._merge_candidate = lost, self.config.merge_keyframes, None
            self._lost_keyframes = numbers[::-1][:self.config.relocalise_keyframes]

    def _merge_lost_map(self, index: int, frame: FrameData, landmark: np.ndarray, result: VOResult) -> None:
        """A keyframe-to-be of a map re-initialised after a loss looks for the lost map (`map_merge.py`); when
        found, the new map, the frames tracked on it and the motion model move into the lost map's frame and
        scale, and the lost map is let go (as it is after ``merge_keyframes`` tries)."""
        cfg = self.config
        self._merge_tries -= 1
        new_positions = np.full((len(landmark), 3), np.nan)
        seen = landmark >= 0
        new_positions[seen] = self.map.positions[landmark[seen]]
        found = find_in_lost_map(self._lost_map, self._lost_keyframes, frame.points, frame.descriptors,
                                 new_positions, self._poses_cw[index], cfg.pnp_threshold_px / self._focal,
                                 cfg.merge_min_pairs, cfg.merge_max_spread, cfg.match_max_distance, cfg.match_ratio)
        # Two keyframes in a row must find it at one scale: a single find on a dozen pairs can be a look-alike.
        confirmed = found is not None and self._merge_candidate is not None and \
            abs(found.scale / self._merge_candidate - 1) <= cfg.merge_max_spread
        self._merge_candidate = None if found is None else found.scale
        if not confirmed:
            if self._merge_tries <= 0:
                self._lost_map = None
            return
        self._lost_map, self._merge_candidate = None, None
        for keyframe in self.map.keyframes:
            keyframe.pose_cw = found.pose(keyframe.pose_cw)
        self.map.positions[:self.map.size] = found.point(self.map.positions[:self.map.size])
        for number, anchored in self._anchors.items():
            self._anchors[number] = [(frame_index, found.relative(relative)) for frame_index, relative in anchored]
            self._follow_keyframe(number)
        self._poses_cw[index] = found.pose(self._poses_cw[index])
        self._velocity = found.relative(self._velocity)
        self._speeds = type(self._speeds)((speed * found.scale for speed in self._speeds), self._speeds.maxlen)
        self._speed_log = type(self._speed_log)(((number, speed * found.scale) for number, speed in self._speed_log),
                                                self._speed_log.maxlen)
        self._travel.clear()  # its frames' poses were in the new map's frame
        result.merged_scale = found.scale
