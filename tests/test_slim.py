"""The slim wide-camera network: a stride-2 stem (`FeatureNetConfig.stem_stride`), `restem`, and its distillation
(`toolkit.compression.slim`) on real images."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.featurenet import FeatureNet, FeatureNetConfig
from toolkit.compression.distill import distillation_loss
from toolkit.compression.images import find_images, load_images
from toolkit.compression.prune import config_of, prune_channels, rebuild
from toolkit.compression.proxy import calibrated_random_featurenet
from toolkit.compression.slim import SlimDistillConfig, _load_gray, distill_slim, make_batch, restem
from toolkit.training.augment import AugmentConfig

torch.set_num_threads(1)
SIZE = (64, 96)
SMALL = FeatureNetConfig(widths=[16, 24, 32, 64], blocks=[0, 1, 1, 2], head_channels=64, descriptor_dim=64,
                         activation="relu", deform_depthwise=True, pixel_head_channels=16)


@pytest.fixture(scope="module")
def teacher(shared_data) -> FeatureNet:
    return calibrated_random_featurenet(SMALL, load_images(shared_data / "train_images", 8, SIZE)[0])


def test_stem_stride_needs_no_full_resolution_blocks():
    with pytest.raises(ValueError, match="stem_stride"):
        FeatureNetConfig(blocks=[1, 1, 2, 2], stem_stride=2)
    with pytest.raises(ValueError, match="stem_stride"):
        FeatureNetConfig(stem_stride=4)
    assert FeatureNetConfig().stem_stride == 1  # checkpoints written before the field load as they were


def test_restem_keeps_every_weight_and_samples_the_stem_at_even_pixels(teacher):
    slim = restem(teacher).eval()
    assert slim.config.stem_stride == 2 and isinstance(slim.stages[1][0], torch.nn.Identity)
    for key, value in teacher.state_dict().items():
        assert torch.equal(slim.state_dict()[key], value), key
    image = torch.rand(1, 1, *SIZE)
    with torch.no_grad():
        full = teacher.stem[1](teacher.stem[0](image))
        strided = slim.stem[1](slim.stem[0](image))
        heads = slim(image)
    assert torch.allclose(strided, full[..., ::2, ::2], atol=1e-6)  # the stride-1 conv's even pixels
    assert heads["logits"].shape == (1, 65, SIZE[0] // 8, SIZE[1] // 8)
    assert heads["descriptors"].shape == (1, 64, SIZE[0] // 8, SIZE[1] // 8)


def test_a_pruned_strided_model_round_trips_its_config(teacher, tmp_path):
    slim = restem(prune_channels(teacher, 0.3, SIZE))
    assert config_of(slim).stem_stride == 2
    rebuilt = rebuild(slim)  # strict load into a FeatureNet built from the config read back
    path = save_checkpoint(rebuilt, tmp_path / "slim.safetensors")
    loaded, _ = load_checkpoint(path)
    image = torch.rand(1, 1, *SIZE)
    with torch.no_grad():
        assert torch.equal(loaded(image)["logits"], rebuilt(image)["logits"])


def test_batches_are_a_function_of_the_seed_and_step(shared_data):
    images = _load_gray(find_images(shared_data / "train_images" / "lowlight_dicm_lime")[:6])
    config = SlimDistillConfig(batch=3, sizes=[(48, 64), (64, 96)])
    first, again = make_batch(images, 5, config, AugmentConfig()), make_batch(images, 5, config, AugmentConfig())
    assert torch.equal(first, again) and first.shape == (3, 1, 64, 96)  # step 5 of two sizes: the second
    assert make_batch(images, 4, config, AugmentConfig()).shape == (3, 1, 48, 64)
    assert not torch.equal(make_batch(images, 7, config, AugmentConfig()), first)
    assert 0.0 <= float(first.min()) and float(first.max()) <= 1.0


def test_distillation_brings_the_student_towards_the_teacher(teacher, shared_data):
    """The strided, pruned student reproduces the teacher's heads better after distilling (held-out batches)."""
    student = restem(prune_channels(teacher, 0.3, SIZE))
    images = shared_data / "train_images" / "lowlight_dicm_lime"
    config = SlimDistillConfig(steps=60, batch=4, lr=2e-3, sizes=[SIZE], seed=1)
    held_out = torch.cat([make_batch(_load_gray(find_images(images)[:20]), 10_000 + i, config, AugmentConfig())
                          for i in range(2)])

    def gap() -> float:
        with torch.no_grad():
            return float(distillation_loss(student.eval()(held_out), teacher.eval()(held_out), config.temperature))

    before = gap()
    sampling = teacher.deform.strategy
    rows = distill_slim(student, teacher, images, config, log=lambda _text: None)
    assert teacher.deform.strategy == sampling  # trained through grid_sample, handed back as it came
    after = gap()
    assert len(rows) == 1 and np.isfinite(rows[0]["loss"])
    assert after < 0.8 * before, (before, after)
    assert not student.training  # handed back in eval mode, as export expects


def test_the_command_refuses_bad_input_and_never_replaces_a_foreign_file(shared_data, tmp_path):
    import subprocess
    import sys

    foreign = tmp_path / "mine.safetensors"
    foreign.write_bytes(b"the user's file")
    images = str(shared_data / "train_images" / "coco128")
    for argv, message in ((["--images", str(tmp_path / "none"), "-o", str(tmp_path / "a.safetensors")], "image folder not found"),
                          (["--images", images, "-o", str(foreign)], "never replaced"),
                          (["--images", images, "-o", str(tmp_path / "a.pt")], ".safetensors")):
        done = subprocess.run([sys.executable, "-m", "toolkit.compression.slim", *argv, "--steps", "1"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and done.stderr.strip().startswith("error:") and message in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
    assert foreign.read_bytes() == b"the user's file" and not (tmp_path / "a.safetensors").exists()
