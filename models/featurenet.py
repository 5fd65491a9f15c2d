"""FeatureNet: the depthwise-separable, deformable SuperPoint-style detector/descriptor.

Layout (default widths, 240x320 input):

    stem 3x3 conv 1->16 (H)            | maxpool
    DS blocks at H/2, H/4, H/8         | maxpool between stages
    DeformableConv 3x3 at H/8          | offsets from a depthwise-separable branch
    context blocks at H/8 (optional)   | inverted residual: 1x1 expand, depthwise 3x3, 1x1 project, + x
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
from models.keypoints import parse_refinement, unit_rows

ACTIVATIONS = ("elu", "relu")
CELL = 8


class ELU(nn.ELU):
    """ELU (alpha 1) that traces either as the ONNX Elu op (``form = "native"``, which TensorRT fuses) or,
    for onnxruntime, as max(x, exp(min(x, 0)) - 1) (``form = "max_exp"``).

    onnxruntime neither fuses Elu into the Conv before it nor runs it fast, and it reorders the NCHWc
    layout around it; as Min, Exp, Sub and Max the same values cost half (0.8 against 1.6 ms at
    32x120x160, one thread). Exact: e^x - 1 >= x for every x, with equality at 0.
    """

    form = "native"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.form == "max_exp":
            return torch.maximum(x, torch.exp(torch.clamp(x, max=0.0)) - 1.0)
        return super().forward(x)


def set_elu_form(model: nn.Module, form: str) -> nn.Module:
    """Set how every `ELU` in ``model`` traces: ``native`` or ``max_exp`` (see `ELU`); returns ``model``."""
    if form not in ("native", "max_exp"):
        raise ValueError(f"unknown ELU form {form!r}")
    for module in model.modules():
        if isinstance(module, ELU):
            module.form = form
    return model


def make_activation(name: str) -> nn.Module:
    """``elu`` (the paper's choice) or ``relu`` (fuses into Conv in onnxruntime and quantises to INT8)."""
    if name == "elu":
        return ELU(inplace=True)
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


MAX_CHANNELS = 4096  # per layer: 16x the shipped model's widest; beyond it only memory runs out
MAX_BLOCKS = 64
MAX_PIXEL_MARGIN = 4  # half a cell: beyond it the window is mostly the neighbours' pixels


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
    deform_fraction: float = 1.0  # depthwise only: share of channels sampled at the offsets (the rest: plain 3x3)
    pixel_head_channels: int = 64  # width of the cell-pixel keypoint head; 0 = no such head
    # Pixels the cell-pixel head sees beyond its own cell on each side: 0 = the cell's 8x8 pixels only, so a
    # corner on a cell's border is half outside its view; m = an (8 + 2m)^2 window (`WindowPixelHead`).
    pixel_head_margin: int = 0
    context_blocks: int = 0  # inverted residual blocks at H/8, after the deformable conv, before the heads
    context_channels: int = 256  # their expanded width
    # How the heatmap is read to sub-pixel positions (`models.keypoints.parse_refinement`): the one these
    # weights were trained for, which export and evaluation use unless told otherwise.
    refinement: str = "centroid"
    # 1: the stem conv runs at H and a max-pool halves it (every model trained before this field); 2: the stem
    # conv itself has stride 2, so nothing runs at full resolution (a full-resolution conv and max-pool were a
    # fifth of the 480x752 graph's time in onnxruntime). Needs blocks[0] == 0.
    stem_stride: int = 1

    def __post_init__(self) -> None:
        if len(self.widths) != 4 or len(self.blocks) != 4:
            raise ValueError("widths and blocks need one entry per scale: H, H/2, H/4, H/8")
        if any(int(w) < 1 for w in self.widths) or any(int(b) < 0 for b in self.blocks):
            raise ValueError("widths must be >= 1 and blocks >= 0")
        # Bounded before any layer exists: a width of 10^6 asks for terabytes of weights at construction.
        channels = {"widths": max(int(w) for w in self.widths), "head_channels": int(self.head_channels),
                    "descriptor_dim": int(self.descriptor_dim), "pixel_head_channels": int(self.pixel_head_channels),
                    "context_channels": int(self.context_channels)}
        too_wide = [f"{name} {value}" for name, value in channels.items() if value > MAX_CHANNELS]
        if too_wide or max(int(b) for b in self.blocks) > MAX_BLOCKS or int(self.context_blocks) > MAX_BLOCKS:
            raise ValueError(f"channels must be at most {MAX_CHANNELS} and blocks at most {MAX_BLOCKS} per stage "
                             f"(got {', '.join(too_wide) or 'more blocks'})")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if int(self.pixel_head_channels) < 0:
            raise ValueError("pixel_head_channels must be >= 0")
        if int(self.context_blocks) < 0 or int(self.context_channels) < 1:
            raise ValueError("context_blocks must be >= 0 and context_channels >= 1")
        self.context_blocks, self.context_channels = int(self.context_blocks), int(self.context_channels)
        self.pixel_head_channels = int(self.pixel_head_channels)
        if not 0 <= int(self.pixel_head_margin) <= MAX_PIXEL_MARGIN:
            raise ValueError(f"pixel_head_margin must be within [0, {MAX_PIXEL_MARGIN}]")
        self.pixel_head_margin = int(self.pixel_head_margin)
        parse_refinement(self.refinement)  # ValueError names the bad text
        if self.deform_scale not in (2, 3):
            raise ValueError("deform_scale must be 2 (H/4) or 3 (H/8)")
        if int(self.stem_stride) not in (1, 2) or (int(self.stem_stride) == 2 and int(self.blocks[0])):
            raise ValueError("stem_stride must be 1, or 2 with no blocks at full resolution (blocks[0] = 0)")
        self.stem_stride = int(self.stem_stride)
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


class InvertedResidualBlock(nn.Module):
    """x + BN(1x1(act(BN(dw3x3(act(BN(1x1(x)))))))): expand to ``hidden`` channels, depthwise 3x3, project
    back. [B, C, H, W] -> [B, C, H, W].

    The last BN's scale starts at zero, so a new block is the identity: blocks added to a trained network
    leave its outputs unchanged until training gives them a use (capacity grown without a restart).
    """

    def __init__(self, channels: int, hidden: int, activation: str) -> None:
        super().__init__()
        self.expand = nn.Conv2d(channels, hidden, 1, bias=False)
        self.expand_bn = nn.BatchNorm2d(hidden)
        self.depthwise = nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden, bias=False)
        self.depthwise_bn = nn.BatchNorm2d(hidden)
        self.project = nn.Conv2d(hidden, channels, 1, bias=False)
        self.project_bn = nn.BatchNorm2d(channels)
        self.activation = make_activation(activation)
        nn.init.zeros_(self.project_bn.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.activation(self.expand_bn(self.expand(x)))
        y = self.activation(self.depthwise_bn(self.depthwise(y)))
        return x + self.project_bn(self.project(y))


class CellContrast(nn.Module):
    """Each 8x8 cell's pixels as channels, zero mean and unit contrast per cell.

    image [B, 1, H, W] -> [B, 64, H/8, W/8], channel dy*8 + dx. One 8x8 stride-8 conv with a fixed kernel
    (I - 1/64: each output channel picks one pixel of the cell and subtracts the cell's mean) and a 1x1
    conv with weights 1/64 (the mean square) replace the 5-D Transpose that gathers a cell's pixels
    (0.57 against 0.91 ms for the whole cell-pixel head in onnxruntime, 240x320, one thread), same values
    to float rounding. Its convs hold fixed kernels on raw pixel differences and must stay float when a
    graph is quantised (`toolkit quantise` keeps every Conv under this module's scope float).
    """

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        count = CELL * CELL
        pick = torch.eye(count, dtype=image.dtype, device=image.device)
        centred = F.conv2d(image, (pick - 1.0 / count).reshape(count, 1, CELL, CELL), stride=CELL)
        mean_of_squares = torch.full((1, count, 1, 1), 1.0 / count, dtype=image.dtype, device=image.device)
        variance = F.conv2d(centred * centred, mean_of_squares)
        return centred / torch.sqrt(variance + 1e-4)


class CellPixelHead(nn.Module):
    """Keypoint logits from each 8x8 cell's own pixels. image [B, 1, H, W] -> [B, 65, H/8, W/8].

    The 64 pixels of a cell become 64 channels (order dy*8 + dx, as the detector's pixel_shuffle), are
    normalised to zero mean and unit contrast per cell (so dark and bright cells look alike), then pass
    through 1x1 convs. ``cells_by_conv`` gathers the cells with `CellContrast` (the inference graphs);
    training and pruning trace the Reshape/Transpose path, whose layers they know. Both export targets
    run either.
    """

    def __init__(self, channels: int, activation: str) -> None:
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(CELL * CELL, channels, 1, bias=False), nn.BatchNorm2d(channels), make_activation(activation),
            nn.Conv2d(channels, channels, 1, bias=False), nn.BatchNorm2d(channels), make_activation(activation),
            nn.Conv2d(channels, CELL * CELL + 1, 1),
        )
        self.cell_contrast = CellContrast()  # no parameters: the checkpoint format is unchanged
        # Starts silent: an untrained head leaves the detector's logits unchanged.
        nn.init.zeros_(self.layers[-1].weight)
        nn.init.zeros_(self.layers[-1].bias)

    def forward(self, image: torch.Tensor, cells_by_conv: bool = False) -> torch.Tensor:
        if cells_by_conv:
            return self.layers(self.cell_contrast(image))
        batch, _, height, width = image.shape
        h, w = height // CELL, width // CELL
        cells = image.reshape(batch, h, CELL, w, CELL).permute(0, 2, 4, 1, 3).reshape(batch, CELL * CELL, h, w)
        centred = cells - cells.mean(dim=1, keepdim=True)
        contrast = torch.sqrt((centred * centred).mean(dim=1, keepdim=True) + 1e-4)
        return self.layers(centred / contrast)


