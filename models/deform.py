"""Deformable 3x3 convolution (DCN v1/v2) in plain PyTorch, exportable two ways.

One sampler, ``deform_conv2d``, serves training (autograd) and the ``portable`` ONNX export: it uses only
Pad, Floor, Clip, Cast, Gather (non-negative indices), Mul/Add and MatMul, which TensorRT 8.0 parses at
opset 13. The ``native`` strategy emits the ONNX ``DeformConv`` op (opset 19) that onnxruntime >= 1.25
runs with its own kernel; its PyTorch side still runs ``deform_conv2d`` so tracing sees real values.

Sampling semantics (same as torchvision and ONNX DeformConv): tap k of output pixel (i, j) reads the
input at (i*s - p + ky*d + dy, j*s - p + kx*d + dx) by bilinear interpolation, where each of the four
corners that falls outside the image contributes zero.
"""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

DeformStrategy = Literal["torch", "native", "grid_sample"]


def is_depthwise(weight: torch.Tensor, channels: int) -> bool:
    """True for a depthwise kernel [C, 1, kh, kw] over C > 1 channels, False for a dense [Cout, C, kh, kw];
    any other grouping is refused."""
    if weight.shape[1] == channels:
        return False
    if weight.shape[1] == 1 and weight.shape[0] == channels:
        return True
    raise ValueError(f"deformable kernel {tuple(weight.shape)} is neither dense nor depthwise over {channels} channels")


def _output_size(size: int, kernel: int, stride: int, padding: int, dilation: int) -> int:
    return (size + 2 * padding - dilation * (kernel - 1) - 1) // stride + 1


def deform_conv2d(
    x: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    stride: int = 1,
    padding: int = 1,
    dilation: int = 1,
) -> torch.Tensor:
    """Deformable convolution by bilinear gathering (offset groups = 1; groups = 1, or C for depthwise).

    Args:
        x: input [B, C, H, W].
        offset: [B, 2*kh*kw, Ho, Wo], (dy, dx) per kernel tap in row-major tap order.
        weight: [Cout, C, kh, kw] (dense), or [C, 1, kh, kw] (depthwise: each channel its own kernel).
        bias: [Cout] or None.
        mask: modulation [B, kh*kw, Ho, Wo] or None (DCN v1).
    Returns:
        [B, Cout, Ho, Wo].
    """
    batch, channels, height, width = x.shape
    out_channels, _, kh, kw = weight.shape
    depthwise = is_depthwise(weight, channels)
    taps = kh * kw
    out_h = _output_size(height, kh, stride, padding, dilation)
    out_w = _output_size(width, kw, stride, padding, dilation)
    locations = out_h * out_w

    # Regular grid positions of every tap, [taps, Ho, Wo], plus the learned offsets. Positions and
    # indices stay at least float32 whatever the input dtype: half precision cannot hold integers above 2048.
    dtype, device = torch.promote_types(x.dtype, torch.float32), x.device
    offset = offset.to(dtype)
    mask = None if mask is None else mask.to(dtype)
    base_y = (torch.arange(out_h, dtype=dtype, device=device) * stride - padding).view(1, out_h, 1)
    base_x = (torch.arange(out_w, dtype=dtype, device=device) * stride - padding).view(1, 1, out_w)
    tap_y = (torch.arange(kh, dtype=dtype, device=device) * dilation).repeat_interleave(kw).view(taps, 1, 1)
    tap_x = (torch.arange(kw, dtype=dtype, device=device) * dilation).repeat(kh).view(taps, 1, 1)
    offset = offset.reshape(batch, taps, 2, out_h, out_w)
    pos_y = base_y + tap_y + offset[:, :, 0]  # [B, taps, Ho, Wo]
    pos_x = base_x + tap_x + offset[:, :, 1]

    y0 = torch.floor(pos_y)
    x0 = torch.floor(pos_x)
    wy1 = pos_y - y0
    wx1 = pos_x - x0
    wy0 = 1.0 - wy1
    wx0 = 1.0 - wx1

    # A one-pixel zero border lets every out-of-image corner read a zero: clamping a corner to
    # [-1, size] moves it onto the border without changing its (zero) value, and keeps indices >= 0.
    padded_h, padded_w = int(height) + 2, int(width) + 2  # Python ints: traced sizes would make the index int64
    rows = torch.stack([y0, y0, y0 + 1.0, y0 + 1.0]).clamp(-1.0, float(height)) + 1.0
    cols = torch.stack([x0, x0 + 1.0, x0, x0 + 1.0]).clamp(-1.0, float(width)) + 1.0
    weights = torch.stack([wy0 * wx0, wy0 * wx1, wy1 * wx0, wy1 * wx1])  # [4, B, taps, Ho, Wo]
    if mask is not None:
        weights = weights * mask.reshape(1, batch, taps, out_h, out_w)
    # The flat index in int32 (TensorRT has no int64 tensors): rows and columns are small enough to be exact
    # even in half precision, their product with the row length is not (4,800 at 480x640 > 2,048).
    batch_start = (torch.arange(int(batch), dtype=torch.int32, device=device) * (padded_h * padded_w)).view(1, -1, 1, 1, 1)
    flat_index = (rows.to(torch.int32) * padded_w + cols.to(torch.int32) + batch_start).reshape(4, -1)
    weights = weights.reshape(4, -1, 1).to(x.dtype)

    # One Gather per corner, weighted and added: summing a stacked [4, ...] product over its first axis
    # exports a strided ReduceSum that onnxruntime ran ~3x slower than the gathers themselves.
    pixels = F.pad(x, (1, 1, 1, 1)).permute(0, 2, 3, 1).reshape(batch * padded_h * padded_w, channels)
    sampled = torch.index_select(pixels, 0, flat_index[0]) * weights[0]
    for corner in range(1, 4):
        sampled = sampled + torch.index_select(pixels, 0, flat_index[corner]) * weights[corner]
    sampled = sampled.reshape(batch, taps, locations, channels)

    if depthwise:  # each channel weighs its own taps: multiply-adds over the 9 taps, no matmul
        kernel = weight.reshape(channels, taps).transpose(0, 1)  # [taps, C]
        out = sampled[:, 0] * kernel[0]
        for tap in range(1, taps):
            out = out + sampled[:, tap] * kernel[tap]  # [B, L, C]
        if bias is not None:
            out = out + bias
        return out.permute(0, 2, 1).reshape(batch, out_channels, out_h, out_w)
    columns = sampled.permute(0, 2, 1, 3).reshape(batch, locations, taps * channels)
    kernel = weight.permute(2, 3, 1, 0).reshape(taps * channels, out_channels)  # tap-major, then channel
    out = torch.matmul(columns, kernel)  # [B, L, Cout]
    if bias is not None:
        out = out + bias
    return out.permute(0, 2, 1).reshape(batch, out_channels, out_h, out_w)


