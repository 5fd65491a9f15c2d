"""`toolkit eval synth`: the generator (deterministic, homographies as stated, no borders, darkness registered,
easy to hard), the bootstrap intervals on a known spread, the --write round trip and the one-line errors."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from toolkit.cli import main
from toolkit.evaluation.intervals import BootstrapSettings, bootstrap_mean_interval
from toolkit.evaluation.metrics import warp_points
from toolkit.evaluation.synth import SynthConfig, content_digest, generate_sequences
from toolkit.evaluation.synth_frames import find_frames
from toolkit.evaluation.synth_viewpoint import CaptureNoise, corner_motion

SMALL = (240, 320)  # rendered size of the sequences here: small and fast


def checkerboard(shape: tuple[int, int], square: int = 32) -> np.ndarray:
    """HxW uint8 board of grey levels 50 and 200 (no black anywhere), slightly blurred so corners are smooth
    saddles that cornerSubPix finds to a small fraction of a pixel."""
    rows, cols = np.indices(shape)
    board = np.where((rows // square + cols // square) % 2 == 0, 200, 50).astype(np.float32)
    return np.clip(np.rint(cv2.GaussianBlur(board, (0, 0), 0.8)), 0, 255).astype(np.uint8)


def texture(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """HxW uint8 smooth random texture (grey 30..230): no repeating pattern for phase correlation to confuse."""
    coarse = np.random.default_rng(seed).uniform(30, 230, (shape[0] // 8, shape[1] // 8)).astype(np.float32)
    return np.clip(cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC), 30, 230).astype(np.uint8)


def write_frames(folder: Path, images: dict[str, np.ndarray]) -> Path:
    folder.mkdir(parents=True)
    for name, image in images.items():
        cv2.imwrite(str(folder / name), image)
    return folder


def generate(folders: list[Path], **settings) -> list:
    return generate_sequences(find_frames(folders), SynthConfig(out_size=SMALL, **settings))


def test_same_seed_same_bytes_whatever_the_listing_order(tmp_path):
    first = write_frames(tmp_path / "a", {f"{i}.png": texture((300, 400), i) for i in range(3)})
    second = write_frames(tmp_path / "b", {"x.png": checkerboard((300, 500))})
    shutil.copy(first / "0.png", second / "copy_of_0.png")  # the same content twice is one frame
    digest = content_digest(generate([first, second], sequences=2))
    assert content_digest(generate([second, first], sequences=2)) == digest
    assert content_digest(generate([first, second], sequences=2, seed=1)) != digest
    assert len(find_frames([first, second])) == 4


CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)


def board_corners(image: np.ndarray) -> np.ndarray:
    """``[N, 2]`` sub-pixel checkerboard corners of an image, 10 px or more inside it."""
    found = cv2.goodFeaturesToTrack(image, 300, 0.1, 8)
    corners = cv2.cornerSubPix(image, found.astype(np.float32), (4, 4), (-1, -1), CRITERIA).reshape(-1, 2)
    return corners[np.all((corners > 10) & (corners < np.array([image.shape[1], image.shape[0]]) - 10), axis=1)]


def corner_offsets(image: np.ndarray, predicted: np.ndarray, window: int = 4) -> np.ndarray:
    """``[N, 2]`` px from each predicted corner to the corner cornerSubPix finds in ``image`` from there."""
    start = predicted.astype(np.float32).reshape(-1, 1, 2)
    return cv2.cornerSubPix(image, start.copy(), (window, window), (-1, -1), CRITERIA).reshape(-1, 2) - predicted


def test_viewpoint_homographies_map_checkerboard_corners_where_they_say(tmp_path):
    folder = write_frames(tmp_path / "board", {"board.png": checkerboard((480, 640))})
    (sequence,) = generate([folder], sequences=1, kinds=("viewpoint",))
    corners = board_corners(sequence.images[0])
    assert len(corners) > 40
    for target, homography in zip(sequence.images[1:], sequence.homographies):
        predicted = warp_points(corners, homography)
        inside = np.all((predicted > 12) & (predicted < np.array([SMALL[1], SMALL[0]]) - 12), axis=1)
        assert inside.sum() > 15
        error = np.linalg.norm(corner_offsets(target, predicted[inside]), axis=1)
        # the corner the target shows is where H_1_k puts it: a wrong pixel convention alone would be 0.1-0.5 px
        assert np.median(error) < 0.1 and error.max() < 1.0, (np.median(error), error.max())


@pytest.mark.parametrize("shape", [(480, 640), (200, 720), (560, 360)])  # 4:3, KITTI-wide, portrait
def test_viewpoint_targets_show_the_scene_not_a_border_and_go_easy_to_hard(tmp_path, shape):
    folder = write_frames(tmp_path / "board", {"board.png": checkerboard(shape, 24)})
    exact = CaptureNoise(gain=0.0, gamma=0.0, sigma=0.0)  # exact warps: a border would show as black
    for sequence in generate([folder], sequences=3, kinds=("viewpoint",), capture=exact):
        assert len(sequence.images) == 6 and all(image.shape == SMALL for image in sequence.images)
        assert min(int(image.min()) for image in sequence.images) >= 45  # the board's darkest grey is 50
        motion = [corner_motion(h, SMALL) for h in sequence.homographies]
        assert motion == sorted(motion) and motion[0] > 1.0 and motion[-1] > 3 * motion[0]


def test_darkness_stays_registered_and_gets_darker(tmp_path):
    folder = write_frames(tmp_path / "board", {"board.png": checkerboard((480, 640))})
    for sequence in generate([folder], sequences=3, kinds=("darkness",)):
        assert all(np.array_equal(h, np.eye(3)) for h in sequence.homographies)
        means = [float(image.mean()) for image in sequence.images]
        assert means == sorted(means, reverse=True) and means[-1] < 0.2 * means[0]
        corners = board_corners(sequence.images[0])
        for dark in sequence.images[1:]:
            # Smoothed against the noise, which still moves each corner by ~0.2 px; a shift would move them
            # all one way (the blur kernel of OnboardLight uncentred: 0.5 px), so the median offset is the test.
            offsets = corner_offsets(cv2.GaussianBlur(dark.astype(np.float32), (0, 0), 1.0), corners, 5)
            assert np.abs(np.median(offsets, axis=0)).max() < 0.08, np.median(offsets, axis=0)


def test_bootstrap_interval_of_a_known_spread():
    rng = np.random.default_rng(7)
    sigma, n, trials = 0.1, 400, 200
    covered, widths = 0, []
    for trial in range(trials):  # 200 data sets from N(0.5, 0.1): the 95 % interval covers 0.5 in ~95 % of them
        low, high = bootstrap_mean_interval([[v] for v in rng.normal(0.5, sigma, n)], BootstrapSettings(seed=trial))
        covered += low < 0.5 < high
        widths.append(high - low)
    assert 0.90 <= covered / trials <= 0.99
    assert np.mean(widths) == pytest.approx(2 * 1.96 * sigma / np.sqrt(n), rel=0.05)
    values = rng.normal(0.5, sigma, n)
    # The unit is the sequence: 50 sequences of five equal pairs spread like 50 values, not like 250.
    per_sequence = rng.normal(0.5, sigma, 50)
    low, high = bootstrap_mean_interval([[v] * 5 for v in per_sequence], BootstrapSettings(seed=3))
    assert (high - low) == pytest.approx(2 * 1.96 * per_sequence.std() / np.sqrt(50), rel=0.15)
    # NaN is undefined and left out, as the report's MLE leaves it out; all undefined: no interval.
    plain = bootstrap_mean_interval([[v] for v in values], BootstrapSettings(seed=3))
    with_nan = bootstrap_mean_interval([[v, float("nan")] for v in values], BootstrapSettings(seed=3))
    assert with_nan == pytest.approx(plain)
    assert bootstrap_mean_interval([[float("nan")]] * 4) is None
    assert bootstrap_mean_interval([[v] for v in values], BootstrapSettings(seed=3)) == plain  # seeded


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_write_round_trip_reads_back_the_same_numbers(tmp_path, capsys):
    folder = write_frames(tmp_path / "frames" / "rgb", {f"{i}.png": texture((300, 400), i) for i in range(3)})
    common = ["--model", "orb", "--max-keypoints", "300", "--size", "120x160"]
    synth = ["eval", "synth", "--images", folder, "--sequences", "2", "--render-size", "240x320", *common]
    code, out, _ = run_cli(capsys, *synth, "--write", tmp_path / "set", "-o", tmp_path / "report")
    assert code == 0 and "[" in out and "2 viewpoint and 2 darkness sequences (20 pairs)" in out
    sequences = sorted(p.name for p in (tmp_path / "set").iterdir() if p.is_dir())
    assert [s.split("_")[0] for s in sequences] == ["dark", "dark", "v", "v"]
    assert sorted(p.name for p in (tmp_path / "set" / sequences[0]).iterdir()) == \
        [f"{i}.png" for i in range(1, 7)] + [f"H_1_{k}" for k in range(2, 7)]
    code, _, _ = run_cli(capsys, "eval", "hpatches", "--data", tmp_path / "set", *common, "-o", tmp_path / "back")
    assert code == 0
    (synth_model,) = json.loads((tmp_path / "report" / "results.json").read_text())["models"]
    (back_model,) = json.loads((tmp_path / "back" / "results.json").read_text())["models"]
    assert synth_model["pairs"] == back_model["pairs"]
    assert {g: {k: v for k, v in s.items() if k != "intervals"} for g, s in synth_model["summary"].items()} == \
        back_model["summary"]
    for group, summary in synth_model["summary"].items():
        assert set(summary["intervals"]) == {"repeatability", "localisation_error", "nn_map", "matching_score",
                                             "homography_1px", "homography_3px", "homography_5px"}
        low, high = summary["intervals"]["repeatability"]
        assert low <= summary["repeatability"] <= high, group
    # Claimed like -o: a second write replaces the earlier set with the same bytes; someone else's folder is kept.
    written = {p: p.read_bytes() for p in (tmp_path / "set").rglob("*") if p.is_file()}
    assert run_cli(capsys, *synth, "--write", tmp_path / "set")[0] == 0
    assert {p: p.read_bytes() for p in (tmp_path / "set").rglob("*") if p.is_file()} == written
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    assert run_cli(capsys, *synth, "--write", tmp_path / "mine")[0] == 2
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]


def test_dataset_layouts_are_found_recursively(shared_data):
    for folder, count in (("kitti_odom06_f000000-000050", 51), ("tum_fr2_desk_snippet", 20),
                          ("euroc_mh05_f000000-000199", 200)):
        frames = find_frames([shared_data / folder])
        assert len(frames) == count
        assert {f.key.split("/")[1] for f in frames} <= {"image_0", "rgb", "mav0"}


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys):
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    (empty / "sub" / "notes.txt").write_text("no images here")
    frames = write_frames(tmp_path / "frames", {"a.png": texture((120, 160))})
    base = ["eval", "synth", "--model", "orb", "-o", tmp_path / "report", "--write", tmp_path / "set"]
    for extra, fragment in (([empty], "no images"), ([tmp_path / "absent"], "no such directory"),
                            ([frames / "a.png"], "not a directory"),
                            ([frames, "--sequences", "0"], "--sequences must be at least 1"),
                            ([frames, "--kinds", "brightness"], "invalid choice"),
                            ([frames, "--seed", "-1"], "--seed must be >= 0"),
                            ([frames, "--render-size", "big"], "--render-size"),
                            ([frames, "--model", "nothing-here"], "no such file")):
        code, _, err = run_cli(capsys, *base, "--images", *extra)
        lines = [line for line in err.splitlines() if line.startswith("error:")]
        assert code == 2 and len(lines) == 1 and fragment in lines[0], err
        assert not (tmp_path / "report").exists() and not (tmp_path / "set").exists()
    code, _, err = run_cli(capsys, "eval", "synth", "--images", frames, "-o", tmp_path / "same", "--write",
                           tmp_path / "same")
    assert code == 2 and "two separate folders" in err and not (tmp_path / "same").exists()
    # a report inside a frames folder would be read as frames by the next run
    code, _, err = run_cli(capsys, "eval", "synth", "--images", frames, "--model", "orb", "-o", frames / "report")
    assert code == 2 and "inside the input" in err and sorted(p.name for p in frames.iterdir()) == ["a.png"]


def test_each_view_of_a_viewpoint_sequence_is_its_own_exposure(tmp_path):
    folder = write_frames(tmp_path / "board", {"board.png": checkerboard((480, 640), 24)})
    noisy = generate([folder], sequences=1, kinds=("viewpoint",))[0]
    exact = generate([folder], sequences=1, kinds=("viewpoint",), capture=CaptureNoise(0.0, 0.0, 0.0))[0]
    assert all(np.array_equal(a, b) for a, b in zip(noisy.homographies, exact.homographies))  # same geometry
    for with_noise, without in zip(noisy.images, exact.images):
        # what a smooth tone curve of the exact view does not explain is the sensor noise (~2 grey levels)
        curve = np.polyval(np.polyfit(without.ravel(), with_noise.ravel(), 2), without.astype(float))
        assert 1.0 < float(np.std(with_noise - curve)) < 3.0
    gains = [float(a.mean()) / float(b.mean()) for a, b in zip(noisy.images, exact.images)]
    assert max(gains) - min(gains) > 0.02  # exposures differ from view to view
