"""Losses of the distill recipe: keypoint cross-entropy, descriptor distillation and InfoNCE across views.

    total = CE(a) + CE(b)                                  teacher keypoints, one per cell, 65-way
          + distill_weight * mean(1 - cos(P d_s, d_t))    student descriptor of a cell, projected by a
                                                           training-only P (256 -> 128), against the
                                                           teacher's descriptor of the same scene point
          + nce_weight * InfoNCE(a <-> b)                  a cell of a must pick its own scene point in b
                                                           among the other sampled cells

The projection makes the 256 vs 128 dimensions meet without constraining the student's own space; it is
never exported. InfoNCE keeps the student's own descriptors discriminative across the homography.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from models.keypoints import Refinement, heatmap_from_logits, max_pool_nms, peak_windows, refine_keypoints
from toolkit.training.distill_pairs import sample_map
from toolkit.training.homographies import points_inside, warp_points
from toolkit.training.losses import cell_centres, detector_loss
from toolkit.training.pairs import CELL, DUSTBIN


NEGATIVE_MIN_DISTANCE = 4.0  # px: anchors nearer each other than this are not negatives


@dataclass
class DistillLossConfig:
    distill_weight: float = 2.0
    nce_weight: float = 0.25
    temperature: float = 0.1  # InfoNCE logits = cosine / temperature
    nce_cells: int = 256  # cells of view a per image in the InfoNCE (bounds the [N, N] matrix)
    # Spread a keypoint's target over its pixel and the neighbours its sub-pixel offset leans to (bilinear
    # weights), so the heatmap's 3x3 centroid (`models.keypoints.refine_keypoints`) learns the position.
    subpixel_targets: bool = False
    # Where the InfoNCE anchors of view a lie: "cells" (every cell centre) or "keypoints" (the teacher's
    # keypoints of a, the student's map sampled there bilinearly as at inference, against each other).
    nce_anchors: str = "cells"
    # Positions trained directly (`position_loss`): the sub-pixel keypoint the graph computes from the student's
    # heatmap, by the refinement the model names (``model.refinement``), against the teacher's keypoint.
    position_weight: float = 0.0
    peakiness_weight: float = 0.0  # keeps the mass of a keypoint's window on its peak pixel
    # Which teacher keypoints the position loss pulls on: "all" (one per labelled cell) or "detected" (those
    # whose student peak is a detection: a local maximum within the NMS radius above the detection threshold).
    position_targets: str = "all"

    def __post_init__(self) -> None:
        if self.position_targets not in ("all", "detected"):
            raise ValueError('position_targets must be "all" or "detected"')
        if self.nce_anchors not in ("cells", "keypoints"):
            raise ValueError('nce_anchors must be "cells" or "keypoints"')
        if self.temperature <= 0 or self.nce_cells < 2:
            raise ValueError("temperature must be > 0 and nce_cells >= 2")
        if min(self.distill_weight, self.nce_weight, self.position_weight, self.peakiness_weight) < 0:
            raise ValueError("loss weights must be >= 0")


class DescriptorProjection(nn.Module):
    """Training-only linear map from the student's descriptor space to the teacher's. [B, Ds, h, w] -> [B, Dt, h, w]."""

    def __init__(self, student_dim: int, teacher_dim: int) -> None:
        super().__init__()
        self.linear = nn.Conv2d(student_dim, teacher_dim, 1, bias=False)

    def forward(self, descriptors: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.linear(descriptors.float()), p=2.0, dim=1)


def distillation_loss(projected: torch.Tensor, teacher: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """mean(1 - cos) over valid cells. projected, teacher [B, D, h, w] unit vectors; valid [B, h, w] bool."""
    cosine = (projected.float() * teacher.float()).sum(dim=1)
    weights = valid.float()
    return ((1.0 - cosine) * weights).sum() / weights.sum().clamp_min(1.0)


def keypoint_positions(labels: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
    """Pixel (x, y) of each labelled cell's keypoint, [N, 2], row-major over cells; dustbin cells skipped.

    labels [h, w] int64 in 0..64; offsets [2, h, w] sub-pixel (x, y) offsets from the labelled pixel, or None.
    """
    rows, cols = (labels < DUSTBIN).nonzero(as_tuple=True)
    inner = labels[rows, cols]
    points = torch.stack([cols * CELL + inner % CELL, rows * CELL + inner // CELL], dim=1).float()
    if offsets is not None:
        points = points + offsets[:, rows, cols].T.float()
    return points


def info_nce_loss(
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    homography: torch.Tensor,
    valid_b: torch.Tensor,
    config: DistillLossConfig,
    generator: torch.Generator | None = None,
    anchors: list[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Symmetric InfoNCE between points of a and the same scene points in b.

    Args:
        descriptors_a, descriptors_b: [B, D, h, w] unit vectors; homography [B, 3, 3] a -> b pixels;
        valid_b [B, h, w] bool (cells of b whose content comes from a);
        anchors: per image [N_i, 2] pixel points of a, sampled bilinearly; None: every cell centre.
    Returns:
        scalar, the mean over images that have at least two usable points.
    """
    batch, _, height, width = descriptors_a.shape
    centres = cell_centres(height, width, descriptors_a.device)
    losses = []
    for i in range(batch):
        points = centres if anchors is None else anchors[i].to(descriptors_a.device)
        warped = warp_points(points, homography[i].float())
        usable = points_inside(warped, (height * 8, width * 8), border=4)
        cell_b = (warped / 8.0).floor().long()
        usable &= valid_b[i][cell_b[:, 1].clamp(0, height - 1), cell_b[:, 0].clamp(0, width - 1)]
        index = usable.nonzero()[:, 0]
        if index.numel() < 2:
            continue
        if index.numel() > config.nce_cells:
            index = index[torch.randperm(index.numel(), generator=generator)[: config.nce_cells].to(index.device)]
        from_a = sample_map(descriptors_a[i], points[index])  # at a cell centre: that cell's vector exactly
        positives = sample_map(descriptors_b[i], warped[index])
        logits = from_a @ positives.T / config.temperature
        # points closer than a match tolerance are the same point, not negatives (cell centres never are)
        near = torch.cdist(points[index], points[index]) < NEGATIVE_MIN_DISTANCE
        near.fill_diagonal_(False)
        logits = logits.masked_fill(near, float("-inf"))
        target = torch.arange(index.numel(), device=logits.device)
        losses.append(0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target)))
    if not losses:
        return descriptors_a.sum() * 0.0
    return torch.stack(losses).mean()


