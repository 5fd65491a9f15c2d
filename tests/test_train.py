"""`toolkit train`: the loss falls, --resume reproduces an uninterrupted run, a 2-process gloo DDP step,
and every bad input is a one-line error with exit code 2 that loses nothing."""
from __future__ import annotations

import csv
import json
import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from safetensors.torch import load_file

import toolkit.training.trainer as trainer
from models.checkpoint import load_checkpoint
from toolkit.cli import main
from toolkit.training.adaptation import AdaptationConfig
from toolkit.training.augment import AugmentConfig, motion_blur, photometric_augment, simulate_low_light
from toolkit.training.homographies import HomographyConfig, warp_points
from toolkit.training.label_store import LabelStore
from toolkit.training.losses import LossConfig, descriptor_loss
from toolkit.training.pairs import WarpedPairs, cell_labels, load_labelled_images
from toolkit.training.trainer import config_from_dict, resolve_config, train

torch.set_num_threads(1)
# Small network and frequent logging keep every run here to a few seconds on one CPU thread.
SMALL = {"recipe": "paper", "device": "cpu", "log_every": 1, "lr": 1e-3, "val_fraction": 0.2, "model": {"widths": [8, 16, 32, 32], "blocks": [0, 1, 1, 1],
         "head_channels": 32, "descriptor_dim": 64}}


