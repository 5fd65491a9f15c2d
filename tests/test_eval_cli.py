"""`toolkit eval` end to end: real data, every model kind, the report files and the one-line errors."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import torch

from toolkit.cli import main


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line_error(capsys, argv: list, fragment: str) -> None:
    code, _, err = run_cli(capsys, *argv)
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2, err
    assert len(lines) == 1 and fragment in lines[0], err
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def dogman_report(shared_data, tmp_path_factory):
    """ORB on hpatches_v_dogman at 240x320 (the default size), written to a report directory."""
    output = tmp_path_factory.mktemp("reports") / "dogman"
    code = main(["eval", "hpatches", "--data", str(shared_data / "hpatches_v_dogman"), "--model", "orb",
                 "-o", str(output)])
    assert code == 0
    return output


@pytest.fixture(scope="module")
def random_checkpoint_and_artefact(tmp_path_factory):
    """The shipped ReLU checkpoint and its x86-cpu export. (Random weights give a nearly flat heatmap whose
    near-ties flip between runtimes, which says nothing about an export of a trained model.)"""
    from models.weights import shipped_checkpoint

    torch.set_num_threads(1)
    directory = tmp_path_factory.mktemp("model")
    checkpoint = shipped_checkpoint("featurenet-relu")
    artefact = directory / "artefact"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "-o", str(artefact)]) == 0
    return checkpoint, artefact


def test_hpatches_orb_end_to_end(dogman_report, capsys):
    report = json.loads((dogman_report / "results.json").read_text())
    (model,) = report["models"]
    assert model["label"] == "ORB" and report["protocol"]["size"] == [240, 320]
    assert [p["pair"] for p in model["pairs"]] == [f"v_dogman/1-{k}" for k in range(2, 7)]
    summary = model["summary"]
    assert set(summary) == {"all", "v"} and summary["all"] == summary["v"]
    everything = summary["all"]
    assert everything["num_pairs"] == 5 and 0 < everything["num_keypoints"] <= 1000
    # ORB repeats well under viewpoint change but its matches are weaker than its detections.
    assert 0.5 < everything["repeatability"] <= 1.0
    assert 0.0 < everything["matching_score"] < everything["repeatability"]
    assert 0.0 < everything["localisation_error"] < 3.0
    assert everything["homography_1px"] <= everything["homography_3px"] <= everything["homography_5px"]
    # The pair with the smallest viewpoint change is solved within 5 px.
    assert model["pairs"][0]["corner_error"] < 5.0
    markdown = (dogman_report / "results.md").read_text()
    assert "| ORB | v | 5 |" in markdown and "| ORB | all | 5 |" in markdown
    png = cv2.imread(str(dogman_report / "matches_ORB.png"))
    assert png is not None and png.shape[1] >= 2 * 320
    assert not [p for p in dogman_report.parent.iterdir() if p.name.startswith(".")]   # no staging left


def test_pairs_with_a_homography_file_equal_the_hpatches_numbers(dogman_report, shared_data, tmp_path, capsys):
    sequence = shared_data / "hpatches_v_dogman" / "v_dogman"
    for folder, image in (("low", "1.ppm"), ("high", "3.ppm")):
        (tmp_path / folder).mkdir()
        # Stored gray: decoders convert colour to gray with slightly different rounding.
        cv2.imwrite(str(tmp_path / folder / "x.png"), cv2.imread(str(sequence / image), cv2.IMREAD_GRAYSCALE))
    (tmp_path / "homographies").mkdir()
    shutil.copy(sequence / "H_1_3", tmp_path / "homographies" / "x.txt")
    code, out, _ = run_cli(capsys, "eval", "pairs", "--data", tmp_path, "--model", "orb", "-o", tmp_path / "report")
    assert code == 0 and "ORB" in out
    (pair,) = json.loads((tmp_path / "report" / "results.json").read_text())["models"][0]["pairs"]
    hpatches = json.loads((dogman_report / "results.json").read_text())["models"][0]["pairs"][1]
    assert hpatches["pair"] == "v_dogman/1-3"
    for key in ("repeatability", "localisation_error", "nn_map", "matching_score", "corner_error"):
        assert pair[key] == pytest.approx(hpatches[key]), key


def test_lowlight_pairs_raw_and_contrast_normalised(shared_data, tmp_path, capsys):
    data = shared_data / "lowlight_pairs"
    reports = {}
    for mode in ("none", "minmax"):
        code, _, _ = run_cli(capsys, "eval", "pairs", "--data", data, "--model", "lowlight-orb=orb",
                             "--max-keypoints", "500", "--normalise", mode, "-o", tmp_path / mode)
        assert code == 0
        reports[mode] = json.loads((tmp_path / mode / "results.json").read_text())["models"][0]
    assert reports["none"]["label"] == "lowlight-orb"
    assert len(reports["none"]["pairs"]) == 15 and set(reports["none"]["summary"]) == {"all"}
    # ORB's fixed FAST threshold finds few corners in the dark shots; a contrast stretch brings them back.
    assert reports["minmax"]["summary"]["all"]["repeatability"] > 2 * reports["none"]["summary"]["all"]["repeatability"]
    assert reports["minmax"]["summary"]["all"]["homography_3px"] > 0.5


def test_checkpoint_and_its_artefact_run_through_the_same_path(random_checkpoint_and_artefact, shared_data,
                                                               tmp_path, capsys):
    checkpoint, artefact = random_checkpoint_and_artefact
    code, out, _ = run_cli(capsys, "eval", "hpatches", "--data", shared_data / "hpatches_v_dogman", "--max-keypoints",
                           "500", "--model", f"torch={checkpoint}", "--model", f"onnx={artefact}", "-o", tmp_path / "r")
    assert code == 0 and "torch" in out and "onnx" in out
    models = json.loads((tmp_path / "r" / "results.json").read_text())["models"]
    assert [m["kind"] for m in models] == ["checkpoint", "artefact"]
    assert models[1]["settings"]["checkpoint_sha256"] == models[0]["settings"]["sha256"]
    torch_summary, onnx_summary = models[0]["summary"]["all"], models[1]["summary"]["all"]
    assert torch_summary["num_keypoints"] == onnx_summary["num_keypoints"] == 500
    # Export parity is ~99.6 % identical keypoints, so every detector metric agrees closely.
    for key in ("repeatability", "nn_map", "matching_score"):
        assert onnx_summary[key] == pytest.approx(torch_summary[key], abs=0.03), key
    assert (tmp_path / "r" / "matches_torch.png").is_file() and (tmp_path / "r" / "matches_onnx.png").is_file()


def test_artefact_with_a_bad_checksum_is_refused(random_checkpoint_and_artefact, shared_data, tmp_path, capsys):
    _, artefact = random_checkpoint_and_artefact
    tampered = tmp_path / "tampered"
    shutil.copytree(artefact, tampered)
    with open(tampered / "model.onnx", "ab") as handle:
        handle.write(b"\0")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", shared_data / "hpatches_v_dogman",
                                   "--model", tampered, "-o", tmp_path / "r"], "checksum")
    assert not (tmp_path / "r").exists()


def test_bad_input_gives_one_line_errors(shared_data, tmp_path, capsys):
    sequence = tmp_path / "v_broken"
    sequence.mkdir()
    for name in ("1.ppm", "2.ppm"):
        shutil.copy(shared_data / "hpatches_v_dogman" / "v_dogman" / name, sequence / name)
    (sequence / "H_1_2").write_text("1 0 0\n0 1 0\n")
    dogman = shared_data / "hpatches_v_dogman"
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", tmp_path / "absent"], "data directory not found")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", tmp_path, "--model", "orb"], "malformed homography")
    for name in ("H_1_2", "H_1_3"):   # valid files now, but image 3 does not exist
        (sequence / name).write_text("1 0 0\n0 1 0\n0 0 1\n")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", tmp_path, "--model", "orb"], "3.ppm is missing")
    assert_one_line_error(capsys, ["eval", "pairs", "--data", dogman], "folder low/ is missing")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", dogman, "--model", "nothing-here"], "no such file")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", dogman, "--size", "240by320"], "bad --size")
    missing_weights = f"superpoint:{tmp_path / 'sp.pth'}"
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", dogman, "--model", missing_weights],
                          "SuperPoint weights not found")
    (tmp_path / "notes.txt").write_text("mine")
    assert_one_line_error(capsys, ["eval", "hpatches", "--data", dogman, "-o", tmp_path], "refusing to overwrite")


def test_superpoint_weights_and_a_flat_image(shared_data, tmp_path, capsys):
    """superpoint:PATH with random weights in Magic Leap's layout (code path only), and ORB on a flat pair."""
    from models.superpoint import SuperPointNet

    torch.set_num_threads(1)
    torch.manual_seed(0)
    torch.save(SuperPointNet().state_dict(), tmp_path / "superpoint_random.pth")
    data = tmp_path / "data"
    image = cv2.imread(str(shared_data / "hpatches_v_dogman" / "v_dogman" / "1.ppm"), cv2.IMREAD_GRAYSCALE)
    for folder in ("low", "high"):
        (data / folder).mkdir(parents=True)
        cv2.imwrite(str(data / folder / "1.png"), image)
        cv2.imwrite(str(data / folder / "2.png"), np.full((240, 320), 90, np.uint8))
    code, out, _ = run_cli(capsys, "eval", "pairs", "--data", data, "--model", "orb",
                           "--model", f"superpoint:{tmp_path / 'superpoint_random.pth'}", "-o", tmp_path / "r")
    assert code == 0 and "SuperPoint" in out
    orb, superpoint = json.loads((tmp_path / "r" / "results.json").read_text())["models"]
    assert superpoint["kind"] == "superpoint"
    for model in (orb, superpoint):
        same = model["pairs"][0]
        assert same["pair"] == "1" and same["repeatability"] == 1.0
        assert same["localisation_error"] == pytest.approx(0.0, abs=1e-9)   # H = S I S^-1 up to rounding
        assert same["corner_error"] < 0.5
    flat = orb["pairs"][1]
    assert flat["num_keypoints"] == 0 and flat["repeatability"] == 0.0 and flat["matching_score"] == 0.0
    assert flat["corner_error"] is None and flat["localisation_error"] is None
    assert orb["summary"]["all"]["homography_1px"] == 0.5


