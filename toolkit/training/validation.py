"""Validation on held-back warped pairs: repeatability, localisation error, NN mAP and matching score."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from models.keypoints import (Refinement, border_mask, heatmap_from_logits, keypoint_scores, max_pool_nms,
                              model_refinement, refine_keypoints, sample_descriptors)
from toolkit.training.homographies import valid_mask


@dataclass
class ValidationConfig:
    num_keypoints: int = 300  # per image, top-k after NMS
    nms_radius: int = 4
    score_window: int = 1  # `keypoint_scores` window, as `toolkit eval --score-window` ranks points
    border: int = 4
    distance_px: float = 3.0  # a keypoint repeats / a match is correct within this distance


def detect(logits: torch.Tensor, mask: torch.Tensor, config: ValidationConfig,
           refinement: Refinement | None = None) -> torch.Tensor:
    """logits [1, 65, h, w], mask [H, W] -> top-k keypoints [K, 2] (x, y) where mask > 0, refined to sub-pixel
    positions by ``refinement`` as the exported graph does (None: the integer peaks)."""
    probability = heatmap_from_logits(logits.float())
    scores = keypoint_scores(probability, config.score_window)
    heatmap = max_pool_nms(scores, config.nms_radius)[0, 0]
    height, width = heatmap.shape
    heatmap = heatmap * border_mask(height, width, config.border, heatmap) * mask
    k = min(config.num_keypoints, int((heatmap > 0).sum()))
    values, indices = torch.topk(heatmap.reshape(-1), k)
    peaks = torch.stack([indices % width, indices // width], dim=1).float()
    return peaks if refinement is None else refine_keypoints(probability, peaks, refinement)


@torch.no_grad()
def validate(
    model: nn.Module,
    loader: torch.utils.data.DataLoader,
    device: torch.device,
    loss_fn: Callable[[dict, dict, dict], dict],
    config: ValidationConfig | None = None,
) -> dict[str, float]:
    """Held-back warped pairs -> mean loss and the evaluation's own metrics (`toolkit.evaluation.metrics`).

    Returns val_loss, repeatability, localisation_error (px, repeated keypoints), nn_map and
    matching_score (mutual nearest neighbours, correct within ``distance_px``), averaged over pairs.
    ``matching_score`` is what picks the best checkpoint: it needs both good points and good descriptors.
    """
    from toolkit.evaluation.metrics import (
        descriptor_distances,
        matching_score,
        mutual_nearest_neighbours,
        nearest_neighbour_map,
        repeatability_and_localisation,
    )

    config = config or ValidationConfig()
    refinement = model_refinement(model)
    was_training = model.training
    model.eval()
    sums = {"repeatability": 0.0, "localisation_error": 0.0, "nn_map": 0.0, "matching_score": 0.0}
    pairs = localised = 0
    loss, batches = 0.0, 0
    for batch in loader:
        batch = {key: value.to(device) for key, value in batch.items()}
        outputs_a, outputs_b = model(batch["image_a"]), model(batch["image_b"])
        loss += float(loss_fn(outputs_a, outputs_b, batch)["loss"])
        batches += 1
        size = tuple(batch["image_a"].shape[-2:])
        masks_b = valid_mask(batch["homography"], size, erode=config.border)
        for i in range(batch["image_a"].shape[0]):
            ones = torch.ones(size, device=device)
            keypoints_a = detect(outputs_a["logits"][i : i + 1], ones, config, refinement)
            keypoints_b = detect(outputs_b["logits"][i : i + 1], masks_b[i, 0], config, refinement)
            descriptors_a = sample_descriptors(outputs_a["descriptors"][i].float(), keypoints_a).cpu().numpy()
            descriptors_b = sample_descriptors(outputs_b["descriptors"][i].float(), keypoints_b).cpu().numpy()
            points_a, points_b = keypoints_a.cpu().numpy(), keypoints_b.cpu().numpy()
            homography = batch["homography"][i].double().cpu().numpy()
            repeatability, error = repeatability_and_localisation(points_a, points_b, homography, size, size, config.distance_px)
            matches = mutual_nearest_neighbours(descriptor_distances(descriptors_a, descriptors_b))
            sums["repeatability"] += repeatability
            if error == error:  # NaN when nothing repeats
                sums["localisation_error"] += error
                localised += 1
            sums["nn_map"] += nearest_neighbour_map(points_a, descriptors_a, points_b, descriptors_b, homography, size, size, config.distance_px)
            sums["matching_score"] += matching_score(points_a, points_b, matches, homography, size, size, config.distance_px)
            pairs += 1
    model.train(was_training)
    metrics = {key: value / max(pairs, 1) for key, value in sums.items()}
    metrics["localisation_error"] = sums["localisation_error"] / localised if localised else float("nan")
    return {"val_loss": loss / max(batches, 1), **metrics}
