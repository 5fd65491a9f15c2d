"""The map `MonoVO` tracks against: keyframes and the landmarks they observe.

A keyframe keeps its pose, its keypoints (pixels and normalised), their descriptors and, per keypoint, the
landmark it observes (-1 where none). A landmark keeps its position, a representative descriptor (the
medoid of its last few keyframe observations, so it stays matchable from several viewpoints), the
keyframes that observe it, and two counters for culling: how often it was predicted inside a tracked
frame (``visible``) and how often it was matched there (``found``).

Landmark ids are rows of the arrays here; dead landmarks keep their row (``alive`` is False) so ids stay
valid, until `recycle` gives rows dead for long enough (`keyframing.MAP_HORIZON_KEYFRAMES`) to new
landmarks. Arrays grow by doubling, so adding a keyframe's landmarks does not copy the whole map each time.
"""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass
from itertools import chain

import numpy as np

# The per-landmark arrays, one row per landmark id (grown together by `LocalMap._reserve`).
LANDMARK_ARRAYS = ("positions", "descriptors", "alive", "visible", "found", "created", "angles")
DESCRIPTOR_OBSERVATIONS = 4  # observations the representative descriptor is chosen from (the latest ones)


@dataclass
class Keyframe:
    frame: int               # index of the frame it was made from
    pose_cw: np.ndarray      # world-to-camera 4x4
    points: np.ndarray       # normalised image points [N, 2]
    pixels: np.ndarray       # [N, 2]
    descriptors: np.ndarray | None  # [N, D], unit rows; None once released (`LocalMap.release_descriptors`)
    landmark: np.ndarray     # [N] landmark id observed by each keypoint, -1 where none
    gray: np.ndarray | None = None  # the frame, uint8, for patch alignment (`refine.py`); dropped when old
    sigma: np.ndarray | None = None  # [N] keypoints' expected position errors, relative (`FrameData.sigma`)

    def landmark_ids(self) -> np.ndarray:
        return self.landmark[self.landmark >= 0]