def subpixel_detector_loss(
    logits: torch.Tensor, labels: torch.Tensor, offsets: torch.Tensor, valid: torch.Tensor | None = None
) -> torch.Tensor:
    """65-way cross-entropy against bilinear sub-pixel targets, averaged over valid cells.

    A keypoint at offset (ox, oy) from the centre of its labelled pixel puts (1-|ox|)(1-|oy|) of the target
    on that pixel, |ox|(1-|oy|) on the horizontal neighbour it leans to, and so on; weight that would land
    outside the cell is dropped and the rest renormalised. Offsets of 0 give the hard-label cross-entropy.

    Args:
        logits: [B, 65, h, w]; labels: [B, h, w] int64 in 0..64; offsets: [B, 2, h, w] (x, y) in [-0.5, 0.5];
        valid: [B, h, w] bool or None.
    """
    log_p = F.log_softmax(logits.float(), dim=1)
    column, row = labels % CELL, labels // CELL  # dustbin cells (64) give row 8: never inside below
    step_x, step_y = torch.sign(offsets[:, 0]).long(), torch.sign(offsets[:, 1]).long()
    weight_x, weight_y = offsets[:, 0].abs(), offsets[:, 1].abs()
    total, mass = torch.zeros_like(weight_x), torch.zeros_like(weight_x)
    for use_x, use_y in ((0, 0), (1, 0), (0, 1), (1, 1)):
        x, y = column + use_x * step_x, row + use_y * step_y
        inside = (x >= 0) & (x < CELL) & (y >= 0) & (y < CELL)
        weight = (weight_x if use_x else 1 - weight_x) * (weight_y if use_y else 1 - weight_y) * inside
        total = total + log_p.gather(1, torch.where(inside, y * CELL + x, 0)[:, None])[:, 0] * weight
        mass = mass + weight
    dustbin = log_p[:, DUSTBIN]
    per_cell = -torch.where(labels < DUSTBIN, total / mass.clamp_min(1e-6), dustbin)
    if valid is None:
        return per_cell.mean()
    mask = valid.float()
    return (per_cell * mask).sum() / mask.sum().clamp_min(1.0)


def keypoint_loss(outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], view: str,
                  config: DistillLossConfig) -> torch.Tensor:
    """One view's keypoint term: hard 65-way labels, or sub-pixel targets with ``config.subpixel_targets``."""
    valid = batch["valid_b"] if view == "b" else None
    if config.subpixel_targets:
        return subpixel_detector_loss(outputs["logits"], batch[f"labels_{view}"], batch[f"offsets_{view}"], valid)
    return detector_loss(outputs["logits"], batch[f"labels_{view}"], valid)


