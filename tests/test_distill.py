"""The distill recipe: its losses on cases with known answers, the teacher cache (descriptors, resume), the
multi-scale pairs' geometry, and a short real training run end to end."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from toolkit.cli import main
from toolkit.training.adaptation import AdaptationConfig
from toolkit.training.distill_losses import DistillLossConfig, distillation_loss, info_nce_loss
from toolkit.training.distill_pairs import DistillPairs, MultiScaleConfig, sample_map
from toolkit.training.homographies import HomographyConfig, points_inside, warp_points
from toolkit.training.label_store import LabelStore
from toolkit.training.losses import cell_centres
from toolkit.training.pairs import load_labelled_images

torch.set_num_threads(1)


def test_distillation_loss_is_one_minus_cosine_over_valid_cells() -> None:
    teacher = F.normalize(torch.randn(2, 16, 3, 4), dim=1)
    valid = torch.ones(2, 3, 4, dtype=torch.bool)
    assert distillation_loss(teacher, teacher, valid) == pytest.approx(0.0, abs=1e-6)
    assert distillation_loss(-teacher, teacher, valid) == pytest.approx(2.0, abs=1e-6)
    # Only valid cells count: make half the cells opposite but invalid.
    student = teacher.clone()
    student[:, :, :, 2:] *= -1
    valid[:, :, 2:] = False
    assert distillation_loss(student, teacher, valid) == pytest.approx(0.0, abs=1e-6)


def test_info_nce_has_the_closed_form_value_for_orthogonal_descriptors() -> None:
    """Identity homography, one-hot descriptors per cell: every positive has cosine 1, every negative 0,
    so each row's cross-entropy is log(1 + (N - 1) exp(-1 / T))."""
    height, width = 3, 4
    cells = height * width
    descriptors = torch.eye(cells).reshape(1, cells, height, width)
    config = DistillLossConfig(temperature=0.5, nce_cells=cells)
    # Cells whose centre is >= 4 px from the border all take part (border=4 in the loss): all 12 here.
    valid = torch.ones(1, height, width, dtype=torch.bool)
    loss = info_nce_loss(descriptors, descriptors, torch.eye(3)[None], valid, config)
    usable = int(points_inside(cell_centres(height, width), (height * 8, width * 8), border=4).sum())
    assert loss.item() == pytest.approx(math.log(1 + (usable - 1) * math.exp(-1 / 0.5)), rel=1e-5)
    # Swapping b's descriptors between cells makes the positives wrong: the loss must grow.
    shuffled = descriptors.reshape(1, cells, -1)[:, :, torch.roll(torch.arange(cells), 1)].reshape_as(descriptors)
    assert info_nce_loss(descriptors, shuffled, torch.eye(3)[None], valid, config) > loss + 1.0


def test_sample_map_reads_cell_centres_exactly() -> None:
    descriptors = F.normalize(torch.randn(8, 3, 5), dim=0)
    centres = cell_centres(3, 5)
    sampled = sample_map(descriptors, centres)
    assert torch.allclose(sampled, descriptors.reshape(8, -1).T, atol=1e-5)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """Five real photos (linked) with alike-t keypoints and descriptors at 64x96."""
    root = tmp_path_factory.mktemp("distill")
    images = root / "images"
    images.mkdir()
    for source in sorted((shared_data / "train_images" / "coco128").glob("*.jpg"))[:5]:
        (images / source.name).symlink_to(source)
    code = main(["label", "--teacher", "alike-t", "--images", str(images), "--out", str(root / "labels"), "--num-homographies",
                 "1", "--size", "64x96", "--max-keypoints", "200", "--nms-radius", "2", "--descriptors", "--threads", "1"])
    assert code == 0
    return images, root / "labels"


