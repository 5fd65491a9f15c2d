"""Feature tracks of `MonoVO`: per keypoint, where its track began and the landmark it carries."""
from __future__ import annotations

import numpy as np


class Tracks:
    """Per-keypoint track state, row-aligned with one frame's keypoints."""

    def __init__(self, frame_index: int, points: np.ndarray, pixels: np.ndarray) -> None:
        n = len(points)
        self.points = points                      # this frame, normalised image plane [N, 2]
        self.pixels = pixels                      # this frame, pixels [N, 2]
        self.first_points = points.copy()         # where each track began (normalised)
        self.first_pixels = pixels.copy()
        self.first_frame = np.full(n, frame_index)
        self.landmarks = np.full((n, 3), np.nan)  # world points, NaN where none
        self.angles = np.zeros(n)                 # ray angle when last triangulated (degrees)
        self.ids = track_ids(frame_index, np.arange(n))  # unique per track, for bundle adjustment
        self.resumed = np.zeros(n, bool)          # found again by a direct match after its chain broke

    def extend(self, previous: "Tracks", matches: np.ndarray) -> None:
        """Carry matched tracks over from the previous frame (matches: prev row, this row)."""
        i, j = matches[:, 0], matches[:, 1]
        for name in ("first_points", "first_pixels", "first_frame", "landmarks", "angles", "ids", "resumed"):
            getattr(self, name)[j] = getattr(previous, name)[i]

    def restart(self, rows: np.ndarray, frame_index: int) -> None:
        """Make `rows` begin afresh at this frame, without landmarks."""
        self._begin(rows, frame_index, rows, self.points[rows], self.pixels[rows], resumed=False)

    def resume(self, rows: np.ndarray, frame_index: int, first_rows: np.ndarray, first_points: np.ndarray,
               first_pixels: np.ndarray) -> None:
        """Make `rows` continue the tracks that began at ``first_rows`` of frame ``frame_index`` (found again
        by a direct match), without landmarks."""
        self._begin(rows, frame_index, first_rows, first_points, first_pixels, resumed=True)

    def _begin(self, rows: np.ndarray, frame_index: int, first_rows: np.ndarray, first_points: np.ndarray,
               first_pixels: np.ndarray, resumed: bool) -> None:
        self.first_points[rows] = first_points
        self.first_pixels[rows] = first_pixels
        self.first_frame[rows] = frame_index
        self.landmarks[rows] = np.nan
        self.angles[rows] = 0.0
        self.ids[rows] = track_ids(frame_index, first_rows)
        self.resumed[rows] = resumed

    @property
    def has_landmark(self) -> np.ndarray:
        return ~np.isnan(self.landmarks[:, 0])


def track_ids(frame_index: int, rows: np.ndarray) -> np.ndarray:
    """Track ids unique over a sequence: the frame a track (re)started in, and its row there."""
    return (np.int64(frame_index) << 20) | np.asarray(rows, np.int64)
