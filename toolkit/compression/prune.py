"""Structured channel pruning of FeatureNet with torch-pruning's DepGraph.

DepGraph couples the layers that must shrink together (a depthwise conv with the pointwise conv that
feeds it, BatchNorms, both heads reading the shared features). It cannot trace the gather-based
deformable sampler, so while it traces, each `DeformableConv` acts as its plain 3x3 kernel
(``trace_as_plain_conv``) and a custom pruner (`DeformableConvPruner`) shrinks the layer as a unit:
its input channels cut the kernel, the offset branch's depthwise conv and BN and the offset 1x1's
inputs; its output channels cut the kernel only. The 2*9 offset and 9 mask outputs are never pruned,
nor are the layers whose output channels have a meaning (65-way detector, D-dim descriptor).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Sequence

import torch
import torch_pruning as tp
from torch import nn

from models.deform import DeformableConv
from models.featurenet import FeatureNet, FeatureNetConfig
from toolkit.errors import ToolkitError

CHANNEL_MULTIPLE = 8  # TensorRT FP16 kernels want channel counts in multiples of 8


def _keep(channels: int, pruned: Sequence[int]) -> list[int]:
    dropped = set(int(i) for i in pruned)
    return [i for i in range(channels) if i not in dropped]


def _slice_conv(conv: nn.Conv2d, keep_out: list[int] | None = None, keep_in: list[int] | None = None) -> None:
    """Keep the listed output / input channels of a dense (groups=1) conv, in place."""
    weight = conv.weight.data
    if keep_out is not None:
        weight = weight[keep_out]
        if conv.bias is not None:
            conv.bias = nn.Parameter(conv.bias.data[keep_out].clone())
        conv.out_channels = len(keep_out)
    if keep_in is not None:
        weight = weight[:, keep_in]
        conv.in_channels = len(keep_in)
    conv.weight = nn.Parameter(weight.clone())


def _slice_depthwise_kernel(conv: nn.Conv2d, keep: list[int]) -> None:
    conv.weight = nn.Parameter(conv.weight.data[keep].clone())
    if conv.bias is not None:
        conv.bias = nn.Parameter(conv.bias.data[keep].clone())
    conv.in_channels = conv.out_channels = conv.groups = len(keep)


def _slice_depthwise(conv: nn.Conv2d, bn: nn.BatchNorm2d, keep: list[int]) -> None:
    conv.weight = nn.Parameter(conv.weight.data[keep].clone())
    conv.in_channels = conv.out_channels = conv.groups = len(keep)
    bn.weight = nn.Parameter(bn.weight.data[keep].clone())
    bn.bias = nn.Parameter(bn.bias.data[keep].clone())
    bn.running_mean = bn.running_mean[keep].clone()
    bn.running_var = bn.running_var[keep].clone()
    bn.num_features = len(keep)


class DeformableConvPruner(tp.pruner.BasePruningFunc):
    """torch-pruning pruner for `DeformableConv`: input and output channels are independent (no intra-layer
    coupling), and the offset/mask outputs of ``offset_pw`` are left whole. A depthwise layer's outputs are
    its ``pointwise`` conv's; its inputs are the depthwise kernel's channels and the pointwise conv's inputs."""

    TARGET_MODULES = (DeformableConv,)

    def prune_out_channels(self, layer: DeformableConv, idxs: Sequence[int]) -> DeformableConv:
        mixer = layer.pointwise if layer.pointwise is not None else layer.conv
        _slice_conv(mixer, keep_out=_keep(mixer.out_channels, idxs))
        return layer

    def prune_in_channels(self, layer: DeformableConv, idxs: Sequence[int]) -> DeformableConv:
        keep = _keep(layer.conv.in_channels, idxs)
        if layer.pointwise is not None:
            _slice_depthwise_kernel(layer.conv, keep)
            _slice_conv(layer.pointwise, keep_in=keep)
        else:
            _slice_conv(layer.conv, keep_in=keep)
        _slice_depthwise(layer.offset_dw, layer.offset_bn, keep)
        _slice_conv(layer.offset_pw, keep_in=keep)
        return layer

    def get_out_channels(self, layer: DeformableConv) -> int:
        return (layer.pointwise if layer.pointwise is not None else layer.conv).out_channels

    def get_in_channels(self, layer: DeformableConv) -> int:
        return layer.conv.in_channels