def test_i_and_v_sequences_are_reported_apart_and_together(shared_data, tmp_path, capsys):
    dogman = shared_data / "hpatches_v_dogman" / "v_dogman"
    (tmp_path / "v_dogman").symlink_to(dogman, target_is_directory=True)
    (tmp_path / "i_dogman").mkdir()
    for name in ("1.ppm", "2.ppm", "H_1_2"):   # a one-pair "illumination" sequence
        (tmp_path / "i_dogman" / name).symlink_to(dogman / name)
    code, out, _ = run_cli(capsys, "eval", "hpatches", "--data", tmp_path, "--model", "orb", "--size", "120x160",
                           "-o", tmp_path / "r")
    assert code == 0
    (model,) = json.loads((tmp_path / "r" / "results.json").read_text())["models"]
    summary = model["summary"]
    assert list(summary) == ["all", "i", "v"]
    assert (summary["all"]["num_pairs"], summary["i"]["num_pairs"], summary["v"]["num_pairs"]) == (6, 1, 5)
    pair_repeatability = {p["pair"]: p["repeatability"] for p in model["pairs"]}
    assert summary["i"]["repeatability"] == pytest.approx(pair_repeatability["i_dogman/1-2"])
    assert summary["all"]["repeatability"] == pytest.approx(sum(pair_repeatability.values()) / 6)
    assert pair_repeatability["i_dogman/1-2"] == pytest.approx(pair_repeatability["v_dogman/1-2"])
    *table, written = out.splitlines()[2:]
    assert [line.split()[1] for line in table] == ["all", "i", "v"]
    assert written.startswith(f"wrote {tmp_path / 'r'}: results.json")  # the last line says where it wrote