def distill_loss(
    outputs_a: dict[str, torch.Tensor],
    outputs_b: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    projection: DescriptorProjection,
    config: DistillLossConfig,
    generator: torch.Generator | None = None,
    refinement: Refinement = Refinement(),
) -> dict[str, torch.Tensor]:
    """The recipe's total loss and its parts (scalars; the parts detached). ``refinement``: the model's own."""
    detector = keypoint_loss(outputs_a, batch, "a", config) + keypoint_loss(outputs_b, batch, "b", config)
    position = peakiness = detector * 0.0
    if config.position_weight > 0 or config.peakiness_weight > 0:
        for view in ("a", "b"):
            targets = [keypoint_positions(labels, offsets) if view == "a" else
                       keypoint_positions(torch.where(valid, labels, DUSTBIN), offsets)
                       for labels, offsets, valid in zip(batch[f"labels_{view}"], batch[f"offsets_{view}"], batch["valid_b"])]
            view_position, view_peakiness = position_loss(
                (outputs_a if view == "a" else outputs_b)["logits"], targets, refinement,
                config.position_targets == "detected")
            position, peakiness = position + 0.5 * view_position, peakiness + 0.5 * view_peakiness
        detector = detector + config.position_weight * position + config.peakiness_weight * peakiness
    distill = 0.5 * (
        distillation_loss(projection(outputs_a["descriptors"]), batch["teacher_a"], batch["teacher_valid_a"])
        + distillation_loss(projection(outputs_b["descriptors"]), batch["teacher_b"], batch["teacher_valid_b"])
    )
    anchors = None
    if config.nce_anchors == "keypoints":
        anchors = [keypoint_positions(labels, offsets) for labels, offsets in zip(batch["labels_a"], batch["offsets_a"])]
    nce = info_nce_loss(
        outputs_a["descriptors"], outputs_b["descriptors"], batch["homography"], batch["valid_b"], config, generator,
        anchors,
    )
    total = detector + config.distill_weight * distill + config.nce_weight * nce
    return {
        "loss": total,
        "detector_loss": detector.detach(),
        "descriptor_loss": (config.distill_weight * distill + config.nce_weight * nce).detach(),
        "distill_loss": distill.detach(),
        "nce_loss": nce.detach(),
        "position_loss": position.detach(),
        "peakiness_loss": peakiness.detach(),
    }


def student_peaks(heatmap: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The integer pixel the inference would refine from, for each target: the student's highest heatmap
    pixel in the 3x3 around the target's nearest pixel (NMS picks a peak, not the target's pixel).

    heatmap [1, 1, H, W]; targets [N, 2] float (x, y) -> [N, 2] integer-valued float, inside the image.
    """
    _, _, height, width = heatmap.shape
    nearest = torch.stack([targets[:, 0].round().clamp(0, width - 1), targets[:, 1].round().clamp(0, height - 1)], 1)
    windows, offsets = peak_windows(heatmap.detach(), nearest, 1)
    peaks = nearest + offsets[windows.argmax(dim=1)]
    return torch.stack([peaks[:, 0].clamp(0, width - 1), peaks[:, 1].clamp(0, height - 1)], dim=1)


DETECTION_NMS_RADIUS, DETECTION_THRESHOLD = 4, 0.005  # as `toolkit export` bakes into the graph by default


def detected(heatmap: torch.Tensor, peaks: torch.Tensor) -> torch.Tensor:
    """[N] bool: the integer ``peaks`` [N, 2] of ``heatmap`` [1, 1, H, W] that the graph would keep (a maximum
    within the NMS radius, above the detection threshold)."""
    _, _, _, width = heatmap.shape
    kept = max_pool_nms(heatmap.detach(), DETECTION_NMS_RADIUS).reshape(-1)  # the graph's own NMS
    return kept[(peaks[:, 1] * width + peaks[:, 0]).long()] > DETECTION_THRESHOLD


def position_loss(logits: torch.Tensor, targets: list[torch.Tensor], refinement: Refinement,
                  only_detected: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Localisation trained directly: (mean smooth-L1 distance in px, mean peakiness) over every target.

    The student's sub-pixel keypoint is `refine_keypoints` (the function the exported graph runs) from the
    student's own peak next to each teacher keypoint; its distance to the keypoint is the position term.
    Peakiness is 1 - the peak pixel's share of its 3x3 window's mass: low when the score is sharp, so the
    position can be learned without the heatmap spreading out. A target near a pixel border can flip the
    student's peak to the neighbour, where a 3x3 centroid meets its half-pixel clamp: the gradient passes
    through the clamp, so the mass is still pulled towards the target and the peak flips back.

    Args:
        logits: [B, 65, h, w]; targets: per image [N_i, 2] (x, y) pixel positions (view pixels).
    """
    heatmap = heatmap_from_logits(logits.float())
    errors, spreads = [], []
    for index, points in enumerate(targets):
        if points.numel() == 0:
            continue
        image = heatmap[index : index + 1]
        points = points.to(image.device).float()
        peaks = student_peaks(image, points)
        if only_detected:
            keep = detected(image, peaks)
            points, peaks = points[keep], peaks[keep]
            if points.numel() == 0:
                continue
        refined = refine_keypoints(image, peaks, refinement, gradient_through_clamp=True)
        errors.append(F.smooth_l1_loss(refined, points, reduction="none", beta=0.5).sum(1))
        windows, _ = peak_windows(image, peaks, 1)
        spreads.append(1.0 - windows[:, 4] / windows.sum(1).clamp_min(1e-6))
    if not errors:
        zero = logits.sum() * 0.0
        return zero, zero
    return torch.cat(errors).mean(), torch.cat(spreads).mean()