PRUNER = DeformableConvPruner()


def _set_trace_mode(model: nn.Module, enabled: bool) -> None:
    for module in model.modules():
        if isinstance(module, DeformableConv):
            module.trace_as_plain_conv = enabled


def meaningful_output_layers(model: FeatureNet) -> list[nn.Module]:
    """Layers whose output channels mean something fixed: the 65-logit (detector and cell-pixel head) and
    descriptor 1x1 convs."""
    layers = [model.detector[-1], model.descriptor[-1]]
    if model.config.pixel_head_channels:
        layers.append(model.pixel_head.layers[-1])
    return layers


def kept_channels(channels: int, ratio: float, multiple: int = CHANNEL_MULTIPLE) -> int:
    """Channels left after removing ``ratio`` of ``channels``: nearest multiple of ``multiple``, at least one
    multiple, never more than ``channels`` (a group narrower than ``multiple`` is left alone)."""
    if channels <= multiple:
        return channels
    return min(channels, max(multiple, int(round(channels * (1.0 - ratio) / multiple)) * multiple))


def prune_channels(model: FeatureNet, ratio: float, size: tuple[int, int] = (64, 96)) -> FeatureNet:
    """Remove ``ratio`` of the channels of every prunable group (lowest group L1 magnitude first), the
    count kept rounded to the nearest multiple of 8 (`kept_channels`).

    Returns a pruned deep copy (eval mode, config updated); ``model`` is untouched. Raises `ToolkitError`
    if the result does not fit `FeatureNetConfig` (it should not happen: equal-width groups lose equally).
    """
    if not 0.0 < ratio < 1.0:
        raise ToolkitError(f"pruning ratio must be in (0, 1), got {ratio}")
    if not isinstance(model, FeatureNet):
        raise ToolkitError(f"pruning supports featurenet checkpoints, not {getattr(model, 'arch', type(model).__name__)}")
    pruned = copy.deepcopy(model).eval().requires_grad_(True)  # DepGraph traces through autograd
    ignored = meaningful_output_layers(pruned)
    importance = tp.importance.GroupMagnitudeImportance(p=1)
    _set_trace_mode(pruned, True)
    try:
        graph = tp.DependencyGraph().build_dependency(
            pruned, torch.zeros(1, 1, *size),  # heads stay traced: their input channels must shrink
            customized_pruners={DeformableConv: PRUNER},
        )
        # get_all_groups yields lazily; collect first so each group is pruned against the graph as built.
        groups = list(graph.get_all_groups(ignored_layers=ignored, root_module_types=(nn.Conv2d, DeformableConv)))
        for group in groups:
            root = group[0].dep.target.module
            channels = graph.get_out_channels(root)
            drop = channels - kept_channels(channels, ratio)
            if drop <= 0:
                continue
            with torch.no_grad():
                scores = importance(group)
            order = torch.argsort(scores)[:drop].tolist()
            graph.get_pruning_group(root, group[0].dep.handler, order).prune()
    finally:
        _set_trace_mode(pruned, False)
    pruned.config = config_of(pruned)
    if count_parameters(pruned) == count_parameters(model):
        raise ToolkitError(f"ratio {ratio} removes no channel: every group keeps its width at multiples of {CHANNEL_MULTIPLE}")
    return pruned.requires_grad_(False)