def test_fp16_artefact_runs_and_reports_its_precision(random_checkpoint_and_artefact, shared_data, tmp_path, capsys):
    checkpoint, _ = random_checkpoint_and_artefact
    artefact = tmp_path / "fp16"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--precision", "fp16",
                 "-o", str(artefact)]) == 0
    capsys.readouterr()
    code, out, _ = run_cli(capsys, "eval", "pairs", "--data", shared_data / "lowlight_pairs", "--max-keypoints", "300",
                           "--size", "120x160", "--model", f"half={artefact}", "-o", tmp_path / "r")
    assert code == 0 and "half" in out
    (model,) = json.loads((tmp_path / "r" / "results.json").read_text())["models"]
    assert model["kind"] == "artefact" and model["settings"]["precision"] == "fp16"
    assert len(model["pairs"]) == 15 and model["summary"]["all"]["num_keypoints"] == 300


def test_fp16_quantise_at_240x320_keeps_keypoint_indices_exact(random_checkpoint_and_artefact, tmp_path):
    # 240x320 has 76,800 pixels: a flat pixel index in half precision overflows (max 65,504), so the
    # graph's gather indices must never pass through a float for the FP16 artefact to run and keep its keypoints.
    _, artefact = random_checkpoint_and_artefact
    out = tmp_path / "half"
    assert main(["quantise", "--artefact", str(artefact), "--mode", "fp16", "-o", str(out)]) == 0
    parity = json.loads((out / "manifest.json").read_text())["quantisation"]["parity_vs_fp32"]
    assert parity["keypoints_unchanged"] >= 0.9
