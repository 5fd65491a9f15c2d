"""Distillation across lighting (`toolkit.compression.dark_distill`): the student sees darkened crops and learns
the teacher's heads on the clean ones."""
from __future__ import annotations

import copy
import subprocess
import sys

import numpy as np
import pytest
import torch

from tests.test_slim import SIZE, teacher  # noqa: F401 (the small calibrated teacher, a module fixture)
from toolkit.compression.dark_distill import (DarkDistillConfig, distill_dark, held_out_loss, make_pair_batch,
                                              random_darkening)
from toolkit.compression.images import find_images
from toolkit.compression.slim import _load_gray
from vo_runtime.lowlight import GlobalDark, OnboardLight

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def images(shared_data) -> list[np.ndarray]:
    return _load_gray(find_images(shared_data / "train_images" / "coco128")[:12])


def test_darkenings_are_drawn_around_both_presets():
    rng = np.random.default_rng(0)
    drawn = [random_darkening(rng, 0.5) for _ in range(200)]
    onboard = [d for d in drawn if isinstance(d, OnboardLight)]
    dark = [d for d in drawn if isinstance(d, GlobalDark)]
    assert 70 < len(onboard) < 130 and len(onboard) + len(dark) == 200
    assert min(d.gamma for d in dark) < 2.0 < max(d.gamma for d in dark)  # the dark preset's gamma is inside
    assert min(d.gain for d in dark) < 0.3 < max(d.gain for d in dark)
    assert min(d.photons_per_level for d in onboard) < 4.0 < max(d.photons_per_level for d in onboard)
    assert all(isinstance(d, GlobalDark) for d in (random_darkening(rng, 0.0) for _ in range(20)))


def test_pairs_are_a_function_of_the_step_and_the_student_sees_them_darker(images):
    config = DarkDistillConfig(batch=6, sizes=[(48, 64), (64, 96)], dark_share=1.0)
    clean, seen = make_pair_batch(images, 3, config)
    again_clean, again_seen = make_pair_batch(images, 3, config)
    assert torch.equal(clean, again_clean) and torch.equal(seen, again_seen)
    assert clean.shape == seen.shape == (6, 1, 64, 96)  # step 3 of two sizes: the second
    assert all(float(s.mean()) < float(c.mean()) for s, c in zip(seen, clean))  # every crop darkened
    assert 0.0 <= float(seen.min()) and float(seen.max()) <= 1.0
    light = DarkDistillConfig(batch=6, sizes=[(48, 64)], dark_share=0.0)
    clean, seen = make_pair_batch(images, 3, light)
    assert torch.equal(clean, seen)  # no darkening: the student sees what the teacher sees


def test_the_student_learns_to_see_the_clean_heads_in_the_dark(teacher, images):
    student = copy.deepcopy(teacher)
    config = DarkDistillConfig(steps=40, batch=4, lr=2e-3, sizes=[SIZE], seed=1, dark_share=0.5)
    dark_before, clean_before = held_out_loss(student, teacher, images, config, batches=2)  # all darkened
    assert clean_before < 1e-6 < dark_before  # the same weights: equal on clean crops, apart on dark ones
    sampling = teacher.deform.strategy
    rows = distill_dark(student, teacher, images, config, log=lambda _text: None)
    assert teacher.deform.strategy == sampling and student.deform.strategy == sampling
    dark_after, clean_after = held_out_loss(student, teacher, images, config, batches=2)
    assert len(rows) == 2 and all(np.isfinite(row["loss"]) for row in rows)
    assert dark_after < 0.85 * dark_before, (dark_before, dark_after)
    assert clean_after < 0.7 * dark_after  # the clean half keeps good light's heads (all dark: 1.06x measured)
    assert not student.training
    for name, value in teacher.state_dict().items():  # BatchNorm's running statistics stay the start's
        if "running" in name:
            assert torch.equal(student.state_dict()[name], value), name


def test_the_command_refuses_bad_input_and_never_replaces_a_foreign_file(shared_data, tmp_path):
    foreign = tmp_path / "mine.safetensors"
    foreign.write_bytes(b"the user's file")
    images = str(shared_data / "train_images" / "coco128")
    for argv, message in ((["--images", images, "-o", str(foreign)], "never replaced"),
                          (["--images", images, "-o", str(tmp_path / "a.pt")], ".safetensors"),
                          (["--images", images, "-o", str(tmp_path / "a.safetensors"), "--dark-share", "2"],
                           "--dark-share")):
        done = subprocess.run([sys.executable, "-m", "toolkit.compression.dark_distill", *argv, "--steps", "1"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and done.stderr.strip().startswith("error:") and message in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
    assert foreign.read_bytes() == b"the user's file" and not (tmp_path / "a.safetensors").exists()