def test_teacher_cache_holds_descriptors_and_resumes(cache, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    images, labels = cache
    store = LabelStore.open(labels)
    assert store.descriptor_stride == 4 and store.settings["descriptor_stride"] == 4
    first = json.loads((labels / "index.json").read_text())
    assert len(first) == 5
    maps = {sha: store.get_descriptors(sha) for sha in first.values()}
    for descriptors in maps.values():
        assert descriptors.shape == (64, 16, 24) and descriptors.dtype == np.float16  # alike-t: 64-d, 64x96 / 4
        norms = np.linalg.norm(descriptors.astype(np.float32), axis=0)
        assert np.allclose(norms, 1.0, atol=2e-2)

    # An interrupted run (killed after two images) resumes: the rerun labels only the other three, with the
    # same results as the straight run.
    import toolkit.cmd_label as cmd_label

    real = cmd_label.label_image_with_descriptors
    calls = {"n": 0}

    def dies_on_the_third(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(cmd_label, "label_image_with_descriptors", dies_on_the_third)
    out = tmp_path / "labels"
    args = ["label", "--teacher", "alike-t", "--images", str(images), "--out", str(out), "--num-homographies", "1",
            "--size", "64x96", "--max-keypoints", "200", "--nms-radius", "2", "--descriptors", "--threads", "1"]
    assert main(args) == 130
    assert len(list((out / "items").glob("*.npz"))) == 2
    monkeypatch.setattr(cmd_label, "label_image_with_descriptors", real)
    assert main(args) == 0
    resumed = LabelStore.open(out)
    for sha, descriptors in maps.items():
        assert np.array_equal(resumed.get_descriptors(sha), descriptors)


def test_pairs_carry_teacher_descriptors_and_labels_to_the_same_scene_points(cache) -> None:
    images, labels = cache
    store = LabelStore.open(labels)
    records, _ = load_labelled_images(images, store)
    scales = MultiScaleConfig(sizes=[[32, 48], [64, 96]], max_zoom=1.5)
    pairs = DistillPairs(records, store, scales, HomographyConfig(), None, seed=3, ids_per_step=2)
    for sample_id in range(6):
        item = pairs[sample_id]
        height, width = item["labels_a"].shape
        assert (height * 8, width * 8) == ((32, 48) if (sample_id // 2) % 2 == 0 else (64, 96))
        centres = cell_centres(height, width)
        warped = warp_points(centres, item["homography"])
        inside = points_inside(warped, (height * 8, width * 8), border=8)
        a = item["teacher_a"].reshape(item["teacher_a"].shape[0], -1).T[inside]
        b = sample_map(item["teacher_b"], warped[inside])
        # The teacher's descriptor of a cell of a is closest to its descriptor at the same scene point in b
        # (chance would be 1 / len(b)): the views, the homography and the sampling agree.
        same = (a * b).sum(1).mean()
        nearest = (a @ b.T).argmax(dim=1)
        accuracy = (nearest == torch.arange(len(b))).float().mean()
        assert same > 0.8 and accuracy > 0.5, (float(same), float(accuracy), len(b))


def test_images_kept_finer_show_the_same_scene_with_real_detail(cache) -> None:
    # `scales.detail` keeps images at 2x the label size: the same sample id must show the same scene at the
    # same place with the same labels (only sharper where a view enlarges the image).
    images, labels = cache
    store = LabelStore.open(labels)
    coarse, _ = load_labelled_images(images, store)
    fine, _ = load_labelled_images(images, store, detail=2.0)
    assert fine[0].gray.shape == (128, 192) and coarse[0].gray.shape == (64, 96)
    scales = MultiScaleConfig(sizes=[[64, 96]], max_zoom=2.5)
    pairs = [DistillPairs(records, store, scales, HomographyConfig(), None, seed=5, ids_per_step=1)
             for records in (coarse, fine)]
    sharper = 0
    for sample_id in range(6):
        a, b = pairs[0][sample_id], pairs[1][sample_id]
        for key in ("labels_a", "labels_b", "valid_b", "teacher_a", "homography"):
            assert torch.equal(a[key], b[key]), key
        view, finer = a["image_a"][0].numpy(), b["image_a"][0].numpy()
        energy = [float(np.abs(np.diff(v, axis=1)).mean()) for v in (view, finer)]
        sharper += energy[1] > energy[0]
        # Blurred alike (the fine view has detail the coarse one lacks), they agree best where unshifted.
        view, finer = (cv2.GaussianBlur(v, (0, 0), 1.5) for v in (view, finer))
        error = {(dy, dx): np.abs(view[4 + dy : -4 + dy, 4 + dx : -4 + dx] - finer[4:-4, 4:-4]).mean()
                 for dy in (-1, 0, 1) for dx in (-1, 0, 1)}
        nearest_shift = min(value for shift, value in error.items() if shift != (0, 0))
        assert error[(0, 0)] < 0.7 * nearest_shift, error
    assert sharper >= 4  # most views enlarge the image: the finer source shows more structure


def test_a_short_distill_run_trains_and_picks_the_best_by_matching_score(cache, tmp_path: Path) -> None:
    images, labels = cache
    config = {"recipe": "distill", "device": "cpu", "threads": 1, "log_every": 1, "validate_every": 2, "checkpoint_every": 2,
              "val_fraction": 0.2, "warmup_steps": 1, "scales": {"sizes": [[32, 48], [64, 96]]},
              "model": {"widths": [8, 16, 32, 32], "blocks": [0, 1, 1, 1], "head_channels": 32, "descriptor_dim": 64,
                        "pixel_head_channels": 16}}
    (tmp_path / "c.json").write_text(json.dumps(config))
    run = tmp_path / "run"
    assert main(["train", "--images", str(images), "--labels", str(labels), "--config", str(tmp_path / "c.json"),
                 "--steps", "4", "--batch", "2", "--out", str(run)]) == 0
    with (run / "val.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [int(r["step"]) for r in rows] == [2, 4]
    for row in rows:
        assert 0.0 <= float(row["matching_score"]) <= 1.0 and 0.0 <= float(row["nn_map"]) <= 1.0
    with (run / "log.csv").open() as file:
        log = list(csv.DictReader(file))
    assert all(math.isfinite(float(r["loss"])) for r in log)
    assert float(log[0]["lr"]) < float(log[1]["lr"]) or float(log[1]["lr"]) > float(log[-1]["lr"])  # warm-up, then decay
    assert (run / "best.safetensors").is_file() and (run / "val.png").is_file()

    # A fine-tune starts from that run's weights and projection with a fresh schedule: at a vanishing lr the
    # new run's weights are the old run's, and its first descriptor loss is the old run's level, not a restart.
    source = torch.load(run / "train_state.pt", weights_only=True)
    tune = {**config, "init": str(run), "lr": 1e-12, "validate_every": 100, "checkpoint_every": 100}
    (tmp_path / "t.json").write_text(json.dumps(tune))
    assert main(["train", "--images", str(images), "--labels", str(labels), "--config", str(tmp_path / "t.json"),
                 "--steps", "1", "--batch", "2", "--out", str(tmp_path / "tuned")]) == 0
    tuned = torch.load(tmp_path / "tuned" / "train_state.pt", weights_only=True)
    assert tuned["step"] == 1
    learned = [name for name in source["model"] if "running_" not in name and "num_batches" not in name]  # BN stats move
    assert len(learned) > 10
    for name in learned:
        value = source["model"][name]
        assert torch.allclose(tuned["model"][name].float(), value.float(), atol=1e-6), name
    for name, value in source["projection"].items():
        assert torch.allclose(tuned["projection"][name], value, atol=1e-6), name


def test_init_from_a_mismatched_model_is_one_line(cache, tmp_path: Path, capsys) -> None:
    images, labels = cache
    from models.checkpoint import build_model, save_checkpoint

    save_checkpoint(build_model("featurenet", {"widths": [8, 16, 32, 32], "descriptor_dim": 64}), tmp_path / "small.safetensors")
    (tmp_path / "c.json").write_text(json.dumps({"init": str(tmp_path / "small.safetensors"), "device": "cpu"}))
    assert main(["train", "--images", str(images), "--labels", str(labels), "--config", str(tmp_path / "c.json"),
                 "--steps", "1", "--threads", "1", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot initialise") and "do not match" in err[0]
    assert not (tmp_path / "r").exists()


def test_distill_refuses_labels_without_descriptors(tmp_path: Path, shared_data: Path, capsys) -> None:
    images = tmp_path / "images"
    images.mkdir()
    for source in sorted((shared_data / "train_images" / "coco128").glob("*.jpg"))[:3]:
        (images / source.name).symlink_to(source)
    assert main(["label", "--teacher", "shi-tomasi", "--images", str(images), "--out", str(tmp_path / "l"),
                 "--num-homographies", "1", "--size", "32x48", "--max-keypoints", "100"]) == 0
    capsys.readouterr()
    assert main(["train", "--images", str(images), "--labels", str(tmp_path / "l"), "--out", str(tmp_path / "r"),
                 "--steps", "1", "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--descriptors" in err[0]


def test_a_run_is_fitted_to_its_minutes_from_the_pace_of_its_measured_steps():
    import time

    from toolkit.compression.distill import steps_within

    now = time.perf_counter()
    # began 10 s ago, 20 steps measured over the last 8 s: 0.4 s a step; 50 s of a 1-minute budget left
    total, pace = steps_within(1.0, 10_000, 25, now - 10.0, now - 8.0, 20)
    assert abs(pace - 0.4) < 0.01 and 145 <= total <= 150
    assert steps_within(1.0, 100, 25, now - 10.0, now - 8.0, 20)[0] == 100  # never beyond the step cap
    assert steps_within(0.1, 10_000, 25, now - 10.0, now - 8.0, 20)[0] == 26  # budget spent: stop after this step
