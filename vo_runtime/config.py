"""`VOConfig` (the tuning knobs of `MonoVO`, named and visible), `VOResult` (what one frame returns) and
`Extraction` (a frame's features before it is tracked)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vo_runtime.errors import VORuntimeError
from vo_runtime.features import Features
from vo_runtime.mapping import MappingConfig


@dataclass
class VOConfig:
    """Tuning knobs. Pixel thresholds are in the detector's pixels (the frame's, unless the extractor resizes
    frames to a smaller input: see `detector_pixel`); angles in degrees."""

    match_max_distance: float = 0.9      # L2 between unit descriptors (0..2)
    match_ratio: float | None = 0.9      # Lowe ratio on distances; None disables
    min_features: int = 30               # fewer detections: the frame is not used
    min_matches: int = 30                # correspondences an (re)initialisation needs
    min_pnp_inliers: int = 20            # a pose needs this many inliers to be trusted
    ransac_threshold_px: float = 1.0     # essential-matrix RANSAC (Sampson distance)
    pnp_threshold_px: float = 3.0        # pose inlier gate (reprojection error)
    triangulation_threshold_px: float = 3.0  # largest reprojection error of a new landmark in either view
    init_min_parallax_px: float = 15.0   # median track motion before a two-view initialisation is tried
    init_min_median_deg: float = 2.0     # median ray angle of those landmarks
    # ... for a map built again after a loss or an abandoned map. Its scale comes from the speed before, not
    # from its baseline, and a drone that lost its map in a turn (the dark take-off: 2-20 deg of yaw over the
    # baseline, a few cm a frame) has 50-96 essential inliers at a median ray angle of 1.1-1.9 deg for 20
    # frames. 1.0 (= min_triangulation_deg: no gate beyond the landmarks' own) against 2.0, every sequence with
    # noise draws: lost frames on the drone clip 79 -> 33 (dark), 14 -> 8 (onboard), ATE 0.99x / 0.97x; every
    # KITTI, TUM and normal-light learned run identical; ORB gained too (docs/vo_takeoff.md).
    reinit_min_median_deg: float = 1.0
    # A re-initialisation whose reference the camera has turned more than this away from (the two-view
    # rotation), and which still lacks its landmarks, measures from the current frame instead (0: never).
    # KITTI 07 in a turn waited 20 frames on a reference it turned 10-37 deg away from (2.17 -> 0.52 m); the
    # drone's turns stay under 21 deg; every other dev run identical (docs/vo_takeoff.md).
    reinit_max_turn_deg: float = 25.0
    init_min_landmarks: int = 40         # triangulated points an initialisation must produce ...
    # ... or this many while the tracks from the reference are not dying (as the parallax gate relaxes only
    # for dying tracks). Off (= init_min_landmarks) by default: 100 cured the drone's weak mid-flight first maps
    # in the dark (EuRoC from frames 40-170: worst ATE 0.515 -> 0.017 m, geometric mean 0.0127 -> 0.0092) but
    # cost KITTI 07 in the dark and with the onboard light (0.230 -> 0.268, 0.211 -> 0.233 m), whose forward
    # motion needs its first map early (docs/vo_takeoff.md, "Mid-flight"). A drone in the dark may set it.
    init_wanted_landmarks: int = 40
    # Share of the tracks from the reference that the two-view model (essential matrix or homography) must
    # explain. A rigid scene seen through good tracks fits 50-90 %; the drone's take-off (a fast rotation
    # onset with a few mm of baseline, EuRoC MH_05) fitted 24-45 %: a model fitted to noise, whose map then
    # "tracked" with metres of error. 0 turns the check off.
    init_min_inlier_share: float = 0.0
    # The first map's probation (`probation.py`): over its first this many tracked frames, the median angle
    # between the rotation it tracked from frame to frame and the rotation fitted to the two frames' matches
    # alone must stay below probation_max_deg, or the map is discarded and the VO initialises again (at most
    # probation_max_discards times a run). 0 frames: off. Dev data: broken first maps 1.42-2.54 deg, healthy
    # maps 0.11-0.72 (docs/vo_euroc.md).
    probation_frames: int = 15
    probation_max_deg: float = 1.0
    probation_max_discards: int = 2
    # A first map lost (every search and relocalisation failed) at most this many frames after its first keyframe
    # (and at most young_map_lost_frames, below) is discarded as one that failed its probation (the same budget of
    # probation_max_discards), instead of a new map being scaled by its speed: its frames go back to
    # ``initialising`` and the next map is a first map, with its own baseline's unit and the first map's gates.
    # ORB-SLAM2 resets a map lost while it holds five keyframes or fewer; this VO keyframes every 1-4 frames, so
    # its limit is in frames. 0: off. Drone take-offs, 40 runs each: dark ATE 0.70x, frames lost 111 -> 0,
    # onboard 0.64x, 98 -> 1; 20 frames too few (the maps break 22-30 frames in), 80 the same as 40 and, with
    # young_map_travel, also reaches a map the travel check breaks 57 frames in (docs/vo_euroc.md, "A young map
    # lost in the turn is discarded"); 120 since the baseline rule (`mapping.min_baseline_depth`), under which two
    # onboard take-offs broke 83-86 frames in (1.86, 1.89 m).
    young_map_frames: int = 120
    # A loss alone is judged over a shorter span: a first map lost at most this many frames after its first keyframe
    # (and within young_map_frames) is discarded; one lost later is carried through the loss as any map is. A map
    # that tracked for seconds before it lost its way is a good map in a hard stretch, not a broken one: the drone
    # clip played backwards (`bench/palindrome_sequence.py`, the flight's second half) lost its maps at the end,
    # 37-117 frames after their first keyframe, and the discard threw away every tracked frame of 7 of 33 dark
    # runs and 12 of 33 onboard runs; the take-offs' maps were lost 3-33 frames in. 40 against 120: the reversed
    # flight's runs without a trajectory 7 -> 0 dark, 12 -> 1 onboard; the learned take-offs and clip, KITTI and
    # TUM identical (ORB's clip runs keep some maps: dark 1.08x; docs/vo_euroc.md, "A young map's loss judged over
    # 40 frames"). 0: a lost map is never discarded.
    young_map_lost_frames: int = 40
    # A first map the travel check finds broken within young_map_frames of its first keyframe is discarded the same
    # way (its frames back to ``initialising``, the next map a first map) instead of being abandoned for a map at the
    # speed from before: take-offs dark 0.76x, onboard 0.69x the ATE, the drone clip dark 0.92x, KITTI and TUM
    # identical. False: abandoned as any other map (docs/vo_euroc.md, "A young map lost in the turn").
    young_map_travel: bool = True
    min_triangulation_deg: float = 1.0   # rays closer than this give no landmark
    search_radius_px: float = 15.0       # guided matching around a landmark's predicted position
    wide_search_radius_px: float = 45.0  # ... when the first search explains too little
    local_keyframes: int = 8             # the reference keyframe and its best covisible ones form the local map
    max_local_points: int = 1500         # landmarks projected per search (the most often found)
    keyframe_max_gap: int = 4            # a tracked frame becomes a keyframe at least this often ...
    keyframe_track_ratio: float = 0.8    # ... or when it tracks fewer than this share of the reference keyframe's landmarks
    keyframe_min_tracked: int = 80       # ... or when it tracks fewer landmarks than this (with 50 the VO ran
    #                                      ~10 % faster but lost 17-20 % of the frames of dark KITTI runs: docs/vo.md)
    keyframe_min_gap: int = 1            # ... but not sooner than this many frames after the last
    relocalise_keyframes: int = 5        # recent keyframes a lost frame tries to relocalise against (0: never)
    relocalise_frames: int = 3           # failed relocalisations before a fresh initialisation may start
    # A map re-initialised after a loss has a guessed scale (the speed before the loss); its next this many
    # keyframes look for the lost map's last `relocalise_keyframes` keyframes, and two in a row that find them
    # at one scale move the new map into the lost map's frame and scale (`map_merge.py`; 0: never, the default
    # until the dev table is measured with it: 20 turns it on). A find needs merge_min_pairs landmarks of both
    # maps whose depth ratios agree to merge_max_spread (median absolute deviation / median), the two finds'
    # scales agree to it too.
    merge_keyframes: int = 0
    merge_min_pairs: int = 12
    merge_max_spread: float = 0.1
    # After a loss the motion model keeps predicting for this many frames since the last tracked one, and
    # tracking against the local map is tried before relocalisation: one bad frame (a noise burst in the
    # dark) does not throw away the map's prediction (0: relocalisation only).
    lost_predict_frames: int = 3
    initial_baseline: float = 1.0        # length of the first baseline, in output units
    # A re-initialisation after a loss is scaled by the speed before it: the median over this many tracked
    # frames, not the last one, because a map that is failing shrinks its scale in its last frames (EuRoC's
    # normal-light take-off with init_min_landmarks=100: the last speed was ~1 % of the true one and the new
    # map kept that scale; with the median 24 %, the rest being the drone's real acceleration while lost).
    speed_frames: int = 20
    # A pose refined on the local map that jumped more than pose_check_jump x the median speed from the
    # prediction and explains fewer than pose_check_share of its matches is fitted again by PnP RANSAC on all
    # of them, and the pose explaining more wins (`pose.second_opinion`). Against off, on 18 EuRoC starts in
    # three lights: the dark start from frame 100 0.515 -> 0.017 m; KITTI's runs identical. A check that fires
    # more often (0.75 and 60 %, 0.5 and 70 %) also cured other runs but broke others (docs/vo_takeoff.md).
    pose_check: bool = True
    pose_check_jump: float = 1.0
    pose_check_share: float = 0.5
    # ... and one explaining fewer than pose_check_floor of its matches however little it moved: TUM's worst
    # dark draw (5 of 12) refined frame 7 to 24 of 266 matches with a step 2.5x the true one, two keyframes made
    # from it halved the map's scale (0.032 m); RANSAC explains 84 (0.012 m). No KITTI or drone clip run changes.
    pose_check_floor: float = 0.2
    # The travel check (`travel_check.py`): every tracked frame's direction of travel since the tracked frame
    # travel_check_gap frames back is compared with an essential matrix fitted to the landmarks both saw;
    # travel_check_frames consecutive checks whose essential directions agree within
    # travel_check_consistency_deg and disagree with the map by a median over travel_check_max_deg abandon
    # the map (status lost, `problem` says why) and initialise again, on the check's own baseline when it can,
    # at the speed from before. 0: off. On every dev run with noise draws (EuRoC 18 starts x 3 draws dark and
    # onboard, KITTI 06 x 4, KITTI 07 x 3, TUM x 12, the aligned rows; learned and ORB) it fired on the three
    # broken learned drone runs (1.01 / 0.48 / 0.50 -> 0.10 / 0.30 / 0.37 m) and two broken ORB ones (0.18 ->
    # 0.09 m) and changed no other run (docs/vo_takeoff.md, "Noticing a broken track").
    travel_check_gap: int = 10
    travel_check_max_deg: float = 20.0
    travel_check_consistency_deg: float = 20.0
    travel_check_frames: int = 5
    travel_check_min_inliers: int = 20
    # Where the two frames share too few landmarks for a direction (a car at 10 Hz), their keypoints matched
    # by descriptor (mutual nearest neighbours within this L2 distance, match_ratio) can give the
    # correspondences instead: 0.9 (tracking's distance) judges 75 % of KITTI 07's tracked frames instead of
    # 3 %, and every learned map it abandoned that was traced travelled 20-27 deg off the true direction, but the ATE
    # moved both ways (maps built again at a guessed scale) and a check costs ~10 ms on the car (USAC on
    # ~100 matches with many outliers): off (0) until a rebuilt map keeps its scale (docs/vo_takeoff.md).
    travel_check_match_distance: float = 0.0
    # Patch alignment (`refine.py`): matched keypoints move onto the patch around the landmark's latest
    # keyframe observation (window in frame pixels; 0: off) before the pose and new landmarks are computed.
    # It runs when a detector pixel spans at least `align_min_detector_pixel` frame pixels (an artefact that
    # resizes the frames); at frame resolution it did not pay (ORB, KITTI 07 from 5 starting frames: ATE
    # geometric mean 0.36 -> 0.41 m).
    align_window_px: int = 15
    align_min_detector_pixel: float = 1.5
    align_max_shift: float = 2.0         # detector pixels a keypoint may move; further: left where detected
    # Aligned keypoints are this many times more precise than detections (matches' median epipolar error
    # against KITTI 07's ground truth 1.28 -> 0.64 px), so pixel thresholds are in detector pixels / gain.
    # 3 rather than the measured 2: tighter gates were more accurate over 22 normal-light runs (docs/vo.md).
    align_gain: float = 3.0
    # Align on frames with each pixel's mean and contrast over the alignment window normalised away
    # (`refine.contrast_normalise`): a light carried by the camera or vignetting changes a point's brightness
    # as it crosses the frame, and raw intensities pull the patch off its structure. More precise against
    # KITTI's ground-truth epipolar geometry in every light (3 frames apart: 0.71 -> 0.62 px normal, 1.09 ->
    # 0.86 onboard), but the ATE gained on KITTI 06 in the dark and onboard and lost on KITTI 07 in every light
    # (docs/vo_euroc.md), so it is off until a whole table says otherwise.
    align_normalise: bool = False
    # Keypoints weighted by their detection score in the pose fit and the local bundle adjustment: a
    # keypoint's expected position error is (score / the frame's median score) ** -score_sigma_power, within
    # [1 / score_sigma_limit, score_sigma_limit]; 0: every keypoint alike. Only for a network's detections:
    # the tracked residuals of the drone camera's keypoints fall with the score as score ** -0.41 to -0.46
    # (dark and normal light), hence 0.5; ORB's corner response says nothing of its error, and patch-aligned
    # keypoints (KITTI, TUM at 240x320) are no longer where the score was found (-0.16 there; 0.5 cost KITTI 07
    # in the dark 1.12x). Against 0 on the drone clip (18 starts, noise draws): dark 0.93x, onboard 0.91x,
    # normal 0.91x (one start's thin first map lost 9 frames instead of tracking 25 deg off), dark take-off
    # (40 runs) 0.86x with frames lost 159 -> 97 (docs/vo_euroc.md, "Keypoints weighted by their score").
    score_sigma_power: float = 0.5
    score_sigma_limit: float = 2.0
    # ... and each match by how often its landmark was seen: in the tracked pose fit a match's variance is its
    # keypoint's sigma ** 2 plus landmark_variance / (keyframes that observed the landmark - 1), since a landmark
    # triangulated from few noisy views is itself off (the dark drone clip's inliers lie a median 1.14 / 0.94 /
    # 0.80 / 0.66 px from landmarks seen by 2 / 3 / 4 / 10+ keyframes). 2 against 0: drone clip 18 starts x 3 draws
    # dark 0.94x, onboard 0.97x, normal 1.02x; take-off 40 runs dark 0.91x, onboard 0.79x; 1 against 2 on the clip
    # 1.03x (docs/vo_euroc.md, "Young landmarks weighted down"). Weighted fits only (a network's detections at the
    # camera's resolution: ORB, KITTI and TUM runs are unchanged); 0: every landmark taken as exact.
    landmark_variance: float = 2.0
    # Landmarks the previous frame matched and this one missed, followed by optical flow (`flow_follow.py`):
    # Lucas-Kanade patch side in frame pixels (0: off), the forward-backward check in frame pixels, and the
    # followed point's relative position error in a weighted pose fit. 15 against off, 30 mid-flight drone runs:
    # dark 0.98x, onboard 0.94x (docs/vo_euroc.md, "Landmarks the detector missed" and "The flow made cheaper").
    # Off: at 480x752 the VO runs 26.8 FPS on one core with it, 31.6 without (30 needed); cheaper windows, one
    # pyramid level or no flow back gain no more.
    flow_window_px: int = 0
    flow_check_px: float = 0.5
    flow_sigma: float = 1.0
    # When the search from the constant-velocity prediction fails, the rotation since the last tracked frame
    # measured on the two frames' matches turns the prediction for a second search, and a pose the wide search or
    # the previous frame finds must agree with it within this many degrees (`tracking.track_frame`; 0: off). Off:
    # on the dark take-off's loss at frame 33 the turned prediction is 0.10 deg from the true turn, yet the thin
    # map still gives too few matches; 1 against 0 with `mapping.wide_partner_keyframes` 8 (40 take-off runs):
    # dark 0.85x, onboard 1.21x with 8 runs under 95 % tracked instead of 2 (docs/vo_euroc.md).
    image_rotation_deg: float = 0.0
    # A keyframe's mapping on a second thread, overlapping the next frame's extraction (`background.py`):
    # the same results, sooner; a keyframe's own pose is refined after `process` returns (call `finish`).
    mapping_thread: bool = False
    mapping: MappingConfig = field(default_factory=MappingConfig)

    def __post_init__(self) -> None:
        if self.min_matches < 8 or self.min_pnp_inliers < 6:
            raise VORuntimeError("min_matches must be >= 8 and min_pnp_inliers >= 6")
        if self.initial_baseline <= 0:
            raise VORuntimeError("initial_baseline must be positive")
        if self.align_window_px < 0 or self.align_max_shift <= 0 or self.align_gain < 1:
            raise VORuntimeError("align_window_px must be >= 0, align_max_shift > 0 and align_gain >= 1")
        if self.landmark_variance < 0 or self.image_rotation_deg < 0:
            raise VORuntimeError("landmark_variance and image_rotation_deg must be >= 0")
        if self.flow_window_px < 0 or self.flow_check_px <= 0 or self.flow_sigma <= 0:
            raise VORuntimeError("flow_window_px must be >= 0, flow_check_px and flow_sigma > 0")
        if self.probation_frames < 0 or self.probation_max_deg <= 0 or self.probation_max_discards < 0 \
                or self.young_map_frames < 0 or self.young_map_lost_frames < 0:
            raise VORuntimeError("probation_frames, probation_max_discards, young_map_frames and "
                                 "young_map_lost_frames must be >= 0, probation_max_deg > 0")
        if self.travel_check_gap < 0 or self.travel_check_frames < 1 or self.travel_check_min_inliers < 5 \
                or self.travel_check_max_deg <= 0 or self.travel_check_consistency_deg <= 0 \
                or not 0 <= self.travel_check_match_distance <= 2:
            raise VORuntimeError("travel_check_gap must be >= 0, travel_check_frames >= 1, travel_check_min_inliers "
                                 ">= 5, the travel check's angles > 0 and travel_check_match_distance in [0, 2]")
        if self.merge_keyframes < 0 or self.merge_min_pairs < 6 or self.merge_max_spread <= 0:
            raise VORuntimeError("merge_keyframes must be >= 0, merge_min_pairs >= 6 and merge_max_spread > 0")
        if self.speed_frames < 1:
            raise VORuntimeError("speed_frames must be >= 1")
        if self.pose_check_jump <= 0 or not 0 < self.pose_check_share <= 1 \
                or not 0 <= self.pose_check_floor <= self.pose_check_share:
            raise VORuntimeError("pose_check_jump must be > 0, pose_check_share in (0, 1] and pose_check_floor "
                                 "in [0, pose_check_share]")
        if not 0 < self.search_radius_px <= self.wide_search_radius_px:
            raise VORuntimeError("search radii must be positive, the wide one no smaller")


@dataclass
class VOResult:
    """Outcome of one frame. ``pose`` is camera-to-world (4x4)."""

    index: int
    timestamp: float | None
    pose: np.ndarray
    status: str
    num_features: int
    num_matches: int      # guided (or frame-to-frame) matches
    num_inliers: int      # pose (or two-view) inliers
    num_landmarks: int    # keypoints of this frame that observe a landmark
    extract_ms: float
    track_ms: float
    keyframe: bool = False  # became a keyframe (adds landmarks, runs the local bundle adjustment)
    problem: str | None = None  # why a skipped frame could not be used, or why a map was dropped here
    map_dropped: bool = False   # the VO threw its map away here (probation, young map lost, travel check; see problem)
    merged_scale: float | None = None  # a re-initialised map found the lost one here and took its frame: the
    #                                    ratio of their scales (lost / new; 1: the guessed scale was right)
    tracked_by: str | None = None  # local map | wide search | previous frame | relocalisation | two-view
    mapping_ms: float = 0.0  # keyframe work (triangulation, bundle adjustment, culling): part of track_ms,
    #                          or on the worker thread with VOConfig.mapping_thread
    match_ms: float = 0.0    # of track_ms: guided matching against the local map
    pose_ms: float = 0.0     # of track_ms: pose refinement on those matches


@dataclass
class Extraction:
    """One frame after `MonoVO.extract`: its features, or why it cannot be used (``usable``: it passed
    `check_frame`, so its size is checked against the calibration before it is skipped)."""

    image: np.ndarray | None
    features: Features | None
    problem: str | None = None
    usable: bool = True
    seconds: float = 0.0
