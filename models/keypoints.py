"""Heads to keypoints: softmax + depth-to-space, max-pool NMS, fixed-K top-k, descriptor sampling.

Every function is written with fixed shapes and export-friendly ops (no GridSample, no GatherND, no
NonZero; Gather indices are clamped to be non-negative), so the same code runs in PyTorch and inside the
exported ONNX graph for TensorRT 8.0.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

CELL = 8


def heatmap_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """logits [B, 65, h, w] -> keypoint probability [B, 1, 8h, 8w] (softmax over 65, dustbin dropped).

    Channel ``dy * 8 + dx`` of cell (y, x) lands on pixel (8y + dy, 8x + dx), as ``F.pixel_shuffle``. The
    softmax runs over the last axis of a channels-last copy: onnxruntime's Softmax over axis 1 of NCHW
    transposes internally and took 3x as long (0.63 against 0.20 ms at 240x320, one thread).
    """
    batch, _, height, width = logits.shape
    probabilities = torch.softmax(logits.permute(0, 2, 3, 1), dim=-1)[..., :-1]  # [B, h, w, 64]
    cells = probabilities.reshape(batch, height, width, CELL, CELL).permute(0, 1, 3, 2, 4)  # [B, h, dy, w, dx]
    return cells.reshape(batch, 1, height * CELL, width * CELL)


def max_pool_nms(heatmap: torch.Tensor, radius: int) -> torch.Tensor:
    """Keep local maxima in a (2r+1)^2 window, zero elsewhere. [B, 1, H, W] -> [B, 1, H, W]."""
    if radius <= 0:
        return heatmap
    pooled = F.max_pool2d(heatmap, kernel_size=2 * radius + 1, stride=1, padding=radius)
    return heatmap * (heatmap == pooled).to(heatmap.dtype)


def is_score_window(window: int) -> bool:
    """Whether ``window`` is a `keypoint_scores` window: an odd number of pixels, 1 or more."""
    return window >= 1 and window % 2 == 1


def keypoint_scores(heatmap: torch.Tensor, window: int, threshold: float = 0.0) -> torch.Tensor:
    """Score each local maximum of the heatmap by the probability mass of its ``window`` x ``window``
    neighbourhood; zero elsewhere and where the peak itself is at or below ``threshold``, so a detection
    threshold keeps the points it kept before. [B, 1, H, W] -> same.

    A 65-way cell softmax spreads one keypoint's probability over neighbouring pixels (and across cell
    borders) when the network is unsure where exactly it lies. Ranking by the peak pixel then prefers
    points whose position is certain over points that are certainly there; the mass is the probability
    that a keypoint lies in the window, which is what repeats under a change of view. On the shipped ELU
    model (hpatches_v_dogman, 500 keypoints, 3 px) the matching score rose 0.292 -> 0.303 at 240x320
    (window 3) and 0.218 -> 0.275 at 480x640 (window 5), where the network spreads its probability wider.
    It is not the default: the VO wants the sharpest peaks. With window 3 the shipped ReLU artefact's KITTI 07
    ATE (geometric mean of 14 runs, `bench/vo_settings.py`) rose 0.126 -> 0.227 m (docs/vo.md).
    Only the heatmap's own 3x3 peaks are candidates: the window sums of a sharp peak's neighbours equal its
    own to within rounding, and NMS would keep such ties as duplicate points. ``window`` 1 is the heatmap.
    AveragePool / MaxPool / Equal in ONNX, which TensorRT 8.0 parses.
    """
    if window <= 1:
        return heatmap
    peaks = (heatmap == F.max_pool2d(heatmap, kernel_size=3, stride=1, padding=1)).to(heatmap.dtype)
    mean = F.avg_pool2d(heatmap, kernel_size=window, stride=1, padding=window // 2, count_include_pad=True)
    return mean * float(window * window) * peaks * (heatmap > threshold).to(heatmap.dtype)


def border_mask(height: int, width: int, border: int, like: torch.Tensor) -> torch.Tensor:
    """[H, W] mask, 1 inside, 0 within ``border`` pixels of the edge (a broadcast product of two 1-D masks)."""
    rows = torch.zeros(height, dtype=like.dtype, device=like.device)
    cols = torch.zeros(width, dtype=like.dtype, device=like.device)
    rows[border : height - border] = 1.0
    cols[border : width - border] = 1.0
    return rows[:, None] * cols[None, :]


def top_k_keypoints(scores: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """scores [H, W] -> keypoints [k, 2] (x, y) float and their scores [k], best first.

    The coordinates are read from a constant [H*W, 2] table at the top-k indices: no integer division
    (which TensorRT 8.0 handles poorly) and no flat index in floating point, which half precision cannot
    hold (76,799 at 240x320 is beyond FP16's 65,504) when TensorRT runs a layer in FP16. Every value in the
    table is below 2,048, so exact in FP16.
    """
    height, width = scores.shape
    values, indices = torch.topk(scores.reshape(-1), k)
    rows = torch.arange(height, dtype=scores.dtype, device=scores.device)
    cols = torch.arange(width, dtype=scores.dtype, device=scores.device)
    table = torch.stack([cols.repeat(height), rows.repeat_interleave(width)], dim=1)  # [H*W, 2]
    return torch.index_select(table, 0, indices), values


REFINEMENTS = ("centroid", "softargmax", "quadratic")


@dataclass(frozen=True)
class Refinement:
    """How a heatmap peak becomes a sub-pixel keypoint (`refine_keypoints`).

    - ``centroid``: the probability-weighted mean offset of the (2r+1)^2 window (3x3 by default);
    - ``softargmax``: weights ``exp((p - max) / temperature)`` over the window, as ALIKE's DKD (radius 2,
      temperature 0.1 on its score map): a low temperature listens to the highest values only, so a wide
      window does not let background mass pull the point;
    - ``quadratic``: a parabola through the log-probabilities of the peak and its two neighbours, per axis
      (exact for a Gaussian-shaped peak).
    A centroid's offset is clamped to ``radius - 0.5`` (half a pixel for 3x3: the peak's own pixel), a
    soft-argmax's to ``radius``, a parabola's to half a pixel.
    """

    method: str = "centroid"
    radius: int = 1
    temperature: float = 0.1

    def __post_init__(self) -> None:
        if self.method not in REFINEMENTS:
            raise ValueError(f"refinement must be one of {', '.join(REFINEMENTS)}, not {self.method!r}")
        if not 1 <= self.radius <= 3 or not (self.temperature > 0 and math.isfinite(self.temperature)):
            raise ValueError("refinement radius must be 1..3 and its temperature a positive number")

    def describe(self) -> str:
        if self.method == "softargmax":
            return f"softargmax:{2 * self.radius + 1}:{self.temperature:g}"
        return self.method if self.radius == 1 or self.method == "quadratic" else f"centroid:{2 * self.radius + 1}"


def parse_refinement(text: str) -> Refinement:
    """``centroid``, ``centroid:5``, ``quadratic``, ``softargmax`` (5x5, 0.1) or ``softargmax:W:T`` -> Refinement."""
    parts = text.strip().split(":")
    method = parts[0]
    try:
        window = int(parts[1]) if len(parts) > 1 else (5 if method == "softargmax" else 3)
        temperature = float(parts[2]) if len(parts) > 2 else 0.1
    except ValueError:
        raise ValueError(f"refinement {text!r}: the window must be an odd integer and the temperature a number") from None
    if len(parts) > (3 if method == "softargmax" else 2 if method == "centroid" else 1) or window % 2 == 0:
        raise ValueError(f"refinement {text!r} is not one of centroid[:W], quadratic, softargmax[:W[:T]] (W odd)")
    return Refinement(method, window // 2, temperature)


def model_refinement(net: torch.nn.Module, override: str = "") -> Refinement:
    """``override`` (a `parse_refinement` text) or the refinement a network's config names; the 3x3 centroid for
    networks without one (SuperPoint, weights trained before the setting existed)."""
    config = getattr(net, "config", None)
    return parse_refinement(override or getattr(config, "refinement", "centroid"))


def peak_windows(heatmap: torch.Tensor, keypoints: torch.Tensor, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The (2r+1)^2 heatmap values around each integer keypoint, zero outside the image.

    Args:
        heatmap: [1, 1, H, W]; keypoints: [K, 2] integer (x, y).
    Returns:
        windows [K, (2r+1)^2] row-major, offsets [(2r+1)^2, 2] (dx, dy) of each window column.

    The indices are int32 arithmetic on a zero-bordered map (no clamping, always in range): a flat index in
    floating point would overflow half precision (see `top_k_keypoints`). Only the K windows are read.
    """
    _, _, height, width = heatmap.shape
    side = 2 * radius + 1
    padded = F.pad(heatmap, (radius, radius, radius, radius)).reshape(-1)
    step = torch.arange(-radius, radius + 1, dtype=torch.int32, device=heatmap.device)
    step_x, step_y = step.repeat(side), step.repeat_interleave(side)
    window_offsets = step_y * (width + 2 * radius) + step_x
    rows = keypoints[:, 1:].to(torch.int32) + radius
    centre = rows * (width + 2 * radius) + keypoints[:, :1].to(torch.int32) + radius  # [K, 1]
    windows = torch.index_select(padded, 0, (centre + window_offsets).reshape(-1)).reshape(-1, side * side)
    offsets = torch.stack([step_x, step_y], dim=1).to(heatmap.dtype)
    return windows, offsets


