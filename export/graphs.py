"""The modules that are traced into ONNX: the network plus its fixed-shape post-processing."""
from __future__ import annotations

import torch
from torch import nn

from models.keypoints import Refinement, border_mask, extract_keypoints, heatmap_from_logits, keypoint_heads

KEYPOINT_OUTPUTS = ("keypoints", "scores", "descriptors", "num_valid")
DENSE_OUTPUTS = ("heatmap", "descriptors_coarse")


class KeypointGraph(nn.Module):
    """image [1, 1, H, W] -> keypoints [K, 2], scores [K], descriptors [K, D], num_valid [1] (int32).

    NMS, border removal, top-K and descriptor sampling all run inside the graph, with K fixed.
    """

    def __init__(
        self, net: nn.Module, height: int, width: int, max_keypoints: int, nms_radius: int, threshold: float, border: int,
        score_window: int = 1, refinement: Refinement = Refinement(),
    ) -> None:
        super().__init__()
        self.refinement = refinement
        self.net = net
        self.max_keypoints = int(max_keypoints)
        self.nms_radius = int(nms_radius)
        self.threshold = float(threshold)
        self.border = int(border)
        self.score_window = int(score_window)
        # A stored constant: TensorRT 8.0 cannot parse the ScatterND a traced slice assignment becomes.
        self.register_buffer("border_weights", border_mask(height, width, border, torch.zeros(1)), persistent=False)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        logits, descriptors, projection = keypoint_heads(self.net, image)
        out = extract_keypoints(
            logits, descriptors, self.max_keypoints, self.nms_radius, self.threshold, self.border,
            self.border_weights, projection=projection, score_window=self.score_window,
            refinement=self.refinement,
        )
        return tuple(out[name] for name in KEYPOINT_OUTPUTS)


class DenseGraph(nn.Module):
    """image [1, 1, H, W] -> heatmap [1, 1, H, W] (keypoint probability), descriptors_coarse [1, D, H/8, W/8]."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        heads = self.net(image)
        return heatmap_from_logits(heads["logits"]), heads["descriptors"]