class WindowStatistics(nn.Module):
    """Mean and contrast of every stride-8 window of ``size`` pixels, without padding.

    image [B, 1, H + 2m, W + 2m] -> mean, contrast [B, 1, H/8, W/8]. Two single-channel convs with a box kernel, over
    the image and over its square: onnxruntime runs them 3x faster than one grouped conv over the two stacked
    (0.25 against 0.72 ms at 240x320 on one thread: the grouped conv has no blocked kernel and needs a Concat), and
    faster than two AveragePools of this size (8 % of the ReLU graph's time at margin 2). Fixed kernels on raw
    pixels: they stay float when a graph is quantised, as `CellContrast` does (a dark window's contrast is below
    one uint8 step of its mean).
    """

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = int(size)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image`` comes zero-padded and shifted by a constant per image (`WindowPixelHead`): the variance is
        E[x^2] - E[x]^2, which cancels badly in FP16 unless x is near 0."""
        box = torch.full((1, 1, self.size, self.size), 1.0 / (self.size * self.size), dtype=image.dtype,
                         device=image.device)
        mean = F.conv2d(image, box, stride=CELL)
        mean_square = F.conv2d(image * image, box, stride=CELL)
        return mean, torch.sqrt((mean_square - mean * mean).clamp_min(0.0) + 1e-4)


class WindowPixelHead(nn.Module):
    """`CellPixelHead` over a window that reaches ``margin`` pixels into the neighbouring cells.

    image [B, 1, H, W] -> [B, 65, H/8, W/8]. The window's (8 + 2m)^2 pixels are normalised to zero mean and unit
    contrast as in `CellPixelHead`, then mixed by the first 1x1 conv. Because the normalisation is a per-window
    shift and scale, that conv is applied to the raw pixels instead, as one (8 + 2m)^2 stride-8 conv W, and
    the normalisation afterwards: W(x - mean) / contrast = (W x - mean * sum(W)) / contrast, with the mean and
    the mean square from a stride-8 box kernel (zero padding at the image border, as the window's). So the
    head never gathers the window's pixels as channels: at margin 2 it costs the MACs of the 8x8 head's gather.
    Starting from an 8x8 head (`widen_pixel_window`), the margin weights are zero.
    """

    def __init__(self, channels: int, activation: str, margin: int) -> None:
        super().__init__()
        self.margin = int(margin)
        size = CELL + 2 * self.margin
        self.layers = nn.Sequential(
            # unpadded: forward pads the image first (zeros, as the window sees past the image border)
            nn.Conv2d(1, channels, size, stride=CELL, bias=False), nn.BatchNorm2d(channels),
            make_activation(activation),
            nn.Conv2d(channels, channels, 1, bias=False), nn.BatchNorm2d(channels), make_activation(activation),
            nn.Conv2d(channels, CELL * CELL + 1, 1),
        )
        nn.init.zeros_(self.layers[-1].weight)
        nn.init.zeros_(self.layers[-1].bias)
        self.window_statistics = WindowStatistics(size)  # no parameters: the checkpoint format is unchanged

    def forward(self, image: torch.Tensor, cells_by_conv: bool = False) -> torch.Tensor:
        """``cells_by_conv`` is `CellPixelHead`'s: this head has one path, every graph runs it."""
        window = self.layers[0]
        # Zero padding first, then a shift by the image's mean: the normalised response is the same in exact
        # arithmetic (mean and W x move together), but both subtractions below then cancel numbers near zero,
        # which keeps a dark or flat window's contrast in FP16 (TensorRT --fp16 may run any layer in half).
        padded = F.pad(image, (self.margin,) * 4)
        shifted = padded - image.mean(dim=(2, 3), keepdim=True)
        mean, contrast = self.window_statistics(shifted)
        weight_sums = window.weight.sum(dim=(1, 2, 3)).reshape(1, -1, 1, 1)
        raw = window(shifted)
        return self.layers[1:]((raw - mean * weight_sums) / contrast)


def widen_pixel_window(state: dict, model: nn.Module) -> dict:
    """``state`` of an 8x8 cell-pixel head made to fit ``model``'s `WindowPixelHead`: the first 1x1 conv over
    the cell's 64 pixel channels (order dy*8 + dx) becomes the window conv's inner 8x8 taps, the margin zero."""
    head = getattr(model, "pixel_head", None)
    key = "pixel_head.layers.0.weight"
    if not isinstance(head, WindowPixelHead) or key not in state or state[key].shape[1] != CELL * CELL:
        return state
    old = state[key]
    new = torch.zeros_like(head.layers[0].weight)
    m = head.margin
    new[:, 0, m : m + CELL, m : m + CELL] = old.reshape(old.shape[0], CELL, CELL).to(new.dtype)
    return {**state, key: new}


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
            nn.Conv2d(1, cfg.widths[0], 3, stride=cfg.stem_stride, padding=1, bias=False), nn.BatchNorm2d(cfg.widths[0]),
            make_activation(act),
        )
        stages: list[nn.Module] = []
        channels = cfg.widths[0]
        for scale, (width, count) in enumerate(zip(cfg.widths, cfg.blocks)):
            # A strided stem already halved the image: an Identity keeps the module indices (and so the
            # checkpoint keys) of the max-pool it replaces.
            downsample = nn.Identity() if scale == 1 and cfg.stem_stride == 2 else nn.MaxPool2d(2, 2)
            layers: list[nn.Module] = [downsample] if scale > 0 else []
            for _ in range(count):
                layers.append(DepthwiseSeparableBlock(channels, width, act))
                channels = width
            stages.append(nn.Sequential(*layers))
        self.stages = nn.ModuleList(stages)
        if cfg.deformable:
            deform_channels = _channels_after(cfg, cfg.deform_scale)
            self.deform = DeformableConv(deform_channels, deform_channels, modulated=cfg.modulated,
                                         depthwise=cfg.deform_depthwise, deform_fraction=cfg.deform_fraction)
            self.deform_bn = nn.BatchNorm2d(deform_channels)
            self.deform_act = make_activation(act)
        if cfg.context_blocks:
            self.context = nn.Sequential(
                *(InvertedResidualBlock(channels, cfg.context_channels, act) for _ in range(cfg.context_blocks))
            )
        self.detector = nn.Sequential(
            DepthwiseSeparableBlock(channels, cfg.head_channels, act), nn.Conv2d(cfg.head_channels, 65, 1)
        )
        self.descriptor = nn.Sequential(
            DepthwiseSeparableBlock(channels, cfg.head_channels, act),
            nn.Conv2d(cfg.head_channels, cfg.descriptor_dim, 1),
        )
        if cfg.pixel_head_channels:
            self.pixel_head = (CellPixelHead(cfg.pixel_head_channels, act) if not cfg.pixel_head_margin
                               else WindowPixelHead(cfg.pixel_head_channels, act, cfg.pixel_head_margin))

    def backbone(self, image: torch.Tensor) -> torch.Tensor:
        """image [B, 1, H, W] -> shared features [B, C, H/8, W/8].

        When no block runs at full resolution, the stem's activation runs after the first max-pool: a
        monotonic activation commutes with max, so the result is the same on a quarter of the pixels, and
        the stem conv can stay in float in an INT8 graph while the pool runs in onnxruntime's fast float
        layout (a float stem followed by a quantised ReLU made onnxruntime run an 8-bit NCHW MaxPool,
        3.8 ms of an 8 ms graph).
        """
        conv, norm, activation = self.stem
        x = norm(conv(image))
        deferred = not self.config.blocks[0]
        if not deferred:
            x = activation(x)
        for scale, stage in enumerate(self.stages):
            if deferred and scale == 1:
                x = stage[1:](activation(stage[0](x)))  # stage[0] is the max-pool (Identity after a strided stem)
            else:
                x = stage(x)
            if self.config.deformable and scale == self.config.deform_scale:
                x = self.deform_act(self.deform_bn(self.deform(x)))
        if self.config.context_blocks:
            x = self.context(x)
        return x

    def forward(self, image: torch.Tensor, for_keypoints: bool = False) -> dict[str, torch.Tensor]:
        """The heads; ``for_keypoints`` returns them as keypoint extraction needs them, cheaper.

        With ``for_keypoints``, "descriptors" is replaced by "descriptor_features" [B, C, h, w]: the
        descriptor head before its final 1x1 conv, which `models.keypoints.sample_descriptors` applies
        (`descriptor_projection`) after bilinear sampling, at the K keypoints only. Both steps are linear,
        so their order does not change the sampled vector; only the L2 normalisation moves from the four
        cell corners to the sampled point (identical at cell centres). This skips normalising the dense map
        and, when K is below the cell count, most of a 128 -> 256 conv; the cell-pixel head gathers its
        cells by conv. Used by the inference graphs and `toolkit eval`; training uses the dense heads.
        """
        features = self.backbone(image)
        logits = self.detector(features)
        if self.config.pixel_head_channels:
            logits = logits + self.pixel_head(image, cells_by_conv=for_keypoints)
        if for_keypoints:
            return {"logits": logits, "descriptor_features": self.descriptor[:-1](features)}
        return {"logits": logits, "descriptors": unit_rows(self.descriptor(features))}

    def descriptor_projection(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The descriptor head's final 1x1 conv as (weight [D, C], bias [D]), for `models.keypoints.keypoint_heads`."""
        conv = self.descriptor[-1]
        return conv.weight.reshape(conv.out_channels, conv.in_channels), conv.bias

