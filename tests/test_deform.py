"""The deformable conv three ways (PyTorch autograd, portable ONNX, native ONNX DeformConv) give one answer."""
from __future__ import annotations

import io

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from models.deform import DeformableConv, deform_conv2d, set_deform_strategy

torch.set_num_threads(1)


def reference_deform_conv(x, offset, weight, bias, mask):
    """Direct loop over outputs and taps (no shared code with the implementation): stride 1, pad 1, 3x3."""
    batch, channels, height, width = x.shape
    out = np.zeros((batch, weight.shape[0], height, width))

    def sample(image, y, x_):
        if y <= -1 or y >= height or x_ <= -1 or x_ >= width:
            return 0.0
        y0, x0 = int(np.floor(y)), int(np.floor(x_))
        total = 0.0
        for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
            for xx, wx in ((x0, 1 - (x_ - x0)), (x0 + 1, x_ - x0)):
                if 0 <= yy < height and 0 <= xx < width:
                    total += wy * wx * image[yy, xx]
        return total

    for b in range(batch):
        for i in range(height):
            for j in range(width):
                for k in range(9):
                    ky, kx = divmod(k, 3)
                    py = i - 1 + ky + offset[b, 2 * k, i, j]
                    px = j - 1 + kx + offset[b, 2 * k + 1, i, j]
                    scale = 1.0 if mask is None else mask[b, k, i, j]
                    for c in range(channels):
                        out[b, :, i, j] += weight[:, c, ky, kx] * sample(x[b, c], py, px) * scale
        out[b] += bias[:, None, None]
    return out


def random_case(seed: int, batch=2, channels=3, height=6, width=7, out_channels=4):
    generator = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, channels, height, width, generator=generator)
    # Large and fractional offsets: many taps land between pixels, beyond the border, or far outside.
    offset = torch.randn(batch, 18, height, width, generator=generator) * 3.0
    offset[:, ::5] += 12.0
    mask = torch.rand(batch, 9, height, width, generator=generator)
    weight = torch.randn(out_channels, channels, 3, 3, generator=generator)
    bias = torch.randn(out_channels, generator=generator)
    return x, offset, weight, bias, mask


@pytest.mark.parametrize("modulated", [True, False])
def test_torch_matches_direct_reference(modulated):
    x, offset, weight, bias, mask = random_case(0)
    mask = mask if modulated else None
    expected = reference_deform_conv(x.numpy(), offset.numpy(), weight.numpy(), bias.numpy(), None if mask is None else mask.numpy())
    got = deform_conv2d(x, offset, weight, bias, mask).numpy()
    outside = (offset.abs() > 6).float().mean().item()
    assert outside > 0.1, "the case must exercise samples outside the image"
    assert np.abs(got - expected).max() <= 1e-4


def test_torch_path_has_gradients_for_every_input():
    x, offset, weight, bias, mask = (t.double() for t in random_case(1, batch=1, channels=2, height=4, width=5, out_channels=2))
    offset = offset + 0.37  # keep samples off integer positions, where bilinear sampling has kinks
    inputs = tuple(t.clone().requires_grad_(True) for t in (x, offset, weight, bias, mask))
    assert torch.autograd.gradcheck(lambda *a: deform_conv2d(*a), inputs, eps=1e-6, atol=1e-5)


def _export(module, x, opset):
    buffer = io.BytesIO()
    torch.onnx.export(module, (x,), buffer, dynamo=False, opset_version=opset, input_names=["x"])
    return onnx.load_from_string(buffer.getvalue())


def _run(model, x):
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return session.run(None, {"x": x.numpy()})[0]


@pytest.mark.parametrize("modulated, depthwise, fraction", [(True, False, 1.0), (False, False, 1.0), (True, True, 1.0),
                                                          (True, True, 0.5)])
