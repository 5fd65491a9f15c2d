"""`toolkit label`: homography warps, homographic adaptation, the resumable label store, bad input."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import toolkit.cmd_label as cmd_label
from models.teachers import build_teacher
from toolkit.cli import main
from toolkit.training.adaptation import AdaptationConfig, adapted_heatmap
from toolkit.training.homographies import HomographyConfig, sample_homography, warp_images, warp_points
from toolkit.training.label_store import LabelStore

torch.set_num_threads(1)
SIZE = "64x96"


@pytest.fixture()
def image_folder(tmp_path: Path, shared_data: Path) -> Path:
    """Three real photos, linked (not copied) into a fresh folder."""
    folder = tmp_path / "images"
    folder.mkdir()
    for source in sorted((shared_data / "train_images" / "bsds500").glob("*.jpg"))[:3]:
        (folder / source.name).symlink_to(source)
    return folder


def label(images: Path, out: Path, teacher: str = "shi-tomasi", homographies: int = 3) -> int:
    return main(["label", "--teacher", teacher, "--images", str(images), "--out", str(out),
                 "--num-homographies", str(homographies), "--size", SIZE, "--device", "cpu"])


def read_items(store: Path) -> dict[str, np.ndarray]:
    return {p.stem: np.load(p)["keypoints"] for p in sorted((store / "items").glob("*.npz"))}


def test_warp_images_moves_a_dot_where_warp_points_says() -> None:
    generator = torch.Generator().manual_seed(3)
    homography = sample_homography(64, 96, HomographyConfig(), generator)
    image = torch.zeros(1, 1, 64, 96)
    image[0, 0, 30, 40] = 1.0
    warped = warp_images(image, homography[None])
    peak = torch.nonzero(warped[0, 0] == warped[0, 0].max())[0]
    expected = warp_points(torch.tensor([[40.0, 30.0]]), homography)[0]
    assert float(torch.dist(peak.flip(0).float(), expected)) <= 1.0
    back = warp_images(warped, torch.linalg.inv(homography)[None])
    assert torch.nonzero(back[0, 0] == back[0, 0].max())[0].tolist() == [30, 40]


def test_adaptation_is_the_teacher_itself_with_one_homography_and_close_with_many() -> None:
    teacher = build_teacher("shi-tomasi")
    image = torch.zeros(1, 1, 64, 96)
    image[..., 16:48, 24:72] = 1.0
    generator = torch.Generator().manual_seed(0)
    alone = adapted_heatmap(teacher, image, AdaptationConfig(num_homographies=1, size=(64, 96)), generator)
    assert torch.allclose(alone, teacher(image)[0, 0], atol=1e-4)
    averaged = adapted_heatmap(teacher, image, AdaptationConfig(num_homographies=12, size=(64, 96)), generator)
    corners = [(16, 24), (16, 71), (47, 24), (47, 71)]
    # Un-warping puts every warp's corner response back on the square's corners.
    for y, x in corners:
        assert float(averaged[y - 2 : y + 3, x - 2 : x + 3].max()) > 0.3
    assert float(averaged[30:34, 40:56].max()) < 0.05


def test_label_three_images_with_two_teachers(image_folder: Path, tmp_path: Path) -> None:
    results = {}
    for teacher in ("shi-tomasi", "alike-t"):
        out = tmp_path / teacher
        assert label(image_folder, out, teacher) == 0
        header = json.loads((out / "store.json").read_text())
        assert header["teacher"] == teacher and header["settings"]["num_homographies"] == 3
        index = json.loads((out / "index.json").read_text())
        assert sorted(index) == sorted(p.name for p in image_folder.iterdir())
        items = read_items(out)
        assert sorted(items) == sorted(index.values())
        for keypoints in items.values():
            assert 10 <= len(keypoints) <= 512
            assert keypoints[:, 0].min() >= 4 and keypoints[:, 0].max() <= 95 - 4
            assert keypoints[:, 1].min() >= 4 and keypoints[:, 1].max() <= 63 - 4
        results[teacher] = items
    first = sorted(results["alike-t"])[0]
    assert not np.array_equal(results["alike-t"][first], results["shi-tomasi"][first])


def test_interrupted_labelling_resumes_and_matches_a_clean_run(
    image_folder: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_label_image = cmd_label.label_image
    calls = {"n": 0}

    def dies_on_second_image(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_label_image(*args, **kwargs)

    monkeypatch.setattr(cmd_label, "label_image", dies_on_second_image)
    out = tmp_path / "resumed"
    assert label(image_folder, out) == 130
    assert len(read_items(out)) == 1 and not list((out / "items").glob(".tmp-*"))
    monkeypatch.setattr(cmd_label, "label_image", real_label_image)
    config = AdaptationConfig(num_homographies=3, size=(64, 96))
    summary = cmd_label.label_folder("shi-tomasi", image_folder, out, config, torch.device("cpu"), progress=False)
    assert (summary.labelled, summary.skipped, summary.unreadable) == (2, 1, 0)
    clean = tmp_path / "clean"
    assert label(image_folder, clean) == 0
    resumed_items, clean_items = read_items(out), read_items(clean)
    assert sorted(resumed_items) == sorted(clean_items)
    for key in clean_items:
        np.testing.assert_array_equal(resumed_items[key], clean_items[key])


def test_store_refuses_other_settings_or_teacher(image_folder: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "labels"
    assert label(image_folder, out) == 0
    capsys.readouterr()
    assert label(image_folder, out, homographies=5) == 2
    assert "other settings (num_homographies: 3 vs 5)" in capsys.readouterr().err
    assert label(image_folder, out, teacher="alike-t") == 2
    assert "teacher shi-tomasi" in capsys.readouterr().err
    assert LabelStore.open(out).settings["num_homographies"] == 3


def test_bad_input_is_one_line_and_exit_2(image_folder: Path, tmp_path: Path, capsys) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "a.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    (broken / "b.png").write_bytes(b"")
    cases = [
        (["--images", str(empty)], "no image files"),
        (["--images", str(tmp_path / "nowhere")], "image folder not found"),
        (["--images", str(broken)], "none of the 2 image files"),
        (["--images", str(image_folder), "--teacher", "orb"], "unknown teacher"),
        (["--images", str(image_folder), "--teacher", f"superpoint:{tmp_path / 'sp.pth'}"], "weight file not found"),
        (["--images", str(image_folder), "--size", "60x90"], "divisible by 8"),
    ]
    for extra, message in cases:
        args = ["label", "--teacher", "shi-tomasi", "--out", str(tmp_path / "out"), "--num-homographies", "2"]
        assert main(args + extra) == 2, extra
        last_line = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress bar, if any
        assert last_line.startswith("error: ") and message in last_line, last_line
    assert not (tmp_path / "out").exists()  # a failed first run leaves no empty label folder behind
    # A readable image among unreadable ones: skipped files are counted, the rest labelled.
    (broken / "good.jpg").symlink_to(next(image_folder.iterdir()))
    summary = cmd_label.label_folder(
        "shi-tomasi", broken, tmp_path / "mixed", AdaptationConfig(num_homographies=2, size=(64, 96)), torch.device("cpu"),
        progress=False,
    )
    assert (summary.labelled, summary.unreadable) == (1, 2)


def test_a_long_labelling_run_is_announced(image_folder: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    # The cost scales with --num-homographies: the README's tour once started a 24 h run without a word.
    monkeypatch.setattr(cmd_label, "LONG_RUN_S", 0.0)
    monkeypatch.setattr(cmd_label, "ESTIMATE_AFTER", 1)
    assert label(image_folder, tmp_path / "store", homographies=2) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "to label 2 more images at" in warnings[0] and "(2 teacher runs an image)" in warnings[0]
    assert cmd_label.cost_warning(50.0, 1750, cmd_label.AdaptationConfig(num_homographies=100), torch.device("cpu")) \
        .startswith("warning: about 24h18m to label 1750 more images at 0.02 images/s on cpu")
