"""SuperPoint losses (DeTone et al. 2018, eq. 10-15): 65-way keypoint cross-entropy per 8x8 cell and the
descriptor hinge loss over all cell pairs, positives being cells within 8 px after the homography.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from toolkit.training.homographies import warp_points

CELL = 8


@dataclass
class LossConfig:
    positive_margin: float = 1.0  # m_p
    negative_margin: float = 0.2  # m_n
    positive_weight: float = 250.0  # lambda_d: balances the few positive pairs against the many negatives
    descriptor_weight: float = 1.0  # lambda (the paper's 1e-4 goes with a summed, not averaged, hinge)
    correspondence_px: float = 8.0  # a cell pair is positive when the warped centre is this close
    sampled_cells: int = 0  # > 0: compare only this many random cells of view a per image (memory)


def detector_loss(logits: torch.Tensor, labels: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy over 65 classes per cell, averaged over valid cells.

    Args:
        logits: [B, 65, h, w]; labels: [B, h, w] int64 in 0..64; valid: [B, h, w] bool or None.
    """
    per_cell = F.cross_entropy(logits.float(), labels, reduction="none")
    if valid is None:
        return per_cell.mean()
    weights = valid.float()
    return (per_cell * weights).sum() / weights.sum().clamp_min(1.0)


def cell_centres(height: int, width: int, device: torch.device | None = None) -> torch.Tensor:
    """Centres of the 8x8 cells in pixels, [h*w, 2] (x, y), row-major."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float32, device=device),
        torch.arange(width, dtype=torch.float32, device=device),
        indexing="ij",
    )
    return torch.stack([xs, ys], dim=-1).reshape(-1, 2) * CELL + (CELL - 1) / 2


def descriptor_loss(
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    homography: torch.Tensor,
    valid_b: torch.Tensor,
    config: LossConfig,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hinge loss over cell pairs (eq. 13-15).

    l(d, d', s) = lambda_d * s * max(0, m_p - d.d') + (1 - s) * max(0, d.d' - m_n), averaged over the pairs
    whose cell in b is valid.

    Args:
        descriptors_a, descriptors_b: [B, D, h, w] unit vectors.
        homography: [B, 3, 3] a -> b pixels.
        valid_b: [B, h, w] bool.
        generator: draws the sampled cells when ``config.sampled_cells`` > 0.
    Returns:
        (loss, fraction of positive pairs) scalars.
    """
    batch, dim, height, width = descriptors_a.shape
    device = descriptors_a.device
    centres = cell_centres(height, width, device)  # [hw, 2]
    flat_a = descriptors_a.float().reshape(batch, dim, -1)
    flat_b = descriptors_b.float().reshape(batch, dim, -1)
    warped = warp_points(centres.expand(batch, -1, -1), homography.float())  # [B, hw, 2]
    if 0 < config.sampled_cells < height * width:
        picks = torch.stack(
            [torch.randperm(height * width, generator=generator)[: config.sampled_cells] for _ in range(batch)]
        ).to(device)
        flat_a = torch.gather(flat_a, 2, picks[:, None].expand(-1, dim, -1))
        warped = torch.gather(warped, 1, picks[..., None].expand(-1, -1, 2))
    distance = torch.cdist(warped, centres.expand(batch, -1, -1))  # [B, n_a, hw]
    positive = (distance <= config.correspondence_px).float()
    dot = torch.einsum("bdi,bdj->bij", flat_a, flat_b)
    hinge = config.positive_weight * positive * F.relu(config.positive_margin - dot) + (1 - positive) * F.relu(
        dot - config.negative_margin
    )
    weights = valid_b.reshape(batch, 1, -1).float().expand_as(hinge)
    loss = (hinge * weights).sum() / weights.sum().clamp_min(1.0)
    positive_fraction = (positive * weights).sum() / weights.sum().clamp_min(1.0)
    return loss, positive_fraction


def superpoint_loss(
    outputs_a: dict[str, torch.Tensor],
    outputs_b: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    config: LossConfig,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Total loss = CE(a) + CE(b) + lambda * hinge; returns the total and its parts (scalars)."""
    detector_a = detector_loss(outputs_a["logits"], batch["labels_a"])
    detector_b = detector_loss(outputs_b["logits"], batch["labels_b"], batch["valid_b"])
    descriptor, positive_fraction = descriptor_loss(
        outputs_a["descriptors"], outputs_b["descriptors"], batch["homography"], batch["valid_b"], config, generator
    )
    total = detector_a + detector_b + config.descriptor_weight * descriptor
    return {
        "loss": total,
        "detector_loss": (detector_a + detector_b).detach(),
        "descriptor_loss": descriptor.detach(),
        "positive_fraction": positive_fraction.detach(),
    }
