"""FeatureNet: the depthwise-separable, deformable SuperPoint-style detector/descriptor.

Layout (default widths, 240x320 input):

    stem 3x3 conv 1->16 (H)            | maxpool
    DS blocks at H/2, H/4, H/8         | maxpool between stages
    DeformableConv 3x3 at H/8          | offsets from a depthwise-separable branch
    detector head   DS block -> 1x1 -> 65 logits per 8x8 cell (64 pixels + dustbin)
                    + cell-pixel head: the cell's own 64 pixels, contrast-normalised, through 1x1 convs
    descriptor head DS block -> 1x1 -> 256-d, L2-normalised

The deformable conv sits at H/8: there it costs 1/64 of a full-resolution layer and sees the widest
context, which is where geometric flexibility helps descriptors most.

The cell-pixel head exists because three max-pools blur where inside its cell a corner lies: the
H/8 features say *whether* a cell holds a keypoint, the cell's raw pixels say *where* (XFeat's keypoint
branch makes the same observation). Its logits are added to the detector's; ~15 MMACs at 240x320.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from models.deform import DeformableConv
from models.keypoints import unit_rows

ACTIVATIONS = ("elu", "relu")
CELL = 8


def make_activation(name: str) -> nn.Module:
    """``elu`` (the paper's choice) or ``relu`` (fuses into Conv in onnxruntime and quantises to INT8)."""
    if name == "elu":
        return nn.ELU(inplace=True)
    if name == "relu":
        return nn.ReLU(inplace=True)
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


class DepthwiseSeparableBlock(nn.Module):
    """Depthwise 3x3 + BN + ReLU, then pointwise 1x1 + BN + activation. [B, Cin, H, W] -> [B, Cout, H, W]."""

    def __init__(self, in_channels: int, out_channels: int, activation: str) -> None:
        super().__init__()
        self.depthwise = nn.Conv2d(in_channels, in_channels, 3, padding=1, groups=in_channels, bias=False)
        self.depthwise_bn = nn.BatchNorm2d(in_channels)
        self.pointwise = nn.Conv2d(in_channels, out_channels, 1, bias=False)
        self.pointwise_bn = nn.BatchNorm2d(out_channels)
        self.activation = make_activation(activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.depthwise_bn(self.depthwise(x)), inplace=True)
        return self.activation(self.pointwise_bn(self.pointwise(x)))


@dataclass
class FeatureNetConfig:
    """Widths per scale (H, H/2, H/4, H/8), DS blocks per scale, heads and activation."""

    widths: list[int] = field(default_factory=lambda: [16, 32, 64, 128])
    blocks: list[int] = field(default_factory=lambda: [0, 1, 2, 2])
    head_channels: int = 128
    descriptor_dim: int = 256
    activation: str = "elu"
    deformable: bool = True
    modulated: bool = True
    deform_scale: int = 3  # index into widths: 3 = after the H/8 stage, 2 = after the H/4 stage
    deform_depthwise: bool = False  # depthwise deformable 3x3 + pointwise 1x1 instead of a dense deformable 3x3
    pixel_head_channels: int = 64  # width of the cell-pixel keypoint head; 0 = no such head

    def __post_init__(self) -> None:
        if len(self.widths) != 4 or len(self.blocks) != 4:
            raise ValueError("widths and blocks need one entry per scale: H, H/2, H/4, H/8")
        if any(int(w) < 1 for w in self.widths) or any(int(b) < 0 for b in self.blocks):
            raise ValueError("widths must be >= 1 and blocks >= 0")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if int(self.pixel_head_channels) < 0:
            raise ValueError("pixel_head_channels must be >= 0")
        self.pixel_head_channels = int(self.pixel_head_channels)
        if self.deform_scale not in (2, 3):
            raise ValueError("deform_scale must be 2 (H/4) or 3 (H/8)")
        self.widths = [int(w) for w in self.widths]
        self.blocks = [int(b) for b in self.blocks]

    def to_dict(self) -> dict:
        return asdict(self)


def _channels_after(cfg: FeatureNetConfig, scale: int) -> int:
    """Channels leaving stage ``scale``: the last stage up to it that has blocks sets them."""
    channels = cfg.widths[0]
    for index in range(scale + 1):
        if cfg.blocks[index]:
            channels = cfg.widths[index]
    return channels


class CellPixelHead(nn.Module):
    """Keypoint logits from each 8x8 cell's own pixels. image [B, 1, H, W] -> [B, 65, H/8, W/8].

    The 64 pixels of a cell become 64 channels (order dy*8 + dx, as the detector's pixel_shuffle), are
    normalised to zero mean and unit contrast per cell (so dark and bright cells look alike), then pass
    through 1x1 convs. Reshape/Transpose only: both export targets run it.
    """

    def __init__(self, channels: int, activation: str) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(CELL * CELL, channels, 1, bias=False), nn.BatchNorm2d(channels), make_activation(activation),
            nn.Conv2d(channels, channels, 1, bias=False), nn.BatchNorm2d(channels), make_activation(activation),
            nn.Conv2d(channels, CELL * CELL + 1, 1),
        )
        # Starts silent: an untrained head leaves the detector's logits unchanged.
        nn.init.zeros_(self.layers[-1].weight)
        nn.init.zeros_(self.layers[-1].bias)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        batch, _, height, width = image.shape
        h, w = height // CELL, width // CELL
        cells = image.reshape(batch, h, CELL, w, CELL).permute(0, 2, 4, 1, 3).reshape(batch, CELL * CELL, h, w)
        centred = cells - cells.mean(dim=1, keepdim=True)
        contrast = torch.sqrt((centred * centred).mean(dim=1, keepdim=True) + 1e-4)
        return self.layers(centred / contrast)