def test_training_portable_and_native_paths_agree(modulated, depthwise, fraction):
    torch.manual_seed(2)
    layer = DeformableConv(8, 16, modulated=modulated, depthwise=depthwise, deform_fraction=fraction).eval()
    torch.nn.init.normal_(layer.offset_pw.weight, std=1.5)  # offsets of several pixels, fractional
    torch.nn.init.normal_(layer.offset_pw.bias, std=4.0)
    x = torch.randn(1, 8, 12, 16)
    with torch.no_grad():
        offsets, _ = layer.offsets_and_mask(x)
        training = layer(x).numpy()
    assert offsets.abs().max() > 8 and (offsets.frac().abs() > 0.1).float().mean() > 0.5

    portable = _export(set_deform_strategy(layer, "torch"), x, 13)
    native = _export(set_deform_strategy(layer, "native"), x, 19)
    set_deform_strategy(layer, "torch")
    portable_ops = {node.op_type for node in portable.graph.node}
    native_ops = {node.op_type for node in native.graph.node}
    assert portable.opset_import[0].version == 13
    assert not portable_ops & {"DeformConv", "GridSample", "GatherND"}
    assert "DeformConv" in native_ops
    group = next(a.i for n in native.graph.node if n.op_type == "DeformConv" for a in n.attribute if a.name == "group")
    assert group == (int(8 * fraction) if depthwise else 1)

    assert np.abs(_run(portable, x) - training).max() <= 1e-4
    assert np.abs(_run(native, x) - training).max() <= 1e-4


def test_untrained_layer_is_a_plain_convolution():
    layer = DeformableConv(4, 6, modulated=False).eval()
    x = torch.randn(1, 4, 9, 9)
    with torch.no_grad():
        assert torch.allclose(layer(x), layer.conv(x), atol=1e-5)


def test_half_precision_inputs_index_correctly():
    # 60x60 padded maps have flat indices above 2048, which bfloat16/float16 cannot represent exactly.
    x, offset, weight, bias, mask = random_case(3, batch=1, channels=2, height=60, width=60, out_channels=2)
    reference = deform_conv2d(x, offset, weight, bias, mask)
    half = deform_conv2d(x.bfloat16(), offset.bfloat16(), weight.bfloat16(), bias.bfloat16(), mask.bfloat16())
    assert half.dtype == torch.bfloat16
    scale = reference.abs().max()
    assert (half.float() - reference).abs().max() / scale < 0.05


@pytest.mark.parametrize("modulated", [True, False])
def test_training_grid_sample_sampler_matches_the_reference_and_the_gather_gradients(modulated):
    """The training-only grid_sample sampler gives the same values as the loop reference and the same
    gradients as the gather sampler that the portable export uses (native is checked against both above)."""
    from models.deform import deform_conv2d_grid_sample

    x, offset, weight, bias, mask = random_case(7)
    mask = mask if modulated else None
    expected = reference_deform_conv(x.numpy(), offset.numpy(), weight.numpy(), bias.numpy(),
                                     None if mask is None else mask.numpy())
    got = deform_conv2d_grid_sample(x, offset, weight, bias, mask)
    assert np.abs(got.detach().numpy() - expected).max() < 1e-4

    inputs = [t.clone().requires_grad_(True) for t in (x, offset, weight, bias)]
    gather = deform_conv2d(*inputs, mask, 1, 1, 1)
    gather.square().sum().backward()
    gather_grads = [t.grad.clone() for t in inputs]
    inputs = [t.clone().detach().requires_grad_(True) for t in (x, offset, weight, bias)]
    deform_conv2d_grid_sample(*inputs, mask).square().sum().backward()
    for name, a, b in zip(("x", "offset", "weight", "bias"), gather_grads, [t.grad for t in inputs]):
        assert torch.allclose(a, b, atol=1e-3, rtol=1e-4), name


def test_deformable_conv_grid_sample_strategy_is_the_same_layer():
    torch.manual_seed(0)
    layer = DeformableConv(6, 5)
    torch.nn.init.normal_(layer.offset_pw.weight, std=0.5)
    x = torch.randn(2, 6, 9, 11)
    expected = layer(x)
    set_deform_strategy(layer, "grid_sample")
    assert torch.allclose(layer(x), expected, atol=1e-4)