def refine_keypoints(heatmap: torch.Tensor, keypoints: torch.Tensor, refinement: Refinement = Refinement(),
                     gradient_through_clamp: bool = False) -> torch.Tensor:
    """Sub-pixel keypoints from the heatmap around each integer peak (`Refinement` says how).

    Args:
        heatmap: [1, 1, H, W] keypoint probability (before NMS).
        keypoints: [K, 2] integer (x, y) peaks from `top_k_keypoints`.
    Returns:
        [K, 2] float (x, y). The 8x8-cell softmax puts a point's mass on neighbouring pixels too; the integer
        peak alone costs ~0.07 px of localisation error on HPatches. Differentiable in ``heatmap`` (the
        position loss of training runs this very function).

    ``gradient_through_clamp`` (training only): the clamped value, with the gradient of the unclamped one, so
    a point whose peak flipped to the neighbouring pixel is still pulled back instead of resting at the clamp.
    """
    if refinement.method == "quadratic":
        return keypoints + _clamped(_quadratic_shift(heatmap, keypoints), 0.5, gradient_through_clamp)
    windows, offsets = peak_windows(heatmap, keypoints, refinement.radius)
    if refinement.method == "softargmax":
        peak = windows.max(dim=1, keepdim=True).values.detach()
        windows = torch.exp((windows - peak) / refinement.temperature)
    moments = windows @ torch.cat([torch.ones_like(offsets[:, :1]), offsets], dim=1)  # [K, 3]: mass, x, y
    shift = moments[:, 1:] / moments[:, :1].clamp(min=1e-12)
    limit = refinement.radius - 0.5 if refinement.method == "centroid" else float(refinement.radius)
    return keypoints + _clamped(shift, limit, gradient_through_clamp)


