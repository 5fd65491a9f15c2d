"""Context blocks: inverted residual blocks at H/8 that grow a trained FeatureNet without changing what it
computes, then train, prune, save and export like every other layer."""
from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.featurenet import FeatureNet, FeatureNetConfig, InvertedResidualBlock
from models.weights import shipped_checkpoint
from toolkit.compression.images import load_images
from toolkit.compression.prune import prune_channels
from toolkit.compression.proxy import calibrated_random_featurenet
from toolkit.errors import ToolkitError
from toolkit.training.trainer import initialise_from
from roundtrip_support import assert_saves_and_exports

torch.set_num_threads(1)
SIZE = (64, 96)
SMALL = FeatureNetConfig(widths=[16, 24, 32, 64], blocks=[0, 1, 1, 2], head_channels=64, descriptor_dim=64,
                         deform_depthwise=True, context_blocks=2, context_channels=96)


def test_a_new_block_is_the_identity_until_trained():
    block = InvertedResidualBlock(8, 16, "elu").eval()
    x = torch.randn(2, 8, 5, 7)
    with torch.no_grad():
        assert torch.equal(block(x), x)
        block.project_bn.weight.fill_(1.0)
        assert not torch.allclose(block(x), x, atol=1e-3)  # the residual branch is really in the sum


def test_growing_the_shipped_model_keeps_its_outputs(tmp_path):
    shipped, _ = load_checkpoint(shipped_checkpoint("featurenet-relu"))
    assert shipped.config.context_blocks == 0  # a trained model without them, to grow
    grown = FeatureNet(replace(shipped.config, context_blocks=2, context_channels=256))
    initialise_from(str(shipped_checkpoint("featurenet-relu")), grown, None)
    shipped.eval(), grown.eval()
    image = torch.rand(1, 1, 96, 128)
    with torch.no_grad():
        before, after = shipped(image), grown(image)
    assert torch.equal(before["logits"], after["logits"])
    assert torch.equal(before["descriptors"], after["descriptors"])
    # A checkpoint that already has context blocks is loaded as it is, not re-grown.
    with torch.no_grad():
        for block in grown.context:
            block.project_bn.weight.fill_(0.5)
    path = save_checkpoint(grown, tmp_path / "grown.safetensors")
    again = FeatureNet(grown.config)
    initialise_from(str(path), again, None)
    assert torch.equal(again.context[1].project_bn.weight, grown.context[1].project_bn.weight)
    # A grown checkpoint does not fit the smaller model.
    with pytest.raises(ToolkitError, match="do not match"):
        initialise_from(str(path), FeatureNet(shipped.config), None)


def test_bad_context_settings_are_refused():
    with pytest.raises(ValueError, match="context_blocks"):
        FeatureNetConfig(context_blocks=-1)
    with pytest.raises(ValueError, match="context_channels"):
        FeatureNetConfig(context_blocks=1, context_channels=0)


def test_context_blocks_prune_save_and_export(shared_data, tmp_path):
    images = load_images(shared_data / "train_images", 8, SIZE)[0]
    teacher = calibrated_random_featurenet(SMALL, images)
    with torch.no_grad():  # give the residual branches weight, as training does
        for block in teacher.context:
            block.project_bn.weight.fill_(1.0)
    student = prune_channels(teacher, 0.3, SIZE)
    assert student.config.context_channels == 64 and all(b.expand.out_channels == 64 for b in student.context)
    assert all(b.project.out_channels == b.expand.in_channels == 48 for b in student.context)  # coupled to x
    config = assert_saves_and_exports(student, images, tmp_path, SIZE)
    assert config["context_blocks"] == 2 and config["context_channels"] == 64