def test_depthwise_samplers_match_the_reference_and_each_other():
    """A depthwise kernel [C, 1, 3, 3] is the dense loop reference with a block-diagonal kernel; the gather
    sampler (training reference and portable export) and the grid_sample one give it, with equal gradients."""
    from models.deform import deform_conv2d_grid_sample

    x, offset, _, bias, mask = random_case(11, channels=4, out_channels=4)
    weight = torch.randn(4, 1, 3, 3, generator=torch.Generator().manual_seed(5))
    dense = torch.zeros(4, 4, 3, 3)
    dense[range(4), range(4)] = weight[:, 0]
    expected = reference_deform_conv(x.numpy(), offset.numpy(), dense.numpy(), bias.numpy(), mask.numpy())
    gather = deform_conv2d(x, offset, weight, bias, mask)
    assert np.abs(gather.numpy() - expected).max() < 1e-4
    assert np.abs(deform_conv2d_grid_sample(x, offset, weight, bias, mask).numpy() - expected).max() < 1e-4

    grads = []
    for sampler in (lambda *a: deform_conv2d(*a, mask), lambda *a: deform_conv2d_grid_sample(*a, mask)):
        inputs = [t.clone().requires_grad_(True) for t in (x, offset, weight, bias)]
        sampler(*inputs).square().sum().backward()
        grads.append([t.grad for t in inputs])
    for name, a, b in zip(("x", "offset", "weight", "bias"), *grads):
        assert torch.allclose(a, b, atol=1e-3, rtol=1e-4), name
    with pytest.raises(ValueError, match="neither dense nor depthwise"):
        deform_conv2d(x, offset, torch.randn(4, 2, 3, 3), bias, mask)


def test_a_separable_stand_in_is_exact_for_a_rank_one_kernel_and_best_otherwise():
    from models.deform import separable_from_dense

    generator = torch.Generator().manual_seed(3)
    taps = torch.randn(6, 9, generator=generator)  # per input channel: one 3x3 pattern ...
    mix = torch.randn(5, 6, generator=generator)  # ... scaled per output channel: exactly separable
    dense = (mix[:, :, None] * taps[None]).reshape(5, 6, 3, 3)
    bias = torch.randn(5, generator=generator)
    layer = DeformableConv(6, 5, depthwise=True).eval()
    layer.load_state_dict({**layer.state_dict(), **separable_from_dense(dense, bias)})
    x = torch.randn(1, 6, 7, 8, generator=generator)
    with torch.no_grad():
        expected = torch.nn.functional.conv2d(x, dense, bias, padding=1)
        assert torch.allclose(layer.pointwise(layer.conv(x)), expected, atol=1e-4)
        noisy = dense + 0.3 * torch.randn(dense.shape, generator=generator)
        stand_in = separable_from_dense(noisy, bias)
        rebuilt = stand_in["pointwise.weight"][:, :, 0, 0, None, None] * stand_in["conv.weight"][None, :, 0]
        assert (rebuilt - noisy).norm() < (dense - noisy).norm() + 1e-5  # rank-1 SVD: no worse than the true factors


def test_partly_deformable_layer_samples_the_leading_channels_and_convolves_the_rest():
    torch.manual_seed(3)
    full = DeformableConv(8, 6, depthwise=True).eval()
    torch.nn.init.normal_(full.offset_pw.weight, std=1.0)
    torch.nn.init.normal_(full.offset_pw.bias, std=2.0)
    half = DeformableConv(8, 6, depthwise=True, deform_fraction=0.5).eval()
    half.load_state_dict(full.state_dict())  # same parameters: the split only decides which channels sample
    assert half.deform_channels == 4
    x = torch.randn(1, 8, 10, 12)
    with torch.no_grad():
        capture = {}
        full.pointwise.register_forward_hook(lambda m, i, o: capture.__setitem__("full", i[0]))
        half.pointwise.register_forward_hook(lambda m, i, o: capture.__setitem__("half", i[0]))
        full(x), half(x)
        plain = torch.nn.functional.conv2d(x, full.conv.weight, full.conv.bias, padding=1, groups=8)
    # leading 4 channels: exactly the fully deformable layer's; the other 4: a plain depthwise 3x3
    assert torch.allclose(capture["half"][:, :4], capture["full"][:, :4], atol=1e-6)
    assert torch.allclose(capture["half"][:, 4:], plain[:, 4:], atol=1e-6)
    assert not torch.allclose(capture["full"][:, 4:], plain[:, 4:], atol=1e-3)  # the offsets did move them
    with torch.no_grad():
        gather = half(x)
        set_deform_strategy(half, "grid_sample")  # the training sampler splits the same way
        assert torch.allclose(half(x), gather, atol=1e-4)


def test_partial_deformation_needs_a_depthwise_kernel():
    with pytest.raises(ValueError, match="depthwise"):
        DeformableConv(8, 8, depthwise=False, deform_fraction=0.5)
    with pytest.raises(ValueError):
        DeformableConv(8, 8, depthwise=True, deform_fraction=0.0)