def config_of(model: FeatureNet) -> FeatureNetConfig:
    """Read the widths of a (pruned) FeatureNet back into a config that rebuilds exactly this network."""
    base = model.config
    widths = list(base.widths)
    widths[0] = model.stem[0].out_channels
    for scale, stage in enumerate(model.stages):
        blocks = [m for m in stage if not isinstance(m, (nn.MaxPool2d, nn.Identity))]
        outs = {block.pointwise.out_channels for block in blocks}
        if len(outs) > 1:
            raise ToolkitError(f"pruned stage {scale} has unequal block widths {sorted(outs)}; the config cannot express it")
        if outs:
            widths[scale] = outs.pop()
    heads = {model.detector[0].pointwise.out_channels, model.descriptor[0].pointwise.out_channels}
    if len(heads) > 1:
        raise ToolkitError(f"pruned heads have unequal widths {sorted(heads)}; the config cannot express it")
    if base.deformable and PRUNER.get_out_channels(model.deform) != model.deform.conv.in_channels:
        raise ToolkitError("pruned deformable conv has unequal input and output widths; the config cannot express it")
    pixel = 0
    if base.pixel_head_channels:
        pixel_widths = {model.pixel_head.layers[0].out_channels, model.pixel_head.layers[3].out_channels}
        if len(pixel_widths) > 1:
            raise ToolkitError(f"pruned cell-pixel head has unequal widths {sorted(pixel_widths)}; the config cannot express it")
        pixel = pixel_widths.pop()
    context = base.context_channels
    if base.context_blocks:
        hidden = {block.expand.out_channels for block in model.context}
        if len(hidden) > 1:
            raise ToolkitError(f"pruned context blocks have unequal widths {sorted(hidden)}; the config cannot express it")
        context = hidden.pop()
    return replace(base, widths=widths, head_channels=heads.pop(), pixel_head_channels=pixel,
                   context_channels=context)


def rebuild(model: FeatureNet) -> FeatureNet:
    """A fresh FeatureNet from ``config_of(model)`` with ``model``'s weights (strict): proves the config is exact."""
    fresh = FeatureNet(config_of(model))
    fresh.load_state_dict(model.state_dict(), strict=True)
    return fresh.eval()


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def count_macs(model: nn.Module, size: tuple[int, int]) -> int:
    """Multiply-accumulates of one forward pass on a [1, 1, H, W] image: every conv, plus the deformable
    layer's kernel matmul and its 4-corner bilinear sampling (which run outside ``nn.Conv2d``)."""
    total = 0
    deform_kernels = {m.conv for m in model.modules() if isinstance(m, DeformableConv)}

    def conv_hook(module: nn.Conv2d, _inputs, output: torch.Tensor) -> None:
        nonlocal total
        kh, kw = module.kernel_size
        total += output.numel() * (module.in_channels // module.groups) * kh * kw

    def deform_hook(module: DeformableConv, inputs, output: torch.Tensor) -> None:
        nonlocal total
        conv = module.conv
        taps = conv.kernel_size[0] * conv.kernel_size[1]
        locations = output.shape[0] * output.shape[2] * output.shape[3]
        kernel = conv.out_channels * (conv.in_channels // conv.groups)  # dense: Cout*C; depthwise: C (a pointwise conv follows)
        total += locations * taps * (kernel + 4 * conv.in_channels)

    hooks = [m.register_forward_hook(conv_hook) for m in model.modules()
             if isinstance(m, nn.Conv2d) and m not in deform_kernels]
    hooks += [m.register_forward_hook(deform_hook) for m in model.modules() if isinstance(m, DeformableConv)]
    try:
        with torch.no_grad():
            model(torch.zeros(1, 1, *size))
    finally:
        for hook in hooks:
            hook.remove()
    return int(total)


@dataclass
class PruneSearch:
    ratio: float
    macs: int


def ratio_for_target_macs(model: FeatureNet, target_macs: int, size: tuple[int, int], steps: int = 8) -> PruneSearch:
    """Smallest pruning ratio whose pruned network needs at most ``target_macs`` (bisection on the ratio).

    MACs fall in steps (channel counts move by 8), so the bisection settles on the step's lower edge.
    """
    full = count_macs(model, size)
    if target_macs >= full:
        raise ToolkitError(f"--target-macs {target_macs:,} is not below the model's {full:,} MACs at {size[0]}x{size[1]}")
    low, high = 0.0, 0.95
    high_macs = count_macs(prune_channels(model, high), size)
    if high_macs > target_macs:
        raise ToolkitError(f"--target-macs {target_macs:,} is out of reach: pruning 95% of channels still needs {high_macs:,}")
    for _ in range(steps):
        middle = (low + high) / 2
        macs = count_macs(prune_channels(model, middle), size)
        if macs <= target_macs:
            high, high_macs = middle, macs
        else:
            low = middle
    return PruneSearch(round(high, 4), high_macs)
