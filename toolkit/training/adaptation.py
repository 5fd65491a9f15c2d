"""Homographic adaptation (SuperPoint, DeTone et al. 2018, sec. 5): a teacher's score map averaged over
many random warps of the same image, then reduced to keypoints by NMS and top-k.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F

from models.keypoints import border_mask, max_pool_nms, refine_keypoints
from models.teachers import TEACHER_REFINEMENT
from toolkit.training.homographies import (
    HomographyConfig,
    pixel_grid,
    points_inside,
    sample_homographies,
    warp_images,
    warp_points,
)


@dataclass
class AdaptationConfig:
    """Everything that changes the labels; the label store records it and refuses to mix."""

    num_homographies: int = 100  # warps per image, the identity included
    size: tuple[int, int] = (240, 320)  # (height, width) images are labelled at
    homography: HomographyConfig = field(default_factory=HomographyConfig)
    mask_erosion: int = 3  # px: teacher responses on the black border of a warp are discarded
    nms_radius: int = 4
    border: int = 4  # px removed at the image edge
    threshold: float = 0.015  # minimum averaged score of a kept keypoint
    max_keypoints: int = 512
    seed: int = 0
    # Keep the teacher's dense descriptor map (pooled to 1/stride resolution) for descriptor distillation.
    # 0 = keypoints only. Only teachers with a `dense` method (the ALIKE family) provide one.
    descriptor_stride: int = 0
    # Keypoints at the teacher's own sub-pixel positions: a soft-argmax of its score map in the 5x5 window
    # around each peak (temperature 0.1, as ALIKE's keypoint detector), not the integer peak pixel.
    subpixel: bool = False

    def to_dict(self) -> dict:
        settings = asdict(self)
        settings["size"] = list(self.size)
        settings["homography"]["scale"] = list(self.homography.scale)
        for name in ("descriptor_stride", "subpixel"):  # stores written before these existed stay comparable
            if not settings[name]:
                del settings[name]
        return settings

    @staticmethod
    def from_dict(settings: dict) -> "AdaptationConfig":
        settings = dict(settings)
        homography = dict(settings.pop("homography"))
        homography["scale"] = tuple(homography["scale"])
        settings["size"] = tuple(settings["size"])
        return AdaptationConfig(homography=HomographyConfig(**homography), **settings)


@torch.no_grad()
def adapted_heatmap(
    teacher: torch.nn.Module,
    image: torch.Tensor,
    config: AdaptationConfig,
    generator: torch.Generator,
    chunk: int = 32,
) -> torch.Tensor:
    """Average the teacher's score over ``config.num_homographies`` warps of one image.

    Args:
        image: [1, 1, H, W] in [0, 1], on the device the teacher runs on.
        generator: CPU generator the random homographies are drawn from.
        chunk: warps per teacher call (batched on the GPU).
    Returns:
        [H, W] mean score over the warps that see each pixel.
    """
    height, width = image.shape[-2:]
    device = image.device
    identity = torch.eye(3).unsqueeze(0)
    randoms = sample_homographies(config.num_homographies - 1, height, width, config.homography, generator)
    homographies = torch.cat([identity, randoms]).to(device)
    total = torch.zeros(1, 1, height, width, device=device)
    count = torch.zeros(1, 1, height, width, device=device)
    grid = pixel_grid(height, width, device)
    for start in range(0, homographies.shape[0], chunk):
        batch = homographies[start : start + chunk]
        warped = warp_images(image.expand(batch.shape[0], -1, -1, -1), batch)
        scores = teacher(warped).float()
        unwarped = warp_images(scores, torch.linalg.inv(batch.double()).float())
        # A source pixel counts for a warp when it lands inside the warped frame, away from its black
        # border (teacher responses there are artefacts); the identity has no such border.
        landing = warp_points(grid, batch)
        seen = points_inside(landing, (height, width), border=config.mask_erosion)
        if start == 0:
            seen[0] = True
        seen = seen.float().reshape(-1, 1, height, width)
        total += (unwarped * seen).sum(0, keepdim=True)
        count += seen.sum(0, keepdim=True)
    return (total / count.clamp_min(1e-3))[0, 0]


def heatmap_to_keypoints(heatmap: torch.Tensor, config: AdaptationConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """NMS, border removal, threshold and top-k on an aggregated heatmap.

    Args:
        heatmap: [H, W].
    Returns:
        keypoints [N, 2] (x, y) float32 and scores [N], best first, N <= ``config.max_keypoints``.
    """
    height, width = heatmap.shape
    suppressed = max_pool_nms(heatmap[None, None], config.nms_radius)[0, 0]
    suppressed = suppressed * border_mask(height, width, config.border, suppressed)
    k = min(config.max_keypoints, height * width)
    values, indices = torch.topk(suppressed.reshape(-1), k)
    keep = values > config.threshold
    values, indices = values[keep], indices[keep]
    keypoints = torch.stack([indices % width, indices // width], dim=1).float()
    if config.subpixel:
        keypoints = refine_keypoints(heatmap[None, None].float(), keypoints, TEACHER_REFINEMENT)
    return keypoints, values


def label_image(
    teacher: torch.nn.Module, image: torch.Tensor, config: AdaptationConfig, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """[1, 1, H, W] image -> (keypoints [N, 2], scores [N]) on the CPU."""
    keypoints, scores = heatmap_to_keypoints(adapted_heatmap(teacher, image, config, generator), config)
    return keypoints.cpu(), scores.cpu()


@torch.no_grad()
def teacher_descriptor_map(teacher: torch.nn.Module, image: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The teacher's own (unwarped) score map and its descriptor map pooled to 1/stride resolution.

    Args:
        image: [1, 1, H, W] in [0, 1], H and W multiples of ``stride``.
    Returns:
        scores [H, W], descriptors [D, H/stride, W/stride] float16 on the CPU, unit L2 norm over D.
    """
    if not hasattr(teacher, "dense"):
        raise ValueError("this teacher has no dense descriptor map (use an ALIKE teacher: alike-t|s|n|l)")
    scores, descriptors = teacher.dense(image)
    pooled = F.normalize(F.avg_pool2d(descriptors.float(), stride), p=2.0, dim=1)
    return scores[0, 0].float(), pooled[0].half().cpu()


def label_image_with_descriptors(
    teacher: torch.nn.Module, image: torch.Tensor, config: AdaptationConfig, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`label_image` plus the teacher's descriptor map; one teacher pass when there is one homography."""
    scores, descriptors = teacher_descriptor_map(teacher, image, config.descriptor_stride)
    heatmap = scores if config.num_homographies == 1 else adapted_heatmap(teacher, image, config, generator)
    keypoints, values = heatmap_to_keypoints(heatmap, config)
    return keypoints.cpu(), values.cpu(), descriptors