class LocalMap:
    """Keyframes and landmarks; all bookkeeping between them goes through these methods."""

    def __init__(self, descriptor_size: int) -> None:
        self.keyframes: list[Keyframe] = []
        self.size = 0
        capacity = 1024
        self.positions = np.zeros((capacity, 3))
        self.descriptors = np.zeros((capacity, descriptor_size), np.float32)
        self.alive = np.zeros(capacity, bool)
        self.visible = np.zeros(capacity, np.int64)
        self.found = np.zeros(capacity, np.int64)
        self.created = np.zeros(capacity, np.int64)   # keyframe that created it
        self.angles = np.zeros(capacity)              # ray angle (degrees) of the views it was triangulated from
        self.observations: list[dict[int, int]] = []  # per landmark: keyframe -> keypoint row
        # Ids of dead landmarks, batched by the keyframe count at their death: `recycle` hands them to new
        # landmarks once no frame's state can still name them, so a long flight's arrays stop growing.
        self._dead: deque[tuple[int, list[int]]] = deque()
        self._free: list[int] = []

    # ------------------------------------------------------------------ building
    def add_keyframe(self, keyframe: Keyframe) -> int:
        """Append a keyframe whose ``landmark`` column names landmarks it matched; record those observations."""
        self.keyframes.append(keyframe)
        number = len(self.keyframes) - 1
        rows = np.flatnonzero(keyframe.landmark >= 0)
        ids = keyframe.landmark[rows]
        alive = self.alive[ids]
        keyframe.landmark[rows[~alive]] = -1
        for landmark, row in zip(ids[alive].tolist(), rows[alive].tolist()):
            self.observations[landmark][number] = row
        self._update_descriptors(ids[alive])
        return number

    def add_landmarks(self, positions: np.ndarray, seen_by: list[tuple[int, np.ndarray]],
                      angles: np.ndarray) -> np.ndarray:
        """New landmarks at ``positions``, triangulated from rays ``angles`` (degrees) apart and observed by
        each (keyframe, keypoint rows) in ``seen_by``. The last keyframe listed is the creating one. Returns
        their ids."""
        count = len(positions)
        reused, self._free = self._free[:count], self._free[count:]
        fresh = count - len(reused)
        self._reserve(self.size + fresh)
        ids = np.concatenate([np.asarray(reused, np.int64), np.arange(self.size, self.size + fresh)])
        self.size += fresh
        self.positions[ids] = positions
        self.angles[ids] = angles
        self.alive[ids] = True
        self.visible[ids] = self.found[ids] = 1
        self.created[ids] = seen_by[-1][0]
        self.observations.extend({} for _ in range(fresh))  # a reused id's observations were emptied at its death
        for number, rows in seen_by:
            self.keyframes[number].landmark[rows] = ids
            for landmark, row in zip(ids.tolist(), rows.tolist()):
                self.observations[landmark][number] = row
        self._update_descriptors(ids)
        return ids

    def add_observations(self, number: int, landmarks: np.ndarray, rows: np.ndarray) -> None:
        """Keyframe ``number``'s keypoints ``rows`` observe ``landmarks`` (found after the keyframe was made);
        each landmark's observations stay in keyframe order, so its first is still its oldest view. The
        representative descriptors are left as they are (they come from the latest views)."""
        keyframe = self.keyframes[number]
        keyframe.landmark[rows] = landmarks
        for landmark, row in zip(np.asarray(landmarks).tolist(), np.asarray(rows).tolist()):
            seen = self.observations[landmark]
            seen[number] = row
            self.observations[landmark] = dict(sorted(seen.items()))

    def remove_observations(self, landmarks: np.ndarray, keyframes: np.ndarray) -> None:
        """Drop the observation of each landmark in the matching keyframe; a landmark left with fewer than
        two observations cannot be triangulated and dies."""
        for landmark, number in zip(landmarks.tolist(), keyframes.tolist()):
            row = self.observations[landmark].pop(number, None)
            if row is not None:
                self.keyframes[number].landmark[row] = -1
            if len(self.observations[landmark]) < 2:
                self.kill(np.array([landmark]))

    def kill(self, landmarks: np.ndarray) -> None:
        died = []
        for landmark in np.asarray(landmarks).tolist():
            if not self.alive[landmark]:
                continue
            self.alive[landmark] = False
            for number, row in self.observations[landmark].items():
                self.keyframes[number].landmark[row] = -1
            self.observations[landmark] = {}
            died.append(landmark)
        if died:
            self._dead.append((len(self.keyframes), died))

    def retire(self, number: int) -> None:
        """Kill the landmarks no keyframe after ``number`` observes: keyframe ``number`` is so old that
        tracking's local map and the mapping's windows (recent covisible keyframes) no longer reach them."""
        ids = self.keyframes[number].landmark_ids()
        self.kill(np.array([i for i in ids.tolist() if max(self.observations[i]) <= number], np.int64))

    def recycle(self, before: int) -> None:
        """Free for reuse the ids of landmarks that died while the map held at most ``before`` keyframes."""
        while self._dead and self._dead[0][0] <= before:
            self._free.extend(self._dead.popleft()[1])

    # ------------------------------------------------------------------ queries
    def covisible(self, number: int, count: int, recent: int = 30) -> list[int]:
        """Up to ``count`` keyframes sharing the most landmarks with keyframe ``number`` (searched among the
        ``recent`` keyframes before and after it), best first."""
        return [k for k, _ in self.covisible_counts(number, count, recent)]

    def covisible_counts(self, number: int, count: int, recent: int = 30) -> list[tuple[int, int]]:
        """`covisible` with the landmarks each shares: [(keyframe, shared)], best first."""
        # Counted from the landmarks' own observation lists (a keyframe observes a landmark at most once):
        # the same counts as intersecting every recent keyframe's landmark column, at a fifth of the cost.
        # Counter over the chained keys: the same counts as a loop, counted in C (~5x faster)
        shared = Counter(chain.from_iterable(map(self.observations.__getitem__,
                                                 self.keyframes[number].landmark_ids().tolist())))
        ranked = sorted(((n, k) for k, n in shared.items() if k != number and abs(k - number) <= recent),
                        key=lambda item: (-item[0], -item[1]))
        return [(k, n) for n, k in ranked[:count]]

    def landmarks_of(self, keyframes: list[int]) -> np.ndarray:
        """Unique alive landmark ids observed by any of ``keyframes``."""
        if not keyframes:
            return np.zeros(0, np.int64)
        ids = np.unique(np.concatenate([self.keyframes[k].landmark_ids() for k in keyframes]))
        return ids[self.alive[ids]]

    def release_descriptors(self, number: int) -> None:
        """Forget keyframe ``number``'s descriptors (its pose, keypoints and observations stay): the search for
        new landmarks and the neighbour search only read recent keyframes' descriptors, and at 512 x 256 floats
        they are 0.5 MB of the ~0.52 MB a keyframe holds, so a long flight's memory stops growing with them."""
        self.keyframes[number].descriptors = None

    def observation_counts(self, landmarks: np.ndarray) -> np.ndarray:
        return np.fromiter(map(len, map(self.observations.__getitem__, landmarks.tolist())), np.int64, len(landmarks))

    # ------------------------------------------------------------------ internals
    def _reserve(self, size: int) -> None:
        capacity = len(self.alive)
        if size <= capacity:
            return
        while capacity < size:
            capacity *= 2
        for name in LANDMARK_ARRAYS:
            old = getattr(self, name)
            grown = np.zeros((capacity,) + old.shape[1:], old.dtype)
            grown[: len(old)] = old
            setattr(self, name, grown)

    def _update_descriptors(self, landmarks: np.ndarray) -> None:
        """Representative descriptor: the medoid (least summed distance to the others) of the landmark's
        latest keyframe observations, as a binary or learnt descriptor has no meaningful mean."""
        by_count: dict[int, tuple[list[int], list[np.ndarray]]] = {}  # grouped by observations used, batched
        for landmark in np.asarray(landmarks).tolist():
            seen = [(k, row) for k, row in self.observations[landmark].items()
                    if self.keyframes[k].descriptors is not None][-DESCRIPTOR_OBSERVATIONS:]
            if not seen:
                continue
            if len(seen) <= 2:  # no medoid among two: the latest
                k, row = seen[-1]
                self.descriptors[landmark] = self.keyframes[k].descriptors[row]
                continue
            ids, rows = by_count.setdefault(len(seen), ([], []))
            ids.append(landmark)
            rows.extend(self.keyframes[k].descriptors[row] for k, row in seen)
        for n, (ids, rows) in by_count.items():
            stack = np.asarray(rows).reshape(len(ids), n, -1)
            summed = np.einsum("lnd,lmd->ln", stack, stack)  # unit rows: summed similarity to the others
            self.descriptors[ids] = stack[np.arange(len(ids)), np.argmax(summed, axis=1)]
