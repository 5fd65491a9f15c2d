"""FeatureNet budget and structure, the SuperPoint loader, and checkpoints that never unpickle."""
from __future__ import annotations

import pickle

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from models.featurenet import ELU, FeatureNet, FeatureNetConfig, set_elu_form
from models.weights import shipped_checkpoint
from models.superpoint import SuperPointNet, load_superpoint_v1

torch.set_num_threads(1)
DEFAULT_RELU = shipped_checkpoint("featurenet-relu")


def macs_at(model: torch.nn.Module, height: int, width: int) -> float:
    counter = FlopCounterMode(display=False)
    with counter, torch.no_grad():
        model(torch.rand(1, 1, height, width))
    return counter.get_total_flops() / 2  # the counter reports FLOPs = 2 x multiply-accumulates


def test_featurenet_default_width_fits_the_budget():
    model = FeatureNet().eval()
    params = sum(p.numel() for p in model.parameters())
    macs = macs_at(model, 240, 320)
    assert params <= 350_000
    assert macs <= 0.5e9
    reference = macs_at(SuperPointNet().eval(), 240, 320)
    assert 6.0e9 < reference < 7.0e9  # the published 6.5 GMACs: the counter is sound
    assert reference / macs > 10


def test_featurenet_outputs_and_activation_variant():
    image = torch.rand(2, 1, 64, 96)
    for activation in ("elu", "relu"):
        model = FeatureNet(FeatureNetConfig(activation=activation)).eval()
        with torch.no_grad():
            out = model(image)
        assert out["logits"].shape == (2, 65, 8, 12)
        assert out["descriptors"].shape == (2, 256, 8, 12)
        assert torch.allclose(out["descriptors"].norm(dim=1), torch.ones(2, 8, 12), atol=1e-5)
        kinds = {type(m).__name__ for m in model.modules()}
        assert ("ELU" in kinds) == (activation == "elu")
    with pytest.raises(ValueError):
        FeatureNetConfig(activation="gelu")


def test_elu_max_exp_form_equals_elu():
    model = FeatureNet(FeatureNetConfig(activation="elu")).eval()
    image = torch.rand(1, 1, 64, 96)
    with torch.no_grad():
        native = model(image)
        set_elu_form(model, "max_exp")
        rewritten = model(image)
    assert torch.allclose(native["logits"], rewritten["logits"], atol=1e-5)
    rewritten_elu = ELU()
    rewritten_elu.form = "max_exp"
    x = torch.linspace(-30, 30, 10001)
    assert torch.allclose(rewritten_elu(x), torch.nn.functional.elu(x), atol=1e-7)
    assert all(m.form == "max_exp" for m in model.modules() if isinstance(m, ELU))
    with pytest.raises(ValueError):
        set_elu_form(model, "fast")


