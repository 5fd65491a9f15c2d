"""SuperPoint as a teacher: a user's Magic Leap ``superpoint_v1.pth`` through the lead's loader."""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from models.keypoints import heatmap_from_logits
from models.superpoint import SuperPointNet, load_superpoint_v1


class SuperPointTeacher(nn.Module):
    """image [B, 1, H, W] in [0, 1] -> full-resolution keypoint probability [B, 1, H, W].

    SuperPoint needs sides divisible by 8: other sizes are padded (replicated edge) and cropped back.
    """

    def __init__(self, network: SuperPointNet) -> None:
        super().__init__()
        self.network = network.eval()

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        height, width = image.shape[-2:]
        pad_h, pad_w = (-height) % 8, (-width) % 8
        if pad_h or pad_w:
            image = torch.nn.functional.pad(image, (0, pad_w, 0, pad_h), mode="replicate")
        heatmap = heatmap_from_logits(self.network(image)["logits"])
        return heatmap[:, :, :height, :width]


def load_superpoint_teacher(path: str | Path) -> SuperPointTeacher:
    """Raises ``ValueError``/``OSError`` for a file that is not a superpoint_v1 state dict."""
    return SuperPointTeacher(load_superpoint_v1(path))