class FeatureNet(nn.Module):
    """Depthwise-separable SuperPoint-style network with one deformable conv at H/8.

    forward(image [B, 1, H, W] gray in [0, 1], H and W divisible by 8) ->
        {"logits": [B, 65, H/8, W/8], "descriptors": [B, D, H/8, W/8] (unit L2 norm over D)}
    """

    arch = "featurenet"

    def __init__(self, config: FeatureNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or FeatureNetConfig()
        cfg = self.config
        act = cfg.activation
        self.stem = nn.Sequential(
            nn.Conv2d(1, cfg.widths[0], 3, padding=1, bias=False), nn.BatchNorm2d(cfg.widths[0]), make_activation(act)
        )
        stages: list[nn.Module] = []
        channels = cfg.widths[0]
        for scale, (width, count) in enumerate(zip(cfg.widths, cfg.blocks)):
            layers: list[nn.Module] = [nn.MaxPool2d(2, 2)] if scale > 0 else []
            for _ in range(count):
                layers.append(DepthwiseSeparableBlock(channels, width, act))
                channels = width
            stages.append(nn.Sequential(*layers))
        self.stages = nn.ModuleList(stages)
        if cfg.deformable:
            deform_channels = _channels_after(cfg, cfg.deform_scale)
            self.deform = DeformableConv(deform_channels, deform_channels, modulated=cfg.modulated,
                                         depthwise=cfg.deform_depthwise)
            self.deform_bn = nn.BatchNorm2d(deform_channels)
            self.deform_act = make_activation(act)
        self.detector = nn.Sequential(
            DepthwiseSeparableBlock(channels, cfg.head_channels, act), nn.Conv2d(cfg.head_channels, 65, 1)
        )
        self.descriptor = nn.Sequential(
            DepthwiseSeparableBlock(channels, cfg.head_channels, act),
            nn.Conv2d(cfg.head_channels, cfg.descriptor_dim, 1),
        )
        if cfg.pixel_head_channels:
            self.pixel_head = CellPixelHead(cfg.pixel_head_channels, act)

    def backbone(self, image: torch.Tensor) -> torch.Tensor:
        """image [B, 1, H, W] -> shared features [B, C, H/8, W/8]."""
        x = self.stem(image)
        for scale, stage in enumerate(self.stages):
            x = stage(x)
            if self.config.deformable and scale == self.config.deform_scale:
                x = self.deform_act(self.deform_bn(self.deform(x)))
        return x

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        features = self.backbone(image)
        descriptors = unit_rows(self.descriptor(features))
        logits = self.detector(features)
        if self.config.pixel_head_channels:
            logits = logits + self.pixel_head(image)
        return {"logits": logits, "descriptors": descriptors}
