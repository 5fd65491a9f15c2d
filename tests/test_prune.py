"""`toolkit prune`: DepGraph channel pruning with the deformable conv's custom pruner, distillation,
checkpoint round trip, export parity, and the bad inputs."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from export.artefact import ExportOptions, export_artefact
from models.checkpoint import load_checkpoint, save_checkpoint
from models.featurenet import FeatureNet, FeatureNetConfig
from toolkit.cli import main
from toolkit.compression.distill import DistillConfig, distill
from toolkit.compression.images import load_images
from toolkit.compression.prune import (count_macs, count_parameters, kept_channels, prune_channels,
                                       ratio_for_target_macs)
from toolkit.compression.proxy import calibrated_random_featurenet
from toolkit.compression.report import torch_drift
from toolkit.compression.workflow import PruneOptions, prune_checkpoint
from vo_runtime.artefact import verify_artefact

torch.set_num_threads(1)
SIZE = (64, 96)
SMALL = FeatureNetConfig(widths=[16, 24, 32, 64], blocks=[0, 1, 1, 2], head_channels=64, descriptor_dim=64)


@pytest.fixture(scope="module")
def images(shared_data) -> np.ndarray:
    return load_images(shared_data / "train_images", 8, SIZE)[0]


@pytest.fixture(scope="module")
def teacher(images) -> FeatureNet:
    # Random weights with image-calibrated BatchNorm: a measurable stand-in, not a trained model.
    return calibrated_random_featurenet(SMALL, images)


def widths(model: FeatureNet) -> list[int]:
    return [m.out_channels for m in model.modules() if isinstance(m, torch.nn.Conv2d)]


def test_kept_channels_rounds_to_multiples_of_8():
    assert kept_channels(128, 0.3) == 88  # 89.6 -> 88
    assert kept_channels(64, 0.3) == 48  # 44.8 -> 48
    assert kept_channels(16, 0.5) == 8
    assert kept_channels(8, 0.9) == 8  # narrower than one multiple: left alone
    assert kept_channels(24, 0.99) == 8  # never below one multiple


def test_prune_30_percent_distil_save_export_parity(teacher, images, shared_data, tmp_path):
    student = prune_channels(teacher, 0.3, SIZE)
    assert student.config.widths == [8, 16, 24, 48] and student.config.head_channels == 48
    assert count_parameters(student) < 0.7 * count_parameters(teacher)
    assert count_macs(student, SIZE) < count_macs(teacher, SIZE)
    assert count_parameters(teacher) == count_parameters(calibrated_random_featurenet(SMALL, images))  # teacher untouched
    # The deformable conv shrank as one unit; its 2*9 offset + 9 mask outputs and the heads' outputs did not.
    deform = student.deform
    assert deform.conv.in_channels == deform.conv.out_channels == deform.offset_dw.groups == deform.offset_pw.in_channels == 48
    assert deform.offset_pw.out_channels == 27
    assert student.detector[-1].out_channels == 65 and student.descriptor[-1].out_channels == 64
    # Depthwise convs shrank with the pointwise conv that feeds them.
    for block in [m for m in student.modules() if hasattr(m, "depthwise")]:
        assert block.depthwise.groups == block.depthwise.in_channels == block.depthwise.out_channels
    for width in widths(student):
        assert width in (27, 65, 64) or width % 8 == 0

    before = torch_drift(teacher, student, images[:4])
    result = distill(student, teacher, shared_data / "train_images",
                     DistillConfig(steps=4, batch=2, lr=1e-3, size=SIZE, images=8), progress=False)
    assert result.steps == 4 and np.isfinite(result.last_loss)
    after = torch_drift(teacher, student, images[:4])
    assert after.heatmap_mean_abs < before.heatmap_mean_abs  # distillation moved the student towards the teacher

    path = save_checkpoint(student, tmp_path / "pruned.safetensors", {"note": "test"})
    loaded, info = load_checkpoint(path)  # strict load from the config's new widths
    assert info.config["widths"] == [8, 16, 24, 48] and info.config["head_channels"] == 48
    with torch.no_grad():
        x = torch.from_numpy(images[:1])
        assert torch.allclose(loaded(x)["logits"], student(x)["logits"], atol=1e-5)
    for target in ("x86-cpu", "tx2"):  # export_artefact raises if onnxruntime and PyTorch disagree
        out = export_artefact(ExportOptions(target=target, output=tmp_path / target, checkpoint=path,
                                            input_size=SIZE, precision="fp32"), log=lambda _m: None)
        manifest = verify_artefact(out)
        assert manifest["parity"]["keypoints_identical"] >= 0.99
        assert manifest["model"]["config"]["widths"] == [8, 16, 24, 48]


def test_target_macs_finds_a_ratio_under_budget(teacher):
    full = count_macs(teacher, SIZE)
    search = ratio_for_target_macs(teacher, full // 2, SIZE, steps=5)
    assert 0.0 < search.ratio < 1.0 and search.macs <= full // 2
    assert count_macs(prune_channels(teacher, search.ratio, SIZE), SIZE) == search.macs


def test_cli_prune_writes_checkpoint_and_report(teacher, shared_data, tmp_path, capsys):
    checkpoint = save_checkpoint(teacher, tmp_path / "full.safetensors")
    out = tmp_path / "p50.safetensors"
    argv = ["prune", "--checkpoint", str(checkpoint), "--ratio", "0.5", "--steps", "2", "--batch", "2",
            "--size", "64x96", "--images", str(shared_data / "lowlight_pairs"), "-o", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "parameters" in printed and "MACs" in printed and "latency" in printed
    model, info = load_checkpoint(out)
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["after"]["parameters"] == count_parameters(model) < report["before"]["parameters"]
    assert report["after"]["macs"] < report["before"]["macs"]
    assert info.metadata["pruning"]["ratio"] == 0.5 and info.config["widths"] == model.config.widths
    for stage in ("before", "after"):  # toolkit eval metrics on the real pairs, before and after pruning
        summary = report["evaluation"][stage]
        assert summary["num_pairs"] > 0 and 0.0 <= summary["repeatability"] <= 1.0
        assert 0.0 <= summary["matching_score"] <= 1.0
    assert "repeatability (eval)" in printed
    assert main(argv) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err


def test_labels_add_the_training_loss(teacher, shared_data, tmp_path):
    images = shared_data / "lowlight_pairs" / "high"
    labels = tmp_path / "labels"
    assert main(["label", "--teacher", "shi-tomasi", "--images", str(images), "--out", str(labels),
                 "--num-homographies", "2", "--size", "64x96"]) == 0
    checkpoint = save_checkpoint(teacher, tmp_path / "full.safetensors")
    options = PruneOptions(checkpoint=checkpoint, output=tmp_path / "p.safetensors", ratio=0.3, images=images,
                           labels=labels, steps=2, batch=2, size=SIZE, timing_repeats=2, evaluate=False)
    with_labels = prune_checkpoint(options, log=lambda _m: None, progress=False)
    options.labels, options.output = None, tmp_path / "q.safetensors"
    without = prune_checkpoint(options, log=lambda _m: None, progress=False)
    assert with_labels.distillation.used_labels and not without.distillation.used_labels
    # The SuperPoint loss (cross-entropy over 65 classes, >= 0) comes on top of the distillation loss.
    assert with_labels.distillation.first_loss > without.distillation.first_loss + 1.0


def expect_error(capsys, argv: list[str], needle: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err
    assert needle in err, err


def test_bad_inputs_exit_2_with_one_line(teacher, tmp_path, capsys):
    checkpoint = str(save_checkpoint(teacher, tmp_path / "full.safetensors"))
    out = str(tmp_path / "out.safetensors")
    for ratio in ("0", "1", "1.5", "-0.2"):
        expect_error(capsys, ["prune", "--checkpoint", checkpoint, "--ratio", ratio, "-o", out], "must be in (0, 1)")
    empty = tmp_path / "empty"
    empty.mkdir()
    expect_error(capsys, ["prune", "--checkpoint", checkpoint, "--ratio", "0.3", "--images", str(empty), "-o", out], "no images")
    expect_error(capsys, ["prune", "--checkpoint", str(tmp_path / "nope.safetensors"), "--ratio", "0.3", "-o", out], "not found")
    expect_error(capsys, ["prune", "--checkpoint", checkpoint, "--target-macs", "10", "--size", "64x96", "-o", out],
                 "out of reach")
    assert not Path(out).exists()


@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_a_depthwise_deformable_conv_prunes_as_one_unit_and_exports(images, tmp_path, fraction):
    config = FeatureNetConfig(**{**SMALL.to_dict(), "deform_depthwise": True, "deform_fraction": fraction})
    teacher = calibrated_random_featurenet(config, images)
    student = prune_channels(teacher, 0.3, SIZE)
    deform = student.deform
    assert deform.conv.groups == deform.conv.in_channels == deform.conv.out_channels == deform.pointwise.in_channels == 48
    assert deform.pointwise.out_channels == 48 and deform.offset_dw.groups == 48 and deform.offset_pw.out_channels == 27
    path = save_checkpoint(student, tmp_path / "pruned-dw.safetensors")
    loaded, info = load_checkpoint(path)
    assert info.config["deform_depthwise"] is True and info.config["deform_fraction"] == fraction
    assert loaded.deform.deform_channels == (48 if fraction == 1.0 else 24)  # the split follows the pruned width
    with torch.no_grad():
        x = torch.from_numpy(images[:1])
        assert torch.allclose(loaded(x)["logits"], student(x)["logits"], atol=1e-5)
    for target in ("x86-cpu", "tx2"):  # DeformConv with group = C natively; the portable sampler on tx2
        out = export_artefact(ExportOptions(target=target, output=tmp_path / target, checkpoint=path,
                                            input_size=SIZE, precision="fp32"), log=lambda _m: None)
        assert verify_artefact(out)["parity"]["keypoints_identical"] >= 0.99
