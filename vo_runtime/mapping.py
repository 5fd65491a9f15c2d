"""What a new keyframe does to the map: new landmarks, local bundle adjustment, culling.

- New landmarks: the new keyframe's keypoints without a landmark are matched to those of its best covisible
  keyframes (descriptor mutual nearest neighbours near the epipolar line, since the relative pose is known)
  and triangulated when the rays are far enough apart and both reprojections are close.
- Optionally (`neighbour_keyframes`), the new keyframe's landmarks are looked for in covisible keyframes that
  never matched them, around their projections, and found ones become observations.
- Local bundle adjustment over keyframes only: the new keyframe and its covisible ones are free, other
  keyframes that see their landmarks are fixed (at least two, so the adjustment cannot rescale the map);
  points and iterations are capped so one keyframe costs a bounded time.
- Culling: observations still far off after the adjustment are dropped; young landmarks that are rarely
  found where predicted, or that no further keyframe confirmed, die.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from itertools import chain
from typing import Callable

import numpy as np

from vo_runtime.errors import VORuntimeError
from vo_runtime.geometry import camera_centre, ray_angles, triangulate
from vo_runtime.localmap import LocalMap
from vo_runtime.matching import match_by_projection, match_epipolar
from vo_runtime.schur import schur_bundle_adjust
from vo_runtime.tracking import in_view


CONSOLIDATE_POINTS = 2000     # landmarks in `consolidate_map` at most
CONSOLIDATE_ITERATIONS = 20


@dataclass
class MappingConfig:
    """Thresholds of the mapping step (pixels are the frame's, angles in degrees)."""

    triangulation_keyframes: int = 2     # covisible keyframes the new one triangulates against
    # ORB-SLAM's rule for a monocular map: a partner whose baseline to the new keyframe is under this share of
    # the partner's median landmark depth triangulates nothing with it (0: off). In a slow turn such rays cross
    # at angles a small rotation error dominates, and the landmarks made there carry the map's scale away: the
    # drone's dark take-offs (starts 0-15 x 10 draws) 0.78x [0.59, 0.98] the ATE against off (a 1.09 m run whose
    # map shrank in the turn now loses that young map and is rebuilt after it: 0.011 m); the onboard take-offs,
    # the clip's 18 starts x 3 draws, KITTI 06 / 07 and TUM level (with young_map_frames 120; docs/vo_euroc.md).
    # `MonoVO` applies it only while a loss would discard the map and build it again (`MonoVO._young`: the first
    # map, within `VOConfig.young_map_frames` of its first keyframe, a discard left; young_map_frames 0: never): on
    # an older map it starved a drone slowing towards near structure (the clip played back to its start: its last
    # 7-10 frames lost in the dark).
    min_baseline_depth: float = 0.01
    # Besides those, the keyframe furthest from the new one among its this many best covisible ones that share
    # at least `wide_partner_min_shared` landmarks, for a keyframe the local map tracked (0: none). In a turn every
    # frame becomes a keyframe and the neighbours' baselines are a frame long, so the new view gets few landmarks
    # (the dark take-off is lost at frame 34 in 7 of 40 runs). Off: 8 against 0 over those 40 runs, dark 0.89x
    # [0.64, 1.42], lost frames 111 -> 52, but two runs tracked a collapsed map (1.7, 1.9 m); mid-flight 0.99x /
    # 1.00x; with `image_rotation_deg` 1 dark 0.85x (lost 88), onboard 1.21x (lost 98 -> 145; docs/vo_euroc.md).
    wide_partner_keyframes: int = 0
    wide_partner_min_shared: int = 20
    triangulation_candidates: int = 1500  # keypoints without a landmark, per keyframe, that may get one
    # Lowe ratio for matches between keyframes (no stricter than tracking's): a wrong match along the
    # epipolar line passes every geometric check but gives a wrong depth.
    triangulation_ratio: float = 0.9
    epipolar_threshold_px: float = 4.0   # largest distance of a match from its epipolar line
    triangulation_threshold_px: float = 3.0
    # Smallest ray angle of a new landmark, as the arc it spans in detector pixels (angle = px / focal). The
    # gate sees the noisy angle, so points that pass are biased to too much parallax, i.e. too short a depth,
    # and the map shrinks frame after frame (measured on a synthetic scene at 2 px noise: 1 deg lost 70 % of
    # the scale over 100 frames, 3 deg none). In pixels the gate keeps its distance from the keypoint noise.
    # It is low so that tracking never runs out of landmarks (12 lost KITTI at 240x320); the pose then rests
    # on the proven landmarks (next two fields), which keeps most of the bias out.
    min_parallax_px: float = 6.0
    # The same gate when patch alignment runs (an artefact that resizes the frames: KITTI and TUM at 240x320),
    # in its aligned pixels. There 6 let KITTI 07's map grow 25 % over 160 frames (scale drift under forward
    # motion: ATE 0.198 m over 14 starts); 9 kept it within 1 % and gave 0.160 m, while the same 9 at the
    # camera's resolution, without alignment, failed a dark EuRoC start (docs/vo_euroc.md).
    aligned_min_parallax_px: float = 9.0
    pose_min_parallax_px: float = 16.0   # tracking fits the pose to landmarks at least this far apart ...
    pose_min_found: int = 3              # ... or found in this many frames, when it has enough of them
    # Re-triangulate a landmark from its first keyframe and the new one once their rays are this many times
    # further apart than those it was triangulated from: a short baseline gives a noisy depth, and keeping
    # only points whose (noisy) parallax passed the gate biases depths short, which shrinks the map.
    refresh_factor: float = 2.0
    ba_keyframes: int = 5                # free keyframes in the local bundle adjustment (0: none)
    # At most this many fixed keyframes beside them: they hold the window's scale and gauge. 5 instead of 3:
    # ATE geometric mean over the 31-run study KITTI 07 0.181 -> 0.123 m, KITTI 06 0.072 -> 0.039, dark
    # KITTI 06 0.112 -> 0.058 (dark KITTI 07 0.238 -> 0.255); 4 and 7 were in between (docs/vo.md).
    ba_fixed_keyframes: int = 5
    ba_max_points: int = 600
    # Once a map has this many keyframes, one adjustment over all of them with only its first and newest
    # keyframe fixed (`consolidate_map`; 0: never). The local adjustment never moves a map's first two keyframes,
    # so the first baseline's own error stays in the map and in the poses of the frames anchored to them (the
    # first 20 scored frames of the dark drone runs hold a quarter of their ATE). Off: at 20 the drone clip gains
    # in every light (18 starts x 3 draws: dark 0.99x, onboard 0.97x [0.95, 0.99], normal 0.98x; the take-offs
    # 0.96x / 0.91x) but KITTI 07 in the dark loses (5 starts x 3 draws: 1.27x [1.11, 1.44]); at 10 the onboard
    # take-off loses (1.16x) (docs/vo_euroc.md).
    consolidate_keyframes: int = 0
    ba_iterations: int = 10              # Levenberg-Marquardt steps at most ...
    # ... or until a step lowers the robust cost by less than this share. 1e-3 instead of 1e-6 cut the
    # adjustment's time by a third on KITTI 07 (10.7 -> 6.9 ms per keyframe) for a final cost 0.002 % higher.
    ba_min_decrease: float = 1e-3
    ba_huber_px: float = 2.5             # residuals beyond this weigh linearly, not quadratically
    ba_gate_px: float = 12.0             # observations further off are left out of the adjustment
    ba_cull_px: float = 4.0              # ... and those still further off than this afterwards are dropped
    min_found_ratio: float = 0.25        # a young landmark found in fewer of the frames that should see it dies
    probation_keyframes: int = 2         # keyframes after creation at which a landmark must have ...
    min_observations: int = 3            # ... this many keyframe observations, or die
    # The new keyframe's landmarks projected into this many covisible keyframes that did not observe them, and
    # matched there (descriptor nearest to the projection within neighbour_radius_px, as ORB-SLAM's search in
    # neighbours adds observations): more views per landmark for the bundle adjustment. Off: 5 keyframes helped
    # 18 EuRoC starts in normal light and onboard (0.0077 / 0.0151 -> 0.0065 / 0.0129 m; the onboard take-off from 0
    # 0.132 -> 0.037) and KITTI 06 in every light, but cost KITTI 07 in the dark in every variant tried (three
    # noise draws: 0.274 -> 0.346 m, 32 frames lost in its sharp turn; onboard level; docs/vo_takeoff.md).
    neighbour_keyframes: int = 0
    neighbour_radius_px: float = 3.0
    # A new keyframe's pose refined on its landmarks and on the Sampson distances of its descriptor matches with
    # the previous keyframe (`keyframe_pose.py`), before it triangulates: the matches' weight against a
    # landmark's (0: off), the gate on those matches under the tracked poses, and the robust loss's scale.
    # Off: the drone's 80 take-off runs (starts 0-15 x 10 noise draws), weight 1 against 0: dark 0.87x [0.71,
    # 1.10], onboard 1.11x [0.97, 1.25]; refined during the first map's probation too 0.79x / 1.30x; with the
    # refined rotation kept in the bundle adjustment 1.16x / 1.27x; only on keyframes a fallback found 0.80x (but
    # 14 runs under 95 % tracked instead of 10) / 1.07x (docs/vo_takeoff.md).
    keyframe_epipolar_weight: float = 0.0
    keyframe_epipolar_gate_px: float = 20.0
    keyframe_epipolar_scale_px: float = 1.5

    def __post_init__(self) -> None:
        if not 0 <= self.min_baseline_depth < 1:
            raise VORuntimeError("mapping.min_baseline_depth must be in [0, 1)")
        if self.consolidate_keyframes < 0 or 0 < self.consolidate_keyframes < 3:
            raise VORuntimeError("mapping.consolidate_keyframes must be 0 (never) or at least 3")
        if self.neighbour_keyframes < 0 or self.neighbour_radius_px <= 0:
            raise VORuntimeError("mapping.neighbour_keyframes must be >= 0 and mapping.neighbour_radius_px > 0")
        if self.keyframe_epipolar_weight < 0 or self.keyframe_epipolar_gate_px <= 0 \
                or self.keyframe_epipolar_scale_px <= 0:
            raise VORuntimeError("mapping.keyframe_epipolar_weight must be >= 0, keyframe_epipolar_gate_px and "
                                 "keyframe_epipolar_scale_px > 0")


def min_angle(config: MappingConfig, focal: float) -> float:
    """The parallax gate in degrees for a camera of ``focal`` pixels."""
    return float(np.degrees(config.min_parallax_px / focal))


def essential_between(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Essential matrix E with x_b^T E x_a = 0 for world-to-camera poses a and b."""
    rotation = pose_b[:3, :3] @ pose_a[:3, :3].T
    t = pose_b[:3, 3] - rotation @ pose_a[:3, 3]
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return skew @ rotation


def widest_partner(local_map: LocalMap, number: int, count: int, min_shared: int) -> int | None:
    """Among keyframe ``number``'s ``count`` best covisible keyframes sharing >= ``min_shared`` landmarks, the one
    whose camera centre is furthest from its own; None if none (or ``count`` 0)."""
    if count <= 0:
        return None
    shared = local_map.covisible_counts(number, count)
    centre = camera_centre(local_map.keyframes[number].pose_cw)
    best, best_distance = None, 0.0
    for other, n in shared:
        distance = float(np.linalg.norm(camera_centre(local_map.keyframes[other].pose_cw) - centre))
        if n >= min_shared and distance > best_distance:
            best, best_distance = other, distance
    return best


def short_baseline(local_map: LocalMap, other: int, number: int, share: float) -> bool:
    """Whether keyframes ``other`` and ``number`` are closer than ``share`` of ``other``'s median landmark depth
    (False with ``share`` 0 or for a keyframe without landmarks)."""
    if share <= 0:
        return False
    seen = local_map.landmarks_of([other])
    if len(seen) == 0:
        return False
    pose = local_map.keyframes[other].pose_cw
    depth = float(np.median(local_map.positions[seen] @ pose[2, :3] + pose[2, 3]))
    baseline = float(np.linalg.norm(camera_centre(local_map.keyframes[number].pose_cw) - camera_centre(pose)))
    return baseline < share * depth


def triangulate_new_landmarks(local_map: LocalMap, number: int, config: MappingConfig, focal: float,
                              max_distance: float, ratio: float | None, align: Callable | None = None,
                              detection_scale: float = 1.0, wide_partner: bool = True,
                              baseline_rule: bool = True) -> int:
    """Create landmarks between keyframe ``number`` and its covisible keyframes; returns how many.

    ``baseline_rule``: whether ``config.min_baseline_depth`` applies to this keyframe (`MonoVO` keeps it to a
    young first map; see `VOConfig.young_map_frames`).

    ``align(source, target, source_rows, target_rows)``, when given, moves the new keyframe's matched
    keypoints onto the other keyframe's patches (`refine.py`) before they are triangulated. The epipolar
    gate sees the keypoints before that, as detected: ``detection_scale`` widens it by the precision that
    alignment adds (`VOConfig.align_gain`), since ``focal`` measures aligned pixels."""
    new = local_map.keyframes[number]
    # The previous keyframe (the most overlap: in a turn, older keyframes share little of the view) and
    # then the best covisible ones.
    neighbours = [number - 1] if number > 0 else []
    neighbours += [k for k in local_map.covisible(number, config.triangulation_keyframes) if k != number - 1]
    neighbours = neighbours[: config.triangulation_keyframes]
    wide = widest_partner(local_map, number, config.wide_partner_keyframes if wide_partner else 0,
                          config.wide_partner_min_shared)
    if wide is not None and wide not in neighbours:
        neighbours.append(wide)
    created = 0
    for other_number in neighbours:
        other = local_map.keyframes[other_number]
        if other.descriptors is None:  # released: an old keyframe (`LocalMap.release_descriptors`)
            continue
        if baseline_rule and short_baseline(local_map, other_number, number, config.min_baseline_depth):
            continue
        # Bounded work: the strongest keypoints without a landmark (features come sorted by score).
        rows_a = np.flatnonzero(other.landmark < 0)[: config.triangulation_candidates]
        rows_b = np.flatnonzero(new.landmark < 0)[: config.triangulation_candidates]
        essential = essential_between(other.pose_cw, new.pose_cw)
        pairs = match_epipolar(other.points[rows_a], other.descriptors[rows_a], new.points[rows_b],
                               new.descriptors[rows_b], essential, detection_scale * config.epipolar_threshold_px / focal,
                               max_distance, min(ratio or 1.0, config.triangulation_ratio))
        if len(pairs) == 0:
            continue
        a, b = rows_a[pairs[:, 0]], rows_b[pairs[:, 1]]
        if align is not None:
            align(other, new, a, b)
        world, error = triangulate(other.pose_cw, new.pose_cw, other.points[a], new.points[b])
        angles = ray_angles(other.pose_cw, new.pose_cw, other.points[a], new.points[b])
        good = (error < config.triangulation_threshold_px / focal) & (angles >= min_angle(config, focal))
        if np.any(good):
            local_map.add_landmarks(world[good], [(other_number, a[good]), (number, b[good])], angles[good])
            created += int(np.count_nonzero(good))
    return created


def observe_in_neighbours(local_map: LocalMap, number: int, config: MappingConfig, focal: float,
                          max_distance: float, ratio: float | None, align: Callable | None = None) -> int:
    """Find keyframe ``number``'s landmarks in its covisible keyframes that never matched them: each projected
    there and matched among the keypoints without a landmark; returns the observations added.

    ``align(source, target, source_rows, target_rows)``, when given, moves each found keypoint onto the new
    keyframe's patch (`refine.py`), as tracking's matches are moved."""
    if config.neighbour_keyframes <= 0:
        return 0
    new = local_map.keyframes[number]
    ids = local_map.landmarks_of([number])
    added = 0
    for other_number in local_map.covisible(number, config.neighbour_keyframes):
        other = local_map.keyframes[other_number]
        if other.descriptors is None:
            continue
        unseen = ids[np.array([other_number not in local_map.observations[i] for i in ids.tolist()], bool)]
        free = np.flatnonzero(other.landmark < 0)
        if len(unseen) == 0 or len(free) == 0:
            continue
        radius = config.neighbour_radius_px / focal
        low, high = other.points[free].min(axis=0) - radius, other.points[free].max(axis=0) + radius
        unseen, projected = in_view(local_map, unseen, other.pose_cw, (low[0], high[0], low[1], high[1]))
        pairs = match_by_projection(projected, local_map.descriptors[unseen], other.points[free],
                                    other.descriptors[free], radius, max_distance, ratio)
        if len(pairs) == 0:
            continue
        found, rows = unseen[pairs[:, 0]], free[pairs[:, 1]]
        if align is not None:
            new_rows = np.array([local_map.observations[i][number] for i in found.tolist()], np.int64)
            align(new, other, new_rows, rows)
        local_map.add_observations(other_number, found, rows)
        added += len(found)
    return added


def refresh_landmarks(local_map: LocalMap, number: int, config: MappingConfig, focal: float) -> int:
    """Re-triangulate the landmarks keyframe ``number`` observes from their first keyframe and this one, where
    the ray angle has grown by ``refresh_factor``; returns how many moved."""
    new = local_map.keyframes[number]
    rows = np.flatnonzero(new.landmark >= 0)
    ids = new.landmark[rows]
    first = np.array([next(iter(local_map.observations[i])) for i in ids.tolist()], np.int64)
    refreshed = 0
    for other_number in np.unique(first).tolist():
        if other_number == number:
            continue
        pick = first == other_number
        other = local_map.keyframes[other_number]
        other_rows = np.array([local_map.observations[i][other_number] for i in ids[pick].tolist()], np.int64)
        angles = ray_angles(other.pose_cw, new.pose_cw, other.points[other_rows], new.points[rows[pick]])
        due = angles >= np.maximum(min_angle(config, focal), config.refresh_factor * local_map.angles[ids[pick]])
        if not np.any(due):
            continue
        world, error = triangulate(other.pose_cw, new.pose_cw, other.points[other_rows[due]], new.points[rows[pick][due]])
        good = error < config.triangulation_threshold_px / focal
        moved = ids[pick][due][good]
        local_map.positions[moved] = world[good]
        local_map.angles[moved] = angles[due][good]
        refreshed += len(moved)
    return refreshed


def local_bundle_adjustment(local_map: LocalMap, number: int, config: MappingConfig,
                            focal: float) -> list[int]:
    """Adjust keyframe ``number``, its covisible keyframes and their landmarks; returns the keyframes moved."""
    if config.ba_keyframes <= 0:
        return []
    # The map's first two keyframes never move: their baseline is the unit of length.
    free = [k for k in [number] + local_map.covisible(number, config.ba_keyframes - 1) if k >= 2]
    landmarks = local_map.landmarks_of(free)
    if len(landmarks) > config.ba_max_points:  # bound the cost: keep the most observed landmarks
        counts = local_map.observation_counts(landmarks)
        landmarks = landmarks[np.argsort(-counts, kind="stable")[: config.ba_max_points]]
    # Keyframes outside the window that see its landmarks, counted in C; first-seen order kept for the ties below
    observers = Counter(chain.from_iterable(map(local_map.observations.__getitem__, landmarks.tolist())))
    for k in free:
        observers.pop(k, None)
    fixed = sorted(observers, key=lambda k: (k >= 2, -observers[k]))[: config.ba_fixed_keyframes]
    if len(fixed) < 2:  # the gauge and the scale need two fixed views: fix the oldest free ones
        free.sort()
        move = min(2 - len(fixed), len(free))
        fixed, free = fixed + free[:move], free[move:]
    return adjust_window(local_map, fixed, free, landmarks, config, focal)


def adjust_window(local_map: LocalMap, fixed: list[int], free: list[int], landmarks: np.ndarray,
                  config: MappingConfig, focal: float, iterations: int | None = None) -> list[int]:
    """Bundle-adjust keyframes ``free`` and ``landmarks`` with keyframes ``fixed`` held (>= 2: gauge and scale);
    observations off by more than ``ba_gate_px`` stay out, those still off by ``ba_cull_px`` afterwards are
    dropped. Returns the keyframes moved."""
    if not free:
        return []
    window = fixed + free
    position = {k: i for i, k in enumerate(window)}
    lookup = np.full(local_map.size, -1)
    lookup[landmarks] = np.arange(len(landmarks))
    frames, points, xy, scale = [], [], [], []
    for k in window:
        keyframe = local_map.keyframes[k]
        rows = np.flatnonzero(keyframe.landmark >= 0)
        index = lookup[keyframe.landmark[rows]]
        rows, index = rows[index >= 0], index[index >= 0]
        frames.append(np.full(len(rows), position[k]))
        points.append(index)
        xy.append(keyframe.points[rows])
        scale.append(np.ones(len(rows)) if keyframe.sigma is None else 1.0 / keyframe.sigma[rows])
    frames, points, xy = np.concatenate(frames), np.concatenate(points), np.concatenate(xy)
    # Unweighted keyframes (ORB, aligned keypoints) take the plain adjustment, not one scaled by ones.
    scale = np.concatenate(scale) if any(local_map.keyframes[k].sigma is not None for k in window) else None
    poses = [local_map.keyframes[k].pose_cw for k in window]
    world = local_map.positions[landmarks]
    cam = np.einsum("kij,kj->ki", np.stack(poses)[frames, :3, :3], world[points]) + np.stack(poses)[frames, :3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        error = focal * np.linalg.norm(cam[:, :2] / cam[:, 2:3] - xy, axis=1)
    keep = (cam[:, 2] > 0) & (error < config.ba_gate_px)
    counts = np.bincount(points[keep], minlength=len(landmarks))
    keep &= counts[points] >= 2
    if np.count_nonzero(keep) < 20:
        return []
    result = schur_bundle_adjust(poses, len(fixed), world, frames[keep], points[keep], xy[keep], focal,
                                 iterations=iterations or config.ba_iterations, huber_px=config.ba_huber_px,
                                 min_decrease=config.ba_min_decrease,
                                 obs_scale=None if scale is None else scale[keep])
    for k, pose in zip(window[len(fixed):], result.poses_cw[len(fixed):]):
        local_map.keyframes[k].pose_cw = pose
    adjusted = np.unique(points[keep])
    local_map.positions[landmarks[adjusted]] = result.points[adjusted]
    # Observations the adjustment could not explain (or that were gated out) are dropped.
    bad = np.ones(len(frames), bool)
    bad[np.flatnonzero(keep)] = result.residual_px > config.ba_cull_px
    window_numbers = np.array(window)
    local_map.remove_observations(landmarks[points[bad]], window_numbers[frames[bad]])
    return list(window[len(fixed):])


def cull_landmarks(local_map: LocalMap, number: int, config: MappingConfig) -> int:
    """Kill young landmarks that tracking rarely finds or that later keyframes did not confirm."""
    recent = np.flatnonzero(local_map.alive[: local_map.size]
                            & (local_map.created[: local_map.size] >= number - config.probation_keyframes))
    if len(recent) == 0:
        return 0
    ratio = local_map.found[recent] / np.maximum(local_map.visible[recent], 1)
    age = number - local_map.created[recent]
    unconfirmed = (age >= config.probation_keyframes) & (
        local_map.observation_counts(recent) < config.min_observations)
    dead = recent[(ratio < config.min_found_ratio) | unconfirmed]
    local_map.kill(dead)
    return len(dead)


def consolidate_map(local_map: LocalMap, config: MappingConfig, focal: float) -> list[int]:
    """One adjustment of every keyframe of a young map and its landmarks, only the first and the newest keyframe
    held: their distance keeps the map's scale, the first baseline's error is spread over the later views.
    Returns the keyframes moved."""
    count = len(local_map.keyframes)
    if count < 3:
        return []
    landmarks = local_map.landmarks_of(list(range(count)))
    if len(landmarks) > CONSOLIDATE_POINTS:  # bounded, as the local adjustment: the most observed landmarks
        counts = local_map.observation_counts(landmarks)
        landmarks = landmarks[np.argsort(-counts, kind="stable")[:CONSOLIDATE_POINTS]]
    return adjust_window(local_map, [0, count - 1], list(range(1, count - 1)), landmarks, config, focal,
                         iterations=CONSOLIDATE_ITERATIONS)