def _clamped(shift: torch.Tensor, limit: float, gradient_through: bool) -> torch.Tensor:
    clamped = shift.clamp(-limit, limit)
    return shift + (clamped - shift).detach() if gradient_through else clamped


def _quadratic_shift(heatmap: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
    """Per axis, the vertex of the parabola through log p at -1, 0, +1 of the peak (unclamped)."""
    windows, _ = peak_windows(heatmap, keypoints, 1)
    logs = torch.log(windows.clamp(min=1e-6))
    centre = logs[:, 4:5]
    left_right = logs[:, [3, 5]]
    up_down = logs[:, [1, 7]]
    shifts = []
    for low_high in (left_right, up_down):
        curvature = (low_high[:, :1] + low_high[:, 1:] - 2.0 * centre).clamp(max=-1e-6)  # a peak curves down
        shifts.append(0.5 * (low_high[:, :1] - low_high[:, 1:]) / curvature)
    return torch.cat(shifts, dim=1)


def unit_rows(x: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """``x`` scaled to unit L2 norm along ``dim`` (as ``F.normalize``, eps 1e-12), by a broadcast division:
    ``F.normalize`` exports an Expand of the norm to the full shape first, an extra full-size copy."""
    return x / torch.linalg.vector_norm(x, dim=dim, keepdim=True).clamp(min=1e-12)


def sample_descriptors(
    descriptors: torch.Tensor, keypoints: torch.Tensor, projection: tuple[torch.Tensor, torch.Tensor] | None = None
) -> torch.Tensor:
    """Bilinearly sample a coarse descriptor map at pixel keypoints and re-normalise.

    Args:
        descriptors: [C, h, w], one vector per 8x8 cell, centred on the cell's centre pixel.
        keypoints: [K, 2] (x, y) in full-resolution pixels (pixel centres at integers).
        projection: optional (weight [D, C], bias [D]) applied to the sampled vectors before the
            normalisation: a network's final 1x1 descriptor conv run at K points instead of every cell.
    Returns:
        [K, D] (D = C without a projection), unit L2 norm. Positions beyond the outer cell centres take
        the edge value.

    One Gather per corner and two lerps: a stacked [4, K, D] product summed over its first axis ran
    ~7x slower in onnxruntime (a strided ReduceSum over a million values).
    """
    dim, height, width = descriptors.shape
    u = ((keypoints[:, 0] + 0.5) / CELL - 0.5).clamp(0.0, float(width - 1))
    v = ((keypoints[:, 1] + 0.5) / CELL - 0.5).clamp(0.0, float(height - 1))
    u0 = torch.floor(u).clamp(max=float(max(width - 2, 0)))
    v0 = torch.floor(v).clamp(max=float(max(height - 2, 0)))
    wu = (u - u0)[:, None]
    wv = (v - v0)[:, None]
    u1 = (u0 + 1.0).clamp(max=float(width - 1))
    v1 = (v0 + 1.0).clamp(max=float(height - 1))
    table = descriptors.reshape(dim, height * width).transpose(0, 1)  # [h*w, D]

    def corner(row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        # int32 arithmetic: at 480x640 the flat index reaches 4,799, no longer exact in half precision
        return torch.index_select(table, 0, row.to(torch.int32) * width + col.to(torch.int32))  # [K, D]

    top_left, top_right, bottom_left, bottom_right = corner(v0, u0), corner(v0, u1), corner(v1, u0), corner(v1, u1)
    top = top_left + (top_right - top_left) * wu
    bottom = bottom_left + (bottom_right - bottom_left) * wu
    sampled = top + (bottom - top) * wv
    if projection is not None:
        weight, bias = projection
        sampled = F.linear(sampled, weight, bias)
    return unit_rows(sampled)


def keypoint_heads(
    net: torch.nn.Module, image: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
    """A network's heads for `extract_keypoints`: (logits, descriptor map, descriptor projection or None).

    Networks with a ``descriptor_projection`` (FeatureNet) hand over their descriptor head before its final
    1x1 conv (``for_keypoints``), which `sample_descriptors` then applies at the K keypoints only; others
    give their normalised dense descriptors.
    """
    if hasattr(net, "descriptor_projection"):
        heads = net(image, for_keypoints=True)
        return heads["logits"], heads["descriptor_features"], net.descriptor_projection()
    heads = net(image)
    return heads["logits"], heads["descriptors"], None


def extract_keypoints(
    logits: torch.Tensor,
    descriptors: torch.Tensor,
    max_keypoints: int,
    nms_radius: int = 4,
    threshold: float = 0.005,
    border: int = 4,
    border_weights: torch.Tensor | None = None,
    subpixel: bool = True,
    projection: tuple[torch.Tensor, torch.Tensor] | None = None,
    score_window: int = 1,
    refinement: Refinement = Refinement(),
) -> dict[str, torch.Tensor]:
    """One image's heads -> fixed-size keypoint set.

    Args:
        logits: [1, 65, h, w]; descriptors: [1, D, h, w].
        border_weights: a precomputed `border_mask` [8h, 8w] (an export stores it as a constant).
        subpixel: refine each peak to a sub-pixel position (`refine_keypoints` with ``refinement``; the
            default is the 3x3 centroid).
        projection: the descriptor projection from `keypoint_heads`, when ``descriptors`` are features.
        score_window: odd window whose probability mass scores, suppresses and ranks a heatmap peak
            (`keypoint_scores`; 3 at 240x320 and 5 at 480x640 matched best on HPatches); 1, the default,
            scores by the peak pixel. Positions are refined on the heatmap itself.
    Returns:
        keypoints [K, 2] (x, y), scores [K] (descending), descriptors [K, D], num_valid [1] int32:
        rows past ``num_valid`` scored at or below ``threshold`` and are padding.
    """
    heatmap = heatmap_from_logits(logits)
    _, _, height, width = heatmap.shape
    if border_weights is None:
        border_weights = border_mask(height, width, border, heatmap)
    # Reshapes, not [0, 0] / [0]: an index exports as a Gather that copies the whole map.
    candidates = keypoint_scores(heatmap, score_window, threshold)
    scores = max_pool_nms(candidates, nms_radius).reshape(height, width) * border_weights
    keypoints, values = top_k_keypoints(scores, max_keypoints)
    if subpixel:
        keypoints = refine_keypoints(heatmap, keypoints, refinement)
    # Counted in float (exact below 2^24): an integer ReduceSum exports through int64, which TensorRT 8 lacks.
    num_valid = (values > threshold).to(values.dtype).sum().to(torch.int32).reshape(1)
    return {
        "keypoints": keypoints,
        "scores": values,
        "descriptors": sample_descriptors(descriptors.reshape(descriptors.shape[1:]), keypoints, projection),
        "num_valid": num_valid,
    }
