"""Viewpoint change for `toolkit eval synth`: the reference crop of a source frame and SuperPoint-style random
homographies that look at the same scene from elsewhere, each target rendered from the whole source frame.

Coordinates are pixels with centres at integers (OpenCV's convention); an image of width W spans
``-0.5 .. W - 0.5``. The reference shows the crop rectangle of the source (`reference_crop`). A target shows
a quadrilateral of the source: the crop's corners moved by a keystone (yaw and pitch), a zoom, an in-plane
rotation and a shift, all about the crop's centre (DeTone et al. 2018, homographic adaptation). Every
quadrilateral is drawn again until it lies inside the source frame with a one-pixel margin, so every target
pixel shows real image content, never a border. ``H_1_k = T_k^-1 R`` maps reference pixels to target pixels
(``x_k ~ H [x_1, y_1, 1]``), where R and T_k map reference and target pixels to source pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

CROP_SHARE = 0.75        # the reference crop: this share of the largest centred crop of the output's aspect
INSIDE_MARGIN = 1.0      # px of source the quadrilateral keeps from the frame edge (bilinear taps stay inside)
TRIES_PER_LEVEL = 12     # draws at one strength before the strength is lowered
LEVEL_DECAY = 0.85       # strength kept after TRIES_PER_LEVEL draws that left the frame


@dataclass(frozen=True)
class HomographyRanges:
    """The largest change of each kind, reached at strength 1 (the hardest target of a sequence).

    ``zoom``: the quadrilateral is scaled by a factor in ``[1/zoom, zoom]`` (log-uniform); ``rotation_deg``:
    in-plane rotation; ``keystone``: a corner moves by up to this share of the crop's half side (yaw moves
    the left and right edges' corners vertically, pitch the top and bottom ones horizontally); ``shift``:
    translation, share of the crop's side.
    """

    zoom: float = 1.4
    rotation_deg: float = 25.0
    keystone: float = 0.2
    shift: float = 0.1


@dataclass(frozen=True)
class CaptureNoise:
    """Each view of a viewpoint sequence is its own exposure: a gain in ``1 +- gain``, a gamma in
    ``1 +- gamma`` and Gaussian sensor noise of ``sigma`` grey levels, drawn independently per image. Without
    it a target is an exact warp of the reference's pixels, which real viewpoint pairs never are (SIFT then
    solved 98 % of the pairs within 1 px, 60 % on hpatches_v_dogman). All zero: exact warps."""

    gain: float = 0.15
    gamma: float = 0.1
    sigma: float = 2.0


def capture(image: np.ndarray, rng: np.random.Generator, noise: CaptureNoise) -> np.ndarray:
    """``image`` (HxW uint8) as one exposure of `CaptureNoise`; the same geometry, so registration holds."""
    gain = 1.0 + rng.uniform(-noise.gain, noise.gain)
    gamma = 1.0 + rng.uniform(-noise.gamma, noise.gamma)
    exposed = 255.0 * np.clip(gain * (image.astype(np.float64) / 255.0) ** gamma, 0.0, 1.0)
    noisy = exposed + rng.normal(0.0, noise.sigma, size=image.shape) if noise.sigma > 0 else exposed
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def reference_crop(source_shape: tuple[int, int], out_size: tuple[int, int]) -> tuple[float, np.ndarray]:
    """The reference view of a source frame: ``(shrink, R)``.

    ``shrink`` <= 1 is the factor to resize the source by first, so the crop is no larger than the output
    (rendered by interpolation, not aliasing); R (3x3) maps output pixels to pixels of the shrunk source.
    The crop is centred, of the output's aspect, `CROP_SHARE` of the largest such crop: the rest is the
    margin the targets' quadrilaterals move in.
    """
    height, width = source_shape
    out_h, out_w = out_size
    largest = min(width / out_w, height / out_h)       # source px per output px of the largest crop
    scale = CROP_SHARE * largest
    shrink = min(1.0, 1.0 / scale)
    scale *= shrink
    left = (width * shrink - 1.0) / 2.0 - scale * out_w / 2.0    # the crop's left edge, shrunk-source px
    top = (height * shrink - 1.0) / 2.0 - scale * out_h / 2.0
    # x_src = left + (x_out + 0.5) * scale: the output's edge -0.5 meets the crop's edge
    matrix = np.array([[scale, 0.0, left + 0.5 * scale], [0.0, scale, top + 0.5 * scale], [0.0, 0.0, 1.0]])
    return shrink, matrix


def shrink_source(source: np.ndarray, shrink: float) -> np.ndarray:
    """The source resized by ``shrink`` (<= 1, area interpolation), as `reference_crop` asks."""
    if shrink >= 1.0:
        return source
    size = (max(1, round(source.shape[1] * shrink)), max(1, round(source.shape[0] * shrink)))
    return cv2.resize(source, size, interpolation=cv2.INTER_AREA)


def output_corners(out_size: tuple[int, int]) -> np.ndarray:
    """``[4, 2]`` the output image's outer corners (pixel edges), clockwise from top left."""
    out_h, out_w = out_size
    return np.array([[-0.5, -0.5], [out_w - 0.5, -0.5], [out_w - 0.5, out_h - 0.5], [-0.5, out_h - 0.5]])