@pytest.fixture(scope="module")
def labelled(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """Six real photos (linked) and their Shi-Tomasi labels at 64x96."""
    root = tmp_path_factory.mktemp("train")
    images = root / "images"
    images.mkdir()
    for source in sorted((shared_data / "train_images" / "coco128").glob("*.jpg"))[:6]:
        (images / source.name).symlink_to(source)
    from toolkit.cmd_label import label_folder

    config = AdaptationConfig(num_homographies=3, size=(64, 96))
    label_folder("shi-tomasi", images, root / "labels", config, torch.device("cpu"), progress=False)
    return images, root / "labels"


def write_config(path: Path, **overrides) -> Path:
    path.write_text(json.dumps({**SMALL, **overrides}))
    return path


def train_cli(images: Path, labels: Path, run: Path, *extra: str) -> int:
    return main(["train", "--images", str(images), "--labels", str(labels), "--out", str(run), *extra])


def losses(run: Path) -> list[float]:
    with (run / "log.csv").open() as file:
        return [float(row["loss"]) for row in csv.DictReader(file)]


def test_cell_labels_and_warped_pair_labels_agree(labelled) -> None:
    labels = cell_labels(torch.tensor([[10.0, 3.0], [13.0, 4.0], [95.0, 63.0]]), torch.tensor([0.5, 0.9, 0.2]), (64, 96))
    assert labels.shape == (8, 12) and int(labels[0, 1]) == 4 * 8 + 5  # the better of two keypoints in a cell
    assert int(labels[7, 11]) == 63 and int((labels == 64).sum()) == 8 * 12 - 2
    images, store = labelled
    records, _ = load_labelled_images(images, LabelStore.open(store))
    pairs = WarpedPairs(records, (64, 96), HomographyConfig(), None, seed=0)
    sample = pairs[3]
    record = records[pairs.image_index(3)]
    assert torch.equal(sample["image_a"], pairs[3]["image_a"])  # a sample is a function of its id
    moved = warp_points(torch.from_numpy(record.keypoints), sample["homography"])
    inside = (moved[:, 0] >= 0) & (moved[:, 0] <= 95) & (moved[:, 1] >= 0) & (moved[:, 1] <= 63)
    expected = cell_labels(moved[inside], torch.from_numpy(record.scores)[inside], (64, 96))
    assert torch.equal(sample["labels_b"], expected)
    assert int((sample["labels_a"] < 64).sum()) > 10


def test_augmentation_darkens_blurs_and_is_reproducible() -> None:
    image = torch.full((1, 64, 96), 0.6)
    image[:, :, 48:] = 0.9
    config = AugmentConfig(lowlight_rebrighten_prob=0.0)
    dark = simulate_low_light(image, config, torch.Generator().manual_seed(1))
    assert float(dark.mean()) < 0.5 * float(image.mean())
    assert float(dark[:, :, :40].std()) > 0.0  # shot and read noise on a flat region
    line = torch.zeros(1, 33, 33)
    line[0, 16, 16] = 1.0
    blurred = motion_blur(line, 9, 0.0)  # horizontal shake spreads a dot along its row only
    assert abs(float(blurred.sum()) - 1.0) < 1e-5 and float(blurred[0, 16].sum()) > 0.99
    first = photometric_augment(image, AugmentConfig(), torch.Generator().manual_seed(5))
    again = photometric_augment(image, AugmentConfig(), torch.Generator().manual_seed(5))
    assert torch.equal(first, again) and not torch.equal(first, image)


def test_descriptor_loss_prefers_matching_descriptors() -> None:
    torch.manual_seed(0)
    descriptors = torch.nn.functional.normalize(torch.randn(1, 16, 4, 6), dim=1)
    shift = torch.tensor([[[1.0, 0.0, 8.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])  # one cell to the right
    shifted = torch.roll(descriptors, 1, dims=3)
    valid = torch.ones(1, 4, 6, dtype=torch.bool)
    exact = LossConfig(correspondence_px=4.0)  # only the cell the shift lands on is positive
    matched, positives = descriptor_loss(descriptors, shifted, shift, valid, exact)
    unmatched, _ = descriptor_loss(descriptors, descriptors, shift, valid, exact)
    assert float(matched) < 0.5 * float(unmatched)
    assert abs(float(positives) - 4 * 5 / (24 * 24)) < 1e-6


def test_deformable_layer_stays_float32_under_autocast() -> None:
    torch.manual_seed(0)
    model = trainer.build_model("featurenet", {**SMALL["model"]}).eval()
    image = torch.rand(2, 1, 64, 96)
    with torch.no_grad():
        reference = model(image)["logits"]
        assert trainer.keep_deformable_in_float32(model) == 1
        # CPU autocast (bfloat16) stands in for CUDA float16: both break the deformable gather indices.
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = model(image)["logits"].float()
    assert torch.allclose(mixed, reference, atol=0.15 * float(reference.abs().max()))


def test_short_run_loss_falls_and_writes_a_run_folder(labelled, tmp_path: Path) -> None:
    images, labels = labelled
    run = tmp_path / "run"
    config = write_config(tmp_path / "c.json", checkpoint_every=10, validate_every=15)
    assert train_cli(images, labels, run, "--config", str(config), "--steps", "30", "--batch", "2") == 0
    curve = losses(run)
    assert len(curve) == 30
    assert sum(curve[-5:]) / 5 < 0.8 * sum(curve[:5]) / 5
    for name in ("config.json", "train_state.pt", "last.safetensors", "best.safetensors", "loss.png", "val.csv"):
        assert (run / name).is_file(), name
    # the run says what cpu_bf16 came to on this CPU: bfloat16 only where it computes it natively
    from toolkit.training.cpu_precision import cpu_computes_bf16

    precision = json.loads((run / "config.json").read_text())["cpu_precision"]
    assert precision == ("bfloat16" if cpu_computes_bf16() else "float32")
    model, info = load_checkpoint(run / "last.safetensors")
    assert info.arch == "featurenet" and info.metadata["step"] == 30 and info.config["descriptor_dim"] == 64
    with (run / "val.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [int(r["step"]) for r in rows] == [15, 30]
    assert all(0.0 <= float(r["repeatability"]) <= 1.0 and 0.0 <= float(r["matching_score"]) <= 1.0 for r in rows)
    with torch.no_grad():
        out = model(torch.rand(1, 1, 64, 96))
    assert out["logits"].shape == (1, 65, 8, 12) and out["descriptors"].shape == (1, 64, 8, 12)


def test_resume_after_interruption_gives_the_uninterrupted_weights(
    labelled, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    images, labels = labelled
    config = write_config(tmp_path / "c.json", checkpoint_every=2, validate_every=3)
    args = ("--config", str(config), "--steps", "6", "--batch", "2")
    straight = tmp_path / "straight"
    assert train_cli(images, labels, straight, *args) == 0

    real_loss = trainer.superpoint_loss
    calls = {"n": 0}

    def interrupted_in_step_five(*a, **k):
        calls["n"] += torch.is_grad_enabled()  # training steps only: validation runs the loss without gradients
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return real_loss(*a, **k)

    monkeypatch.setattr(trainer, "superpoint_loss", interrupted_in_step_five)
    broken = tmp_path / "broken"
    assert train_cli(images, labels, broken, *args) == 130
    assert torch.load(broken / "train_state.pt", weights_only=True)["step"] == 4  # the last good checkpoint
    monkeypatch.setattr(trainer, "superpoint_loss", real_loss)
    assert train_cli(images, labels, broken, "--resume") == 0

    expected, resumed = load_file(straight / "last.safetensors"), load_file(broken / "last.safetensors")
    assert expected.keys() == resumed.keys()
    for key in expected:
        assert torch.equal(expected[key], resumed[key]), key
    assert losses(broken) == losses(straight)  # log rows past the checkpoint were replayed, not duplicated


def _ddp_worker(rank: int, port: int, images: str, labels: str, run: str, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2", LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    config = config_from_dict({**SMALL, "checkpoint_every": 1, "validate_every": 1})
    config = resolve_config(Path(run), False, config, steps=1, batch=2)
    result = train(config, images, labels, run)
    torch.save({k: v.clone() for k, v in result["model"].state_dict().items()}, Path(out) / f"rank{rank}.pt")


def test_two_process_gloo_ddp_step_keeps_replicas_identical(labelled, tmp_path: Path) -> None:
    images, labels = labelled
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    run = tmp_path / "ddp"
    mp.spawn(_ddp_worker, args=(port, str(images), str(labels), str(run), str(tmp_path)), nprocs=2, join=True)
    rank0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    rank1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    torch.manual_seed(0)
    network = trainer.build_model("featurenet", SMALL["model"])
    initial = network.state_dict()
    parameters = [name for name, _ in network.named_parameters()]
    assert sum(not torch.equal(rank0[k], initial[k]) for k in parameters) > len(parameters) // 2  # the step moved them ...
    for key in parameters:
        assert torch.equal(rank0[key], rank1[key]), key  # ... identically on both ranks (averaged gradients)
    # BatchNorm statistics are per rank (DDP broadcasts rank 0's before each forward); rank 0 saves its own.
    assert load_file(run / "last.safetensors").keys() == rank0.keys()  # only rank 0 wrote the run folder


def test_bad_input_is_one_line_exit_2_and_loses_nothing(labelled, tmp_path: Path, capsys) -> None:
    images, labels = labelled
    config = write_config(tmp_path / "c.json", checkpoint_every=2, validate_every=2)
    empty, broken, few = tmp_path / "empty", tmp_path / "broken", tmp_path / "few"
    for folder in (empty, broken, few):
        folder.mkdir()
    (broken / "x.jpg").write_bytes(b"garbage")
    (few / "one.jpg").symlink_to(next(images.iterdir()))
    other = tmp_path / "other.jpg"  # an image the labels were not made from
    other.write_bytes((next(images.iterdir())).read_bytes()[:-200] + b"\xff\xd9")
    unlabelled = tmp_path / "unlabelled"
    unlabelled.mkdir()
    for path in images.iterdir():
        (unlabelled / path.name).symlink_to(path)
    (unlabelled / "other.jpg").symlink_to(other)
    fake_store = tmp_path / "fake_labels"
    fake_store.mkdir()
    (fake_store / "store.json").write_text(json.dumps({"format": "edgefeat-labels/0", "settings": {}}))
    run = tmp_path / "run"
    cases = [
        ((empty, labels), "no image files"),
        ((broken, labels), "none of the 1 image files"),
        ((few, labels), "at least 2 usable images"),
        ((unlabelled, labels), "1 of 7 images"),
        ((images, tmp_path / "nolabels"), "not a label folder"),
        ((images, fake_store), "is not an edgefeat-labels/1 label folder"),
    ]
    for (folder, store), message in cases:
        assert train_cli(folder, store, run, "--config", str(config), "--steps", "2") == 2, message
        last_line = capsys.readouterr().err.strip().splitlines()[-1]
        assert last_line.startswith("error: ") and message in last_line, last_line
    bad_model = write_config(tmp_path / "bad_model.json", model={"widths": [8, 16]})
    assert train_cli(images, labels, run, "--config", str(bad_model)) == 2
    assert "do not fit arch featurenet" in capsys.readouterr().err
    unknown = write_config(tmp_path / "unknown.json", augment={"sparkle": 1.0})
    assert train_cli(images, labels, run, "--config", str(unknown)) == 2
    assert "unknown config key augment.sparkle" in capsys.readouterr().err
    assert not run.exists()
    # Unreadable files among good ones are skipped and counted, not fatal.
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for path in images.iterdir():
        (mixed / path.name).symlink_to(path)
    (mixed / "corrupt.jpg").write_bytes(b"\xff\xd8\xff garbage")
    mixed_config = resolve_config(tmp_path / "mixed_run", False, config_from_dict(SMALL), steps=1, batch=1)
    result = train(mixed_config, str(mixed), str(labels), tmp_path / "mixed_run")
    assert (result["unreadable"], result["train_images"] + result["val_images"]) == (1, 6)
    assert train_cli(images, labels, tmp_path / "nothing", "--resume") == 2
    assert "cannot resume" in capsys.readouterr().err

    # A good run, then: no --resume over it, a corrupt checkpoint on --resume.
    assert train_cli(images, labels, run, "--config", str(config), "--steps", "2", "--batch", "2") == 0
    assert train_cli(images, labels, run, "--config", str(config), "--steps", "4") == 2
    assert "already holds a training run" in capsys.readouterr().err
    good_weights = (run / "last.safetensors").read_bytes()
    (run / "train_state.pt").write_bytes(b"PK\x03\x04 truncated")
    assert train_cli(images, labels, run, "--resume", "--steps", "4") == 2
    assert "is corrupt or unreadable" in capsys.readouterr().err.strip().splitlines()[-1]
    assert (run / "last.safetensors").read_bytes() == good_weights
    assert train_cli(images, labels, run, "--resume", "--batch", "3") == 2
    assert "cannot change --batch" in capsys.readouterr().err
