"""ALIKE (Zhao et al., IEEE TMM 2022) re-implemented from the paper and the published state-dict layout.

Architecture, read off the key names and shapes of the released weights:

- ``block1``: conv3x3 -> BN -> act -> conv3x3 -> BN -> act on the RGB image (c1 channels, full resolution);
- ``block2..4``: residual blocks (conv3x3-BN-act-conv3x3-BN, plus a 1x1 ``downsample`` projection with
  bias on the shortcut, then act), each after a max-pool: 2x before block2, 4x before block3 and block4,
  so the four scales are 1, 1/2, 1/8 and 1/32;
- ``conv1..4``: 1x1 convs (no bias) bringing every scale to dim/4 channels, act, bilinear upsampling
  (align_corners) back to full resolution, concatenation to ``dim`` channels;
- ``convhead1`` (only in alike-l): 1x1 dim->dim + act; ``convhead2``: 1x1 dim -> dim+1, whose last channel
  through a sigmoid is the dense score map and the others the descriptor map.

The paper's network uses ReLU gates; the teacher only needs the score map.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from models.torch_files import load_weights_only


@dataclass(frozen=True)
class AlikeConfig:
    c1: int
    c2: int
    c3: int
    c4: int
    dim: int
    extra_head: bool  # convhead1 present (alike-l)


ALIKE_CONFIGS: dict[str, AlikeConfig] = {
    "alike-t": AlikeConfig(8, 16, 32, 64, 64, False),
    "alike-s": AlikeConfig(8, 16, 48, 96, 96, False),
    "alike-n": AlikeConfig(16, 32, 64, 128, 128, False),
    "alike-l": AlikeConfig(32, 64, 128, 128, 128, True),
}


class ConvBlock(nn.Module):
    """conv3x3-BN-act twice (no shortcut)."""

    def __init__(self, in_channels: int, out_channels: int, act: nn.Module) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.act = act

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn2(self.conv2(self.act(self.bn1(self.conv1(x))))))


class ResidualBlock(nn.Module):
    """Basic residual block with a 1x1 projection shortcut; ``conv1``/``conv2`` may be deformable."""

    def __init__(
        self, in_channels: int, out_channels: int, act: nn.Module, conv1: nn.Module | None = None,
        conv2: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.conv1 = conv1 or nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = conv2 or nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample = nn.Conv2d(in_channels, out_channels, 1)
        self.act = act

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.act(y + self.downsample(x))


def pad_to_multiple(image: torch.Tensor, multiple: int) -> tuple[torch.Tensor, int, int]:
    """[B, C, H, W] -> (padded [B, C, H', W'], H, W) with H', W' multiples of ``multiple`` (replicated edge)."""
    height, width = image.shape[-2:]
    pad_h, pad_w = (-height) % multiple, (-width) % multiple
    if pad_h or pad_w:
        image = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate")
    return image, height, width


def gray_to_rgb(image: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] -> [B, 3, H, W]; the ALIKE family was trained on RGB in [0, 1]."""
    return image.expand(-1, 3, -1, -1) if image.shape[1] == 1 else image


def upsample_to(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=True)


class Alike(nn.Module):
    """ALIKE network; ``forward`` returns the dense keypoint score map [B, 1, H, W] in [0, 1]."""

    def __init__(self, config: AlikeConfig) -> None:
        super().__init__()
        self.config = config
        act = nn.ReLU(inplace=True)
        self.block1 = ConvBlock(3, config.c1, act)
        self.block2 = ResidualBlock(config.c1, config.c2, act)
        self.block3 = ResidualBlock(config.c2, config.c3, act)
        self.block4 = ResidualBlock(config.c3, config.c4, act)
        quarter = config.dim // 4
        self.conv1 = nn.Conv2d(config.c1, quarter, 1, bias=False)
        self.conv2 = nn.Conv2d(config.c2, quarter, 1, bias=False)
        self.conv3 = nn.Conv2d(config.c3, quarter, 1, bias=False)
        self.conv4 = nn.Conv2d(config.c4, quarter, 1, bias=False)
        if config.extra_head:
            self.convhead1 = nn.Conv2d(config.dim, config.dim, 1, bias=False)
        self.convhead2 = nn.Conv2d(config.dim, config.dim + 1, 1, bias=False)
        self.act = act

    def features(self, image: torch.Tensor) -> torch.Tensor:
        """RGB [B, 3, H, W] with H, W multiples of 32 -> head output [B, dim+1, H, W]."""
        x1 = self.block1(image)
        x2 = self.block2(F.max_pool2d(x1, 2))
        x3 = self.block3(F.max_pool2d(x2, 4))
        x4 = self.block4(F.max_pool2d(x3, 4))
        size = image.shape[-2:]
        merged = torch.cat(
            [
                self.act(self.conv1(x1)),
                upsample_to(self.act(self.conv2(x2)), size),
                upsample_to(self.act(self.conv3(x3)), size),
                upsample_to(self.act(self.conv4(x4)), size),
            ],
            dim=1,
        )
        if self.config.extra_head:
            merged = self.act(self.convhead1(merged))
        return self.convhead2(merged)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image [B, 1 or 3, H, W] in [0, 1] -> score map [B, 1, H, W] in [0, 1]."""
        padded, height, width = pad_to_multiple(gray_to_rgb(image), 32)
        return torch.sigmoid(self.features(padded)[:, -1:, :height, :width])

    def dense(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Score map and descriptor map from one pass (what descriptor distillation learns from).

        image [B, 1 or 3, H, W] in [0, 1] -> (scores [B, 1, H, W] in [0, 1],
        descriptors [B, dim, H, W] with unit L2 norm over dim).
        """
        padded, height, width = pad_to_multiple(gray_to_rgb(image), 32)
        head = self.features(padded)[:, :, :height, :width]
        return torch.sigmoid(head[:, -1:]), F.normalize(head[:, :-1], p=2.0, dim=1)


def load_alike(name: str, weights_dir: Path) -> Alike:
    """Build ``name`` (alike-t|s|n|l) and load ``weights_dir/<name>.pth`` strictly (every key must match)."""
    model = Alike(ALIKE_CONFIGS[name])
    state = load_weights_only(Path(weights_dir) / f"{name}.pth")
    model.load_state_dict(state, strict=True)
    return model.eval()