def _signed(rng: np.random.Generator, level: float, largest: float) -> float:
    """A change of random sign and a magnitude uniform in ``[0.4, 1] * level * largest``."""
    return float(rng.choice((-1.0, 1.0)) * rng.uniform(0.4, 1.0) * level * largest)


def perturbed_quad(crop: np.ndarray, level: float, rng: np.random.Generator, ranges: HomographyRanges) -> np.ndarray:
    """``[4, 2]`` the crop's corners (clockwise from top left, source px) moved at strength ``level`` (0..1]."""
    centre = crop.mean(axis=0)
    half_w, half_h = (crop[1, 0] - crop[0, 0]) / 2.0, (crop[3, 1] - crop[0, 1]) / 2.0
    corners = crop - centre
    yaw, pitch = _signed(rng, level, ranges.keystone), _signed(rng, level, ranges.keystone)
    # yaw: the left edge grows as the right one shrinks; pitch: the top edge as the bottom one
    corners = corners + np.array([[pitch * half_w, yaw * half_h], [-pitch * half_w, -yaw * half_h],
                                  [pitch * half_w, yaw * half_h], [-pitch * half_w, -yaw * half_h]])
    corners = corners * math.exp(_signed(rng, level, math.log(ranges.zoom)))
    angle = math.radians(_signed(rng, level, ranges.rotation_deg))
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    corners = corners @ rotation.T
    shift = np.array([_signed(rng, level, ranges.shift) * 2 * half_w, _signed(rng, level, ranges.shift) * 2 * half_h])
    return corners + centre + shift


def _inside(quad: np.ndarray, source_shape: tuple[int, int]) -> bool:
    """The quadrilateral lies inside the frame (with `INSIDE_MARGIN`) and is convex, so its whole area does."""
    height, width = source_shape
    x, y = quad[:, 0], quad[:, 1]
    if x.min() < INSIDE_MARGIN or y.min() < INSIDE_MARGIN:
        return False
    if x.max() > width - 1 - INSIDE_MARGIN or y.max() > height - 1 - INSIDE_MARGIN:
        return False
    edges = np.roll(quad, -1, axis=0) - quad
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return bool(np.all(turns > 0))


def target_quad(crop: np.ndarray, level: float, rng: np.random.Generator, source_shape: tuple[int, int],
                ranges: HomographyRanges) -> np.ndarray:
    """A `perturbed_quad` inside the source frame: drawn again (and, after `TRIES_PER_LEVEL` draws, at a lower
    strength) until it fits; deterministic for a given ``rng`` state. The crop itself fits by construction."""
    while level > 1e-3:
        for _ in range(TRIES_PER_LEVEL):
            quad = perturbed_quad(crop, level, rng, ranges)
            if _inside(quad, source_shape):
                return quad
        level *= LEVEL_DECAY
    return crop.copy()


def corner_motion(homography: np.ndarray, out_size: tuple[int, int]) -> float:
    """How far a homography moves the output's corners, mean px: the easy-to-hard order of targets."""
    corners = output_corners(out_size)
    moved = np.concatenate([corners, np.ones((4, 1))], axis=1) @ homography.T
    return float(np.linalg.norm(moved[:, :2] / moved[:, 2:] - corners, axis=1).mean())


def render(source: np.ndarray, to_source: np.ndarray, out_size: tuple[int, int]) -> np.ndarray:
    """The output image whose pixel x shows source pixel ``to_source @ x`` (bilinear). The border is black on
    purpose: a quadrilateral outside the frame would show, and the tests look for it."""
    return cv2.warpPerspective(source, to_source, (out_size[1], out_size[0]), flags=cv2.INTER_LINEAR |
                               cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def viewpoint_targets(source: np.ndarray, reference: np.ndarray, out_size: tuple[int, int], count: int,
                      rng: np.random.Generator,
                      ranges: HomographyRanges = HomographyRanges()) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` (target image HxW uint8, H 3x3 reference -> target) sorted by `corner_motion`, easy first.

    ``source`` is the (shrunk) source frame, ``reference`` its R of `reference_crop`. Target k is drawn at
    strength ``k / count``, so the strengths spread over the whole range before the sort makes it exact.
    """
    crop = np.concatenate([output_corners(out_size), np.ones((4, 1))], axis=1) @ reference.T
    crop = crop[:, :2] / crop[:, 2:]
    targets = []
    for k in range(1, count + 1):
        quad = target_quad(crop, k / count, rng, source.shape[:2], ranges)
        to_source = cv2.getPerspectiveTransform(output_corners(out_size).astype(np.float32), quad.astype(np.float32))
        homography = np.linalg.inv(to_source) @ reference
        targets.append((render(source, to_source, out_size), homography / homography[2, 2]))
    return sorted(targets, key=lambda target: corner_motion(target[1], out_size))
