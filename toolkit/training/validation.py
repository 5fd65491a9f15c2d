"""Validation on held-back warped pairs: keypoint repeatability and descriptor nearest-neighbour accuracy."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from models.keypoints import border_mask, heatmap_from_logits, max_pool_nms, sample_descriptors
from toolkit.training.homographies import points_inside, valid_mask, warp_points
from toolkit.training.losses import LossConfig, superpoint_loss


@dataclass
class ValidationConfig:
    num_keypoints: int = 300  # per image, top-k after NMS
    nms_radius: int = 4
    border: int = 4
    distance_px: float = 3.0  # a keypoint repeats / a match is correct within this distance


def detect(logits: torch.Tensor, mask: torch.Tensor, config: ValidationConfig) -> torch.Tensor:
    """logits [1, 65, h, w], mask [H, W] -> top-k keypoints [K, 2] (x, y) where mask > 0."""
    heatmap = max_pool_nms(heatmap_from_logits(logits.float()), config.nms_radius)[0, 0]
    height, width = heatmap.shape
    heatmap = heatmap * border_mask(height, width, config.border, heatmap) * mask
    k = min(config.num_keypoints, int((heatmap > 0).sum()))
    values, indices = torch.topk(heatmap.reshape(-1), k)
    return torch.stack([indices % width, indices // width], dim=1).float()


def pair_metrics(
    keypoints_a: torch.Tensor,
    keypoints_b: torch.Tensor,
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    homography: torch.Tensor,
    size: tuple[int, int],
    distance_px: float,
) -> tuple[float, int, float, int]:
    """Repeatability and nearest-neighbour accuracy of one pair.

    Args:
        keypoints_a [Na, 2], keypoints_b [Nb, 2]; descriptors_a [Na, D], descriptors_b [Nb, D];
        homography [3, 3] a -> b.
    Returns:
        (repeated count, visible count, correct NN count, matchable count): repeatability is
        repeated / visible over the keypoints of both images that the other view sees; NN accuracy is
        correct / matchable over the keypoints of a that have a true correspondent in b.
    """
    if keypoints_a.shape[0] == 0 or keypoints_b.shape[0] == 0:
        return 0.0, 0, 0.0, 0
    a_in_b = warp_points(keypoints_a, homography)
    b_in_a = warp_points(keypoints_b, torch.linalg.inv(homography.double()).float())
    visible_a = points_inside(a_in_b, size)
    visible_b = points_inside(b_in_a, size)
    distance = torch.cdist(a_in_b, keypoints_b)  # [Na, Nb]
    repeated_a = (distance.min(dim=1).values <= distance_px) & visible_a
    repeated_b = (distance.min(dim=0).values <= distance_px) & visible_b
    visible = int(visible_a.sum() + visible_b.sum())
    repeated = float(repeated_a.sum() + repeated_b.sum())
    nearest = (descriptors_a @ descriptors_b.T).argmax(dim=1)
    correct = distance.gather(1, nearest[:, None])[:, 0] <= distance_px
    return repeated, visible, float((correct & repeated_a).sum()), int(repeated_a.sum())


@torch.no_grad()
def validate(
    model: nn.Module,
    loader: torch.utils.data.DataLoader,
    device: torch.device,
    loss_config: LossConfig,
    config: ValidationConfig | None = None,
) -> dict[str, float]:
    """Mean validation loss, repeatability and NN accuracy over a loader of `WarpedPairs` batches."""
    config = config or ValidationConfig()
    was_training = model.training
    model.eval()
    totals = {"repeated": 0.0, "visible": 0, "correct": 0.0, "matchable": 0, "loss": 0.0, "batches": 0}
    generator = torch.Generator().manual_seed(0)
    for batch in loader:
        batch = {key: value.to(device) for key, value in batch.items()}
        outputs_a, outputs_b = model(batch["image_a"]), model(batch["image_b"])
        totals["loss"] += float(superpoint_loss(outputs_a, outputs_b, batch, loss_config, generator)["loss"])
        totals["batches"] += 1
        size = tuple(batch["image_a"].shape[-2:])
        masks_b = valid_mask(batch["homography"], size, erode=config.border)
        for i in range(batch["image_a"].shape[0]):
            ones = torch.ones(size, device=device)
            keypoints_a = detect(outputs_a["logits"][i : i + 1], ones, config)
            keypoints_b = detect(outputs_b["logits"][i : i + 1], masks_b[i, 0], config)
            descriptors_a = sample_descriptors(outputs_a["descriptors"][i].float(), keypoints_a)
            descriptors_b = sample_descriptors(outputs_b["descriptors"][i].float(), keypoints_b)
            repeated, visible, correct, matchable = pair_metrics(
                keypoints_a, keypoints_b, descriptors_a, descriptors_b, batch["homography"][i], size, config.distance_px
            )
            totals["repeated"] += repeated
            totals["visible"] += visible
            totals["correct"] += correct
            totals["matchable"] += matchable
    model.train(was_training)
    return {
        "val_loss": totals["loss"] / max(totals["batches"], 1),
        "repeatability": totals["repeated"] / max(totals["visible"], 1),
        "nn_accuracy": totals["correct"] / max(totals["matchable"], 1),
    }
