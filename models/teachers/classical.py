"""Shi-Tomasi corner score (the classical teacher GCNv2 used), as a dependency-free fallback teacher."""
from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import nn


class ShiTomasiTeacher(nn.Module):
    """Minimum eigenvalue r of the structure tensor, squashed to [0, 1) as r / (r + q).

    The raw eigenvalue scales with the square of the image contrast, so q is the map's own
    ``quantile``-th response: flat regions stay near 0 and the strongest corners approach 1 in every
    image, without clipping (which would create ties between corners and confuse NMS).

    Args:
        block_size: side of the window the structure tensor is summed over (px).
        quantile: response quantile mapped to 0.5.
    """

    def __init__(self, block_size: int = 3, quantile: float = 0.99) -> None:
        super().__init__()
        self.block_size = block_size
        self.quantile = quantile

    def score(self, gray: np.ndarray) -> np.ndarray:
        """[H, W] float32 in [0, 1] -> [H, W] float32 score in [0, 1]."""
        response = cv2.cornerMinEigenVal(gray, self.block_size, ksize=3)
        response = np.maximum(response, 0.0)
        scale = max(float(np.quantile(response, self.quantile)), 1e-6)
        return (response / (response + scale)).astype(np.float32)

    @torch.no_grad()
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image [B, 1, H, W] in [0, 1] -> score map [B, 1, H, W] in [0, 1] (computed on the CPU)."""
        gray = image[:, 0].detach().float().cpu().numpy()
        scores = np.stack([self.score(np.ascontiguousarray(g)) for g in gray])
        return torch.from_numpy(scores)[:, None].to(image.device)
