"""The cell-pixel head over a window reaching into the neighbouring cells (`WindowPixelHead`), grown from an
8x8 head, and head-only fine-tunes (`toolkit.training.freezing`)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import onnx
import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.featurenet import CellPixelHead, FeatureNet, FeatureNetConfig, WindowPixelHead, widen_pixel_window
from models.weights import shipped_checkpoint
from toolkit.compression.images import load_images
from toolkit.compression.prune import prune_channels
from toolkit.compression.proxy import calibrated_random_featurenet
from toolkit.compression.sensitivity import fixed_kernel_convs, single_channel_convs
from toolkit.errors import ToolkitError
from toolkit.training.freezing import freeze_outside, hold_frozen_in_eval
from toolkit.training.trainer import initialise_from
from roundtrip_support import assert_saves_and_exports

torch.set_num_threads(1)
SIZE = (64, 96)
SMALL = FeatureNetConfig(widths=[16, 24, 32, 64], blocks=[0, 1, 1, 2], head_channels=64, descriptor_dim=64,
                         deform_depthwise=True, pixel_head_channels=32, pixel_head_margin=1)


class _Holder(torch.nn.Module):
    def __init__(self, head: torch.nn.Module) -> None:
        super().__init__()
        self.pixel_head = head


def _randomised(head: torch.nn.Module) -> torch.nn.Module:
    torch.manual_seed(0)
    with torch.no_grad():
        for module in head.modules():
            if isinstance(module, torch.nn.Conv2d):
                torch.nn.init.normal_(module.weight, std=0.2)
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5), module.running_var.uniform_(0.5, 2.0)
    return head.eval()


def _grown(cell: CellPixelHead, margin: int) -> WindowPixelHead:
    window = WindowPixelHead(cell.layers[0].out_channels, "elu", margin)
    state = widen_pixel_window({f"pixel_head.{k}": v for k, v in cell.state_dict().items()}, _Holder(window))
    window.load_state_dict({k.removeprefix("pixel_head."): v for k, v in state.items()})
    return window.eval()


def test_a_window_without_margin_computes_the_cell_head():
    cell = _randomised(CellPixelHead(32, "elu"))
    window = _grown(cell, 0)
    image = torch.rand(2, 1, 48, 64)
    with torch.no_grad():
        assert torch.allclose(window(image), cell(image), atol=1e-5)
        assert torch.allclose(window(image), cell(image, cells_by_conv=True), atol=1e-5)


def test_the_window_sees_past_its_cell_and_ignores_brightness():
    cell = _randomised(CellPixelHead(32, "elu"))
    window = _randomised(WindowPixelHead(32, "elu", 1))
    image = torch.rand(1, 1, 48, 64)
    nudged = image.clone()
    nudged[0, 0, 20, 16] += 0.5  # row 20 is inside cell row 2; column 16 is the first of cell column 2
    with torch.no_grad():
        cell_change = (cell(nudged) - cell(image)).abs().sum(dim=1)[0]
        window_change = (window(nudged) - window(image)).abs().sum(dim=1)[0]
    assert cell_change[2, 1] == 0 and cell_change[2, 2] > 0  # the 8x8 head: only its own cell
    assert window_change[2, 1] > 0 and window_change[2, 2] > 0  # the window: its neighbour's first column too
    # cells whose window misses the pixel: unchanged but for rounding (the head shifts by the image's mean)
    assert window_change[2, 0] < 1e-4 and window_change[0, 1] < 1e-4
    with torch.no_grad():  # contrast-normalised: a gain and an offset change little (the 1e-4 in the contrast), away from
        inner = (slice(None), slice(None), slice(1, -1), slice(1, -1))  # the zero padding of the image border
        assert torch.allclose(window(0.5 * image + 0.2)[inner], window(image)[inner], atol=5e-2)


def test_growing_an_8x8_model_keeps_its_inner_weights(tmp_path):
    shipped, _ = load_checkpoint(shipped_checkpoint("featurenet-elu"))
    assert shipped.config.pixel_head_margin == 2  # the shipped weights were grown this way
    cell_model = FeatureNet(replace(shipped.config, pixel_head_margin=0))
    own = {k: v for k, v in shipped.state_dict().items() if not k.startswith("pixel_head.")}
    cell_model.load_state_dict(own, strict=False)
    _randomised(cell_model.pixel_head)
    source = save_checkpoint(cell_model, tmp_path / "cell.safetensors")
    grown = FeatureNet(replace(shipped.config, pixel_head_margin=1))
    initialise_from(str(source), grown, None)
    old = cell_model.pixel_head.layers[0].weight.reshape(-1, 8, 8)
    new = grown.pixel_head.layers[0].weight[:, 0]
    assert torch.equal(new[:, 1:9, 1:9], old) and new[:, 0].abs().sum() == 0 and new[:, 9].abs().sum() == 0
    assert torch.equal(grown.detector[1].weight, cell_model.detector[1].weight)
    cell_model.eval(), grown.eval()
    image = torch.from_numpy(load_images_or_noise())
    with torch.no_grad():  # only the normalising window changed: most peaks stay where they were
        same = (cell_model(image)["logits"].argmax(1) == grown(image)["logits"].argmax(1)).float().mean()
    assert same > 0.8
    path = save_checkpoint(grown, tmp_path / "grown.safetensors")
    assert load_checkpoint(path)[1].config["pixel_head_margin"] == 1
    with pytest.raises(ToolkitError, match="do not match"):
        initialise_from(str(path), FeatureNet(cell_model.config), None)


def load_images_or_noise() -> np.ndarray:
    rng = np.random.default_rng(0)
    return np.clip(rng.normal(0.5, 0.2, (1, 1, 96, 128)), 0, 1).astype(np.float32)


def test_bad_margins_are_refused():
    for margin in (-1, 5):
        with pytest.raises(ValueError, match="pixel_head_margin"):
            FeatureNetConfig(pixel_head_margin=margin)


def test_a_window_head_prunes_saves_and_exports(shared_data, tmp_path):
    images = load_images(shared_data / "train_images", 8, SIZE)[0]
    teacher = calibrated_random_featurenet(SMALL, images)
    student = prune_channels(teacher, 0.3, SIZE)
    assert student.config.pixel_head_margin == 1 and student.pixel_head.layers[0].kernel_size == (10, 10)
    assert assert_saves_and_exports(student, images, tmp_path, SIZE)["pixel_head_margin"] == 1
    # What INT8 keeps in float: the box-kernel conv of the window statistics and the window conv on raw pixels
    graph = onnx.load(str(tmp_path / "x86-cpu" / "model.onnx"))
    assert [n for n in fixed_kernel_convs(graph)] and all("/window_statistics/" in n for n in fixed_kernel_convs(graph))
    assert any("pixel_head/layers.0/" in n for n in single_channel_convs(graph))


def test_only_the_named_parts_learn_and_the_rest_keeps_its_statistics():
    model = FeatureNet(SMALL)
    trained = freeze_outside(model, ["pixel_head", "detector"])
    assert trained and all(name.startswith(("pixel_head.", "detector.")) for name in trained)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.train()
    hold_frozen_in_eval(model, ["pixel_head", "detector"])
    assert not model.stem.training and not model.descriptor.training and model.pixel_head.training
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    out = model(torch.rand(2, 1, *SIZE))
    (out["logits"].square().mean() + out["descriptors"].sum() * 0.0).backward()
    optimizer.step()
    after = model.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert any(k.startswith("pixel_head.") for k in changed) and any(k.startswith("detector.") for k in changed)
    assert all(k.startswith(("pixel_head.", "detector.")) for k in changed)  # weights and BN statistics
    with pytest.raises(ToolkitError, match="not a part"):
        freeze_outside(FeatureNet(SMALL), ["pixel_heads"])
    assert len(freeze_outside(FeatureNet(SMALL), [])) == len(list(FeatureNet(SMALL).parameters()))
