"""ALIKED (Zhao et al., IEEE TIM 2023) re-implemented from the paper and the published state-dict layout.

Same four-scale encoder as ALIKE (scales 1, 1/2, 1/8, 1/32; here with average pooling and SELU gates),
but the two 3x3 convs of ``block3`` and ``block4`` are deformable: each has an ``offset_conv`` (3x3 with
bias, 2*9 channels = one (dy, dx) per tap, no modulation mask) and a ``regular_conv`` kernel without bias.
Offsets are clamped to a quarter of the feature map size, as the paper bounds the deformation.
The score head is conv1x1(dim->8)-act-conv3x3(8->4)-act-conv3x3(4->4)-act-conv3x3(4->1)-sigmoid on the
concatenated multi-scale features. The sparse deformable descriptor head (SDDH: ``desc_head``) only
describes given keypoints; its tensors are declared so the weights load strictly, but the teacher never
runs it (the student learns its own descriptors).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from models.deform import deform_conv2d
from models.torch_files import load_weights_only
from models.teachers.alike import ConvBlock, ResidualBlock, gray_to_rgb, pad_to_multiple, upsample_to


@dataclass(frozen=True)
class AlikedConfig:
    c1: int
    c2: int
    c3: int
    c4: int
    dim: int
    sample_points: int  # M, the number of deformable sample positions of SDDH ("16" in the name)


ALIKED_CONFIGS: dict[str, AlikedConfig] = {
    "aliked-t16": AlikedConfig(8, 16, 32, 64, 64, 16),
    "aliked-n16": AlikedConfig(16, 32, 64, 128, 128, 16),
}


class OffsetDeformConv(nn.Module):
    """3x3 deformable conv (DCN v1): offsets from a plain 3x3 conv on the same input."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.offset_conv = nn.Conv2d(in_channels, 2 * 9, 3, padding=1, bias=True)
        self.regular_conv = nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        limit = max(x.shape[-2:]) / 4.0
        offset = self.offset_conv(x).clamp(-limit, limit)
        return deform_conv2d(x, offset, self.regular_conv.weight, None, None, 1, 1, 1)


class SparseDeformableDescriptorHead(nn.Module):
    """SDDH parameters (offsets for M sample points per keypoint, per-point aggregation weights)."""

    def __init__(self, dim: int, sample_points: int) -> None:
        super().__init__()
        self.offset_conv = nn.Sequential(
            nn.Conv2d(dim, 2 * sample_points, 3, padding=1, bias=True),
            nn.SELU(inplace=True),
            nn.Conv2d(2 * sample_points, 2 * sample_points, 1, bias=True),
        )
        self.sf_conv = nn.Conv2d(dim, dim, 1, bias=False)
        self.agg_weights = nn.Parameter(torch.zeros(sample_points, dim, dim))


class Aliked(nn.Module):
    """ALIKED network; ``forward`` returns the dense keypoint score map [B, 1, H, W] in [0, 1]."""

    def __init__(self, config: AlikedConfig) -> None:
        super().__init__()
        self.config = config
        act = nn.SELU(inplace=True)
        self.block1 = ConvBlock(3, config.c1, act)
        self.block2 = ResidualBlock(config.c1, config.c2, act)
        self.block3 = ResidualBlock(
            config.c2, config.c3, act, OffsetDeformConv(config.c2, config.c3), OffsetDeformConv(config.c3, config.c3)
        )
        self.block4 = ResidualBlock(
            config.c3, config.c4, act, OffsetDeformConv(config.c3, config.c4), OffsetDeformConv(config.c4, config.c4)
        )
        quarter = config.dim // 4
        self.conv1 = nn.Conv2d(config.c1, quarter, 1, bias=False)
        self.conv2 = nn.Conv2d(config.c2, quarter, 1, bias=False)
        self.conv3 = nn.Conv2d(config.c3, quarter, 1, bias=False)
        self.conv4 = nn.Conv2d(config.c4, quarter, 1, bias=False)
        self.score_head = nn.Sequential(
            nn.Conv2d(config.dim, 8, 1, bias=False),
            act,
            nn.Conv2d(8, 4, 3, padding=1, bias=False),
            act,
            nn.Conv2d(4, 4, 3, padding=1, bias=False),
            act,
            nn.Conv2d(4, 1, 3, padding=1, bias=False),
        )
        self.desc_head = SparseDeformableDescriptorHead(config.dim, config.sample_points)
        self.act = act

    def dense_features(self, image: torch.Tensor) -> torch.Tensor:
        """RGB [B, 3, H, W] (multiples of 32) -> concatenated multi-scale features [B, dim, H, W]."""
        x1 = self.block1(image)
        x2 = self.block2(F.avg_pool2d(x1, 2))
        x3 = self.block3(F.avg_pool2d(x2, 4))
        x4 = self.block4(F.avg_pool2d(x3, 4))
        size = image.shape[-2:]
        return torch.cat(
            [
                self.act(self.conv1(x1)),
                upsample_to(self.act(self.conv2(x2)), size),
                upsample_to(self.act(self.conv3(x3)), size),
                upsample_to(self.act(self.conv4(x4)), size),
            ],
            dim=1,
        )

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image [B, 1 or 3, H, W] in [0, 1] -> score map [B, 1, H, W] in [0, 1]."""
        padded, height, width = pad_to_multiple(gray_to_rgb(image), 32)
        scores = torch.sigmoid(self.score_head(self.dense_features(padded)))
        return scores[:, :, :height, :width]


def load_aliked(name: str, weights_dir: Path) -> Aliked:
    """Build ``name`` (aliked-t16|n16) and load ``weights_dir/<name>.pth`` strictly (every key must match)."""
    model = Aliked(ALIKED_CONFIGS[name])
    state = load_weights_only(Path(weights_dir) / f"{name}.pth")
    model.load_state_dict(state, strict=True)
    return model.eval()