def deform_conv2d_grid_sample(
    x: torch.Tensor,
    offset: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """`deform_conv2d` (3x3, stride 1, padding 1) with the bilinear sampling done by ``grid_sample``.

    Training only: the same values as the gather sampler (zero outside the image), but its fused
    forward/backward kernels make a CPU training step 1.3-1.5x faster than gather + ``index_add_``.
    Neither target can run GridSample fast (TensorRT 8.0 lacks it, onnxruntime's kernel is slow), so
    exports keep the ``torch`` (portable) and ``native`` paths.

    Shapes as `deform_conv2d`: x [B, C, H, W], offset [B, 18, H, W], weight [Cout, C, 3, 3] or depthwise
    [C, 1, 3, 3], mask [B, 9, H, W] or None -> [B, Cout, H, W].
    """
    batch, channels, height, width = x.shape
    out_channels = weight.shape[0]
    depthwise = is_depthwise(weight, channels)
    taps = 9
    dtype, device = torch.promote_types(x.dtype, torch.float32), x.device
    offset = offset.to(dtype).reshape(batch, taps, 2, height, width)
    rows = torch.arange(height, dtype=dtype, device=device).view(1, 1, height, 1)
    cols = torch.arange(width, dtype=dtype, device=device).view(1, 1, 1, width)
    tap_y = torch.arange(3, dtype=dtype, device=device).repeat_interleave(3).view(1, taps, 1, 1) - 1.0
    tap_x = torch.arange(3, dtype=dtype, device=device).repeat(3).view(1, taps, 1, 1) - 1.0
    pos_y = rows + tap_y + offset[:, :, 0]  # [B, taps, H, W]
    pos_x = cols + tap_x + offset[:, :, 1]
    # align_corners=True: -1 and +1 are the centres of the first and last pixels.
    grid = torch.stack([pos_x * (2.0 / max(width - 1, 1)) - 1.0, pos_y * (2.0 / max(height - 1, 1)) - 1.0], dim=-1)
    sampled = F.grid_sample(
        x.to(dtype), grid.reshape(batch, taps * height, width, 2), mode="bilinear", padding_mode="zeros", align_corners=True
    ).reshape(batch, channels, taps, height, width)
    if mask is not None:
        sampled = sampled * mask.to(dtype).reshape(batch, 1, taps, height, width)
    if depthwise:  # [B, C, taps, H, W] x [C, taps] -> [B, C, H, W]
        out = torch.einsum("bckhw,ck->bchw", sampled.to(x.dtype), weight.reshape(channels, taps).to(x.dtype))
        return out if bias is None else out + bias.view(1, -1, 1, 1)
    # [B, C, taps, H, W] x [Cout, C, taps] -> [B, Cout, H, W]
    out = torch.einsum("bckhw,ock->bohw", sampled.to(x.dtype), weight.reshape(out_channels, channels, taps).to(x.dtype))
    if bias is not None:
        out = out + bias.view(1, -1, 1, 1)
    return out


@torch.library.custom_op("edgefeat::deform_conv2d", mutates_args=())
def native_deform_conv2d(
    x: torch.Tensor, offset: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, mask: torch.Tensor | None
) -> torch.Tensor:
    """3x3, stride 1, padding 1 `deform_conv2d` as one opaque op, so the exporter emits ONNX ``DeformConv``."""
    return deform_conv2d(x, offset, weight, bias, mask, 1, 1, 1)


@native_deform_conv2d.register_fake
def _native_deform_conv2d_shape(x, offset, weight, bias, mask):  # shapes only, for tracing
    return x.new_empty(x.shape[0], weight.shape[0], x.shape[2], x.shape[3])


def _deform_conv_symbolic(g, x, offset, weight, bias, mask):  # pragma: no cover - runs inside the exporter
    from torch.onnx import symbolic_helper

    # group = C / (kernel's input channels): 1 for a dense kernel, C for a depthwise one.
    group = symbolic_helper._get_tensor_sizes(x)[1] // symbolic_helper._get_tensor_sizes(weight)[1]
    inputs = [x, weight, offset, bias]
    if not (mask.node().kind() == "prim::Constant" and mask.type().kind() == "NoneType"):
        inputs.append(mask)
    return g.op(
        "DeformConv",
        *inputs,
        dilations_i=[1, 1],
        group_i=group,
        kernel_shape_i=[3, 3],
        offset_group_i=1,
        pads_i=[1, 1, 1, 1],
        strides_i=[1, 1],
    )


# DeformConv entered the ONNX standard in opset 19 (onnxruntime >= 1.25 implements it on CPU).
NATIVE_DEFORM_OPSET = 19
torch.onnx.register_custom_op_symbolic("edgefeat::deform_conv2d", _deform_conv_symbolic, NATIVE_DEFORM_OPSET)


class DeformableConv(nn.Module):
    """3x3 deformable conv whose offsets (and optional DCNv2 mask) come from a depthwise-separable branch.

    The kernel lives in a real ``nn.Conv2d`` so pruning tools see an ordinary conv. The offset branch
    (depthwise 3x3 + BN + ReLU, then pointwise 1x1 to 2*9 offsets [+ 9 mask logits]) starts at zero, so
    an untrained layer is exactly a plain 3x3 conv (with mask 0.5 if modulated).

    With ``depthwise`` the sampled 3x3 kernel is depthwise (one per channel) and a 1x1 ``pointwise`` conv
    mixes channels, like every other block of the network: 9*C + C*Cout weights instead of 9*C*Cout, and
    the channel mixing is an ordinary Conv that INT8 can quantise.

    Attributes:
        strategy: ``"torch"`` (the portable export, and the reference), ``"native"`` (ONNX DeformConv) or
            ``"grid_sample"`` (training only: fastest on CPU, not exportable to either target).
    """

    def __init__(self, in_channels: int, out_channels: int, modulated: bool = True, depthwise: bool = False,
                 deform_fraction: float = 1.0) -> None:
        super().__init__()
        if not 0.0 < deform_fraction <= 1.0 or (deform_fraction < 1.0 and not depthwise):
            raise ValueError("deform_fraction must be in (0, 1], and below 1 only for a depthwise kernel")
        self.modulated = modulated
        # Share of the channels (the leading ones) sampled at the learned offsets; the rest take a plain
        # depthwise 3x3. The deformable sampler is the largest single cost of the network on a CPU, and a
        # depthwise kernel lets each channel choose independently, so the split is exact and cheap.
        self.deform_fraction = float(deform_fraction)
        self.strategy: DeformStrategy = "torch"
        taps = 9
        self.offset_dw = nn.Conv2d(in_channels, in_channels, 3, padding=1, groups=in_channels, bias=False)
        self.offset_bn = nn.BatchNorm2d(in_channels)
        self.offset_pw = nn.Conv2d(in_channels, taps * (3 if modulated else 2), 1)
        nn.init.zeros_(self.offset_pw.weight)
        nn.init.zeros_(self.offset_pw.bias)
        if depthwise:
            self.conv = nn.Conv2d(in_channels, in_channels, 3, padding=1, groups=in_channels)
            self.pointwise: nn.Conv2d | None = nn.Conv2d(in_channels, out_channels, 1)
        else:
            self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1)
            self.pointwise = None
        # Tracing hook for structured pruning (torch-pruning's DepGraph), off by default. DepGraph follows
        # autograd through every op, and the gather-based sampler is an op soup it cannot map to channels
        # (it never returns). With ``trace_as_plain_conv`` set, forward is just ``self.conv(x)``: the same
        # Cin -> Cout coupling, so the layer's custom pruner (toolkit.compression.prune) can shrink its
        # kernel and the offset branch's inputs together while the 2*9 offset / 9 mask outputs stay whole.
        self.trace_as_plain_conv = False

    def offsets_and_mask(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x [B, C, H, W] -> offsets [B, 18, H, W], mask [B, 9, H, W] or None."""
        branch = self.offset_pw(F.relu(self.offset_bn(self.offset_dw(x))))
        if not self.modulated:
            return branch, None
        return branch[:, :18], torch.sigmoid(branch[:, 18:])

    @property
    def deform_channels(self) -> int:
        """Leading channels sampled at the offsets (follows the kernel's width, e.g. after pruning)."""
        channels = self.conv.in_channels
        return channels if self.deform_fraction >= 1.0 else max(1, min(channels, round(channels * self.deform_fraction)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.trace_as_plain_conv:  # pruning trace only, see __init__
            out = self.conv(x)
        else:
            offset, mask = self.offsets_and_mask(x)
            weight, bias, split, plain = self.conv.weight, self.conv.bias, self.deform_channels, None
            if split < x.shape[1]:  # depthwise: the channels past the split take the plain kernel
                plain = F.conv2d(x[:, split:], weight[split:], None if bias is None else bias[split:], padding=1,
                                 groups=x.shape[1] - split)
                x, weight, bias = x[:, :split], weight[:split], None if bias is None else bias[:split]
            if self.strategy == "native":
                out = native_deform_conv2d(x, offset, weight, bias, mask)
            elif self.strategy == "grid_sample":
                out = deform_conv2d_grid_sample(x, offset, weight, bias, mask)
            else:
                out = deform_conv2d(x, offset, weight, bias, mask, 1, 1, 1)
            if plain is not None:
                out = torch.cat([out, plain], dim=1)
        return out if self.pointwise is None else self.pointwise(out)


def separable_from_dense(weight: torch.Tensor, bias: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """The best depthwise + pointwise stand-in for a trained dense 3x3 kernel, to start a depthwise layer from.

    Each input channel's [Cout, 9] slice of ``weight`` [Cout, C, 3, 3] is replaced by its rank-1 SVD
    approximation u s v^T: the depthwise kernel takes v (its 9 taps), the pointwise column takes u s.
    Returns ``conv.weight`` [C, 1, 3, 3], ``conv.bias`` [C] (zero), ``pointwise.weight`` [Cout, C, 1, 1] and
    ``pointwise.bias`` [Cout] (the dense bias), as `DeformableConv` state-dict keys.
    """
    out_channels, channels = weight.shape[:2]
    per_channel = weight.detach().float().permute(1, 0, 2, 3).reshape(channels, out_channels, 9)
    u, s, vh = torch.linalg.svd(per_channel, full_matrices=False)
    return {
        "conv.weight": vh[:, 0, :].reshape(channels, 1, 3, 3).contiguous(),
        "conv.bias": torch.zeros(channels),
        "pointwise.weight": (u[:, :, 0] * s[:, :1]).transpose(0, 1).reshape(out_channels, channels, 1, 1).contiguous(),
        "pointwise.bias": torch.zeros(out_channels) if bias is None else bias.detach().float().clone(),
    }


def set_deform_strategy(model: nn.Module, strategy: DeformStrategy) -> nn.Module:
    """Set the execution/export strategy of every `DeformableConv` in ``model``; returns ``model``."""
    if strategy not in ("torch", "native", "grid_sample"):
        raise ValueError(f"unknown deform strategy {strategy!r}")
    for module in model.modules():
        if isinstance(module, DeformableConv):
            module.strategy = strategy
    return model