def test_keypoint_heads_match_the_training_heads():
    # The inference path (cells gathered by convs, descriptor projection deferred to the keypoints, stem
    # activation after the first max-pool) must compute what the training path computes, on a trained net
    # whose BN statistics and weights are far from their initial values.
    from models.keypoints import keypoint_heads, sample_descriptors

    net, _ = load_checkpoint(DEFAULT_RELU)
    net.eval()
    image = torch.rand(1, 1, 96, 128)
    image[..., :40, :48] = 0.5  # flat cells: contrast normalisation at its most fragile
    with torch.no_grad():
        dense = net(image)
        logits, features, projection = keypoint_heads(net, image)
        stem_then_pool = net.stages[1][0](net.stem(image))  # the order training has always used
        pool_then_activation = net.stem[2](net.stages[1][0](net.stem[1](net.stem[0](image))))
    assert torch.equal(stem_then_pool, pool_then_activation)
    assert torch.allclose(logits, dense["logits"], atol=1e-4)
    # At cell centres the deferred projection gives the dense descriptor exactly (bilinear weight 1).
    centres = torch.tensor([[3.5, 3.5], [19.5, 11.5], [123.5, 91.5]])
    expected = torch.stack([dense["descriptors"][0, :, int(y) // 8, int(x) // 8] for x, y in centres.tolist()])
    assert torch.allclose(sample_descriptors(features[0], centres, projection), expected, atol=1e-5)


def magic_leap_state_dict(seed: int) -> dict[str, torch.Tensor]:
    """A state dict with the exact key layout and shapes of Magic Leap's superpoint_v1.pth."""
    generator = torch.Generator().manual_seed(seed)
    shapes = {
        "conv1a": (64, 1, 3, 3), "conv1b": (64, 64, 3, 3), "conv2a": (64, 64, 3, 3), "conv2b": (64, 64, 3, 3),
        "conv3a": (128, 64, 3, 3), "conv3b": (128, 128, 3, 3), "conv4a": (128, 128, 3, 3), "conv4b": (128, 128, 3, 3),
        "convPa": (256, 128, 3, 3), "convPb": (65, 256, 1, 1), "convDa": (256, 128, 3, 3), "convDb": (256, 256, 1, 1),
    }
    state = {}
    for name, shape in shapes.items():
        state[f"{name}.weight"] = torch.randn(shape, generator=generator) * 0.05
        state[f"{name}.bias"] = torch.randn(shape[0], generator=generator) * 0.05
    return state


def test_superpoint_v1_layout_loads_with_every_key(tmp_path):
    state = magic_leap_state_dict(0)
    path = tmp_path / "superpoint_v1.pth"
    torch.save(state, path)
    model = load_superpoint_v1(path)
    assert sum(p.numel() for p in model.parameters()) == sum(t.numel() for t in state.values())
    for key, tensor in model.state_dict().items():
        assert torch.equal(tensor, state[key])
    # Through the generic checkpoint loader too.
    loaded, info = load_checkpoint(path)
    assert info.arch == "superpoint" and len(info.sha256) == 64

    broken = dict(state)
    broken.pop("convDb.bias")
    torch.save(broken, tmp_path / "broken.pth")
    with pytest.raises(CheckpointError, match="convDb.bias"):
        load_checkpoint(tmp_path / "broken.pth")


class Payload:
    def __reduce__(self):
        return (print, ("unpickled!",))


def test_pth_loading_refuses_pickled_objects(tmp_path):
    path = tmp_path / "evil.pth"
    with open(path, "wb") as handle:
        pickle.dump({"conv1a.weight": Payload()}, handle)
    with pytest.raises(CheckpointError):
        load_checkpoint(path)


def test_checkpoint_round_trip_and_bad_files(tmp_path):
    torch.manual_seed(0)
    model = FeatureNet(FeatureNetConfig(widths=[8, 16, 24, 32], head_channels=32, activation="relu")).eval()
    path = save_checkpoint(model, tmp_path / "net.safetensors", metadata={"steps": 3})
    assert not list(tmp_path.glob(".tmp-*")), "no temporary file left behind"
    loaded, info = load_checkpoint(path)
    assert info.config["widths"] == [8, 16, 24, 32] and info.metadata == {"steps": 3}
    image = torch.rand(1, 1, 32, 48)
    with torch.no_grad():
        assert torch.equal(model(image)["logits"], loaded(image)["logits"])

    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(path.read_bytes()[:200])
    with pytest.raises(CheckpointError, match="not a readable"):
        load_checkpoint(truncated)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "absent.safetensors")

    # A header that claims other widths than the tensors hold.
    from safetensors.torch import load_file, save_file
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        header = dict(handle.metadata())
    header["config"] = header["config"].replace("[8, 16, 24, 32]", "[8, 16, 24, 64]")
    mismatched = tmp_path / "mismatched.safetensors"
    save_file(load_file(str(path)), str(mismatched), metadata=header)
    with pytest.raises(CheckpointError, match="does not match"):
        load_checkpoint(mismatched)
