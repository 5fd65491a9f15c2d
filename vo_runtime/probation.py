"""Probation of the first map: its rotations checked against rotations measured without any map.

A two-view initialisation on tracks with less parallax than noise (the drone's blurred take-off on EuRoC
MH_05, 2-5 mm of baseline at 3-8 m) builds a wrong map that then "tracks" every frame: on the onboard-light
take-off, 1.76 m of ATE with every frame reported as tracking. Its poses give it away in a quantity that needs
no scale: from one frame to the next, the rotation the map tracked disagreed with the rotation fitted to the two
frames' own detections (`rotation_fit.py`) by a median of 1.42 deg over its first 15 tracked frames (ORB's broken first maps on KITTI: 1.97 and 2.54),
against 0.11-0.72 deg for the healthy first maps of the dev sequences that were checked (EuRoC, TUM and KITTI
in every light; docs/vo_euroc.md). So a
young map whose median disagreement over ``VOConfig.probation_frames`` tracked frames exceeds
``probation_max_deg`` is discarded, and `MonoVO` initialises again from the current frame (as ORB-SLAM resets a
map lost within its first keyframes). Only the first map is on probation: a re-initialised one carries a scale
from before the loss, and dropping it would not give a better one.
"""
from __future__ import annotations

import numpy as np

from vo_runtime.rotation_fit import rotation_angle_deg, rotation_between


class MapProbation:
    """Collects a young map's rotation disagreements and gives the verdict once it has enough of them.

    Args:
        frames: consecutive tracked frames a verdict needs (0: no probation).
        max_deg: largest median disagreement a map may show.
        max_discards: maps one run may discard (a scene that fails every map keeps the third).
        max_distance, ratio: descriptor matching gates (`match_mutual_nn`), the VO's own.
    """

    def __init__(self, frames: int, max_deg: float, max_discards: int, max_distance: float,
                 ratio: float | None) -> None:
        self.frames, self.max_deg, self.max_discards = int(frames), float(max_deg), int(max_discards)
        self.max_distance, self.ratio = max_distance, ratio
        self.discards = 0
        self.values: list[float] = []
        self.active = False

    def begin(self) -> None:
        """A first map was built: judge it."""
        self.values = []
        self.active = self.frames > 0 and self.discards < self.max_discards

    def end(self) -> None:
        self.active = False

    def disagreement(self, previous_points: np.ndarray, previous_descriptors: np.ndarray, points: np.ndarray,
                     descriptors: np.ndarray, map_rotation: np.ndarray, focal: float) -> float | None:
        """Degrees between the map's rotation from the previous frame to this one (world-to-camera
        ``R_now @ R_previous.T``) and the rotation fitted to the two frames' matches; None with too few."""
        measured = rotation_between(previous_points, previous_descriptors, points, descriptors, focal,
                                    self.max_distance, self.ratio)
        return None if measured is None else rotation_angle_deg(measured[0].T @ map_rotation)

    def judge(self, value: float | None) -> bool:
        """Add one frame's disagreement; True when the map fails its probation (which then ends)."""
        if not self.active or value is None:
            return False
        self.values.append(value)
        if len(self.values) < self.frames:
            return False
        self.active = False
        if float(np.median(self.values)) <= self.max_deg:
            return False
        self.discards += 1
        return True
