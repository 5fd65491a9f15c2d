"""Sub-pixel refinements of a heatmap peak (`models.keypoints.Refinement`) and the position loss that trains
them, on cases with a known answer; and the refinement an export bakes in."""
from __future__ import annotations

import json
import math
import shutil

import pytest
import torch

from models.keypoints import Refinement, model_refinement, parse_refinement, refine_keypoints
from models.weights import shipped_checkpoint
from profiles import load_profile
from toolkit.cli import main
from toolkit.training.adaptation import AdaptationConfig, heatmap_to_keypoints
from toolkit.training.distill_losses import position_loss, student_peaks

torch.set_num_threads(1)


def gaussian_heatmap(x: float, y: float, sigma: float = 0.8, size: tuple[int, int] = (24, 32)) -> torch.Tensor:
    """[1, 1, H, W] a Gaussian blob of peak 0.5 centred at the sub-pixel point (x, y)."""
    rows = torch.arange(size[0], dtype=torch.float32)[:, None]
    cols = torch.arange(size[1], dtype=torch.float32)[None, :]
    return (0.5 * torch.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * sigma * sigma)))[None, None]


@pytest.mark.parametrize("text, method, radius, temperature", [
    ("centroid", "centroid", 1, 0.1), ("centroid:5", "centroid", 2, 0.1), ("quadratic", "quadratic", 1, 0.1),
    ("softargmax", "softargmax", 2, 0.1), ("softargmax:3:0.05", "softargmax", 1, 0.05)])
def test_parse_refinement(text, method, radius, temperature):
    refinement = parse_refinement(text)
    assert (refinement.method, refinement.radius, refinement.temperature) == (method, radius, temperature)
    assert parse_refinement(refinement.describe()) == refinement


@pytest.mark.parametrize("text", ["median", "centroid:4", "softargmax:5:-1", "quadratic:5", "centroid:9", "softargmax:x"])
def test_bad_refinements_are_refused(text):
    with pytest.raises(ValueError):
        parse_refinement(text)


def test_quadratic_fit_of_log_probabilities_is_exact_for_a_gaussian_peak():
    heat = gaussian_heatmap(10.3, 7.8)
    refined = refine_keypoints(heat, torch.tensor([[10.0, 8.0]]), Refinement("quadratic"))
    assert torch.allclose(refined, torch.tensor([[10.3, 7.8]]), atol=1e-3)


def test_centroid_and_softargmax_lean_the_way_the_mass_lies():
    heat = gaussian_heatmap(10.3, 7.8)
    peak = torch.tensor([[10.0, 8.0]])
    for refinement in (Refinement("centroid"), Refinement("centroid", radius=2), Refinement("softargmax", 2, 0.1)):
        shift = refine_keypoints(heat, peak, refinement) - peak
        assert 0.05 < float(shift[0, 0]) <= 0.3 + 1e-4 and -0.2 - 1e-4 <= float(shift[0, 1]) < -0.05, refinement
    # a temperature far below the differences listens to the peak pixel alone
    sharp = refine_keypoints(heat, peak, Refinement("softargmax", 2, 1e-4))
    assert torch.allclose(sharp, peak, atol=1e-4)


def test_model_refinement_reads_the_checkpoint_config_and_an_override_wins():
    from models.checkpoint import build_model

    net = build_model("featurenet", {"refinement": "softargmax:5:0.05"})
    assert model_refinement(net) == Refinement("softargmax", 2, 0.05)
    assert model_refinement(net, "quadratic") == Refinement("quadratic")
    assert model_refinement(torch.nn.Conv2d(1, 1, 1)) == Refinement()  # no config: the 3x3 centroid
    with pytest.raises(ValueError):
        build_model("featurenet", {"refinement": "bogus"})


def _cell_logits(x: float, y: float) -> torch.Tensor:
    """[1, 65, 3, 4] logits whose heatmap is a Gaussian at (x, y) (probabilities per cell, dustbin the rest)."""
    heat = gaussian_heatmap(x, y, size=(24, 32))[0, 0]
    cells = heat.reshape(3, 8, 4, 8).permute(1, 3, 0, 2).reshape(64, 3, 4)
    return torch.log(torch.cat([cells, (1 - cells.sum(0, keepdim=True)).clamp_min(1e-6)]).clamp_min(1e-9))[None]


def test_position_loss_is_the_distance_of_the_refined_point_and_training_moves_it_onto_the_target():
    refinement = Refinement("centroid")
    logits = _cell_logits(12.0, 11.0).requires_grad_(True)
    target = [torch.tensor([[12.3, 10.8]])]
    loss, _ = position_loss(logits, target, refinement)
    # the symmetric blob refines to its centre: the error is (0.3, 0.2); smooth-L1 with beta 0.5 is 0.5 x^2 / 0.5
    assert math.isclose(float(loss.detach()), 0.3 ** 2 + 0.2 ** 2, rel_tol=1e-3)
    optimiser = torch.optim.Adam([logits], lr=0.05)
    for _ in range(300):
        optimiser.zero_grad()
        position_loss(logits, target, refinement)[0].backward()
        optimiser.step()
    from models.keypoints import heatmap_from_logits

    heatmap = heatmap_from_logits(logits.detach())
    refined = refine_keypoints(heatmap, student_peaks(heatmap, target[0]), refinement)  # from its peak, as NMS
    assert torch.allclose(refined, target[0], atol=0.02)


def test_position_loss_starts_from_the_students_own_peak_next_to_the_target():
    # the student's peak is one pixel right of the target's pixel: the refinement starts there, as NMS would
    logits = _cell_logits(13.0, 11.0)
    loss, peakiness = position_loss(logits, [torch.tensor([[12.0, 11.0]])], Refinement("centroid"))
    assert math.isclose(float(loss), 1.0 - 0.25, rel_tol=1e-3)  # |dx| = 1 > beta: 1 - beta / 2
    assert 0 < float(peakiness) < 1
    empty, _ = position_loss(logits, [torch.zeros(0, 2)], Refinement("centroid"))
    assert float(empty) == 0.0


def test_subpixel_labels_follow_the_teachers_score_map():
    heat = gaussian_heatmap(10.3, 7.8, sigma=0.6)[0, 0]
    plain = AdaptationConfig(num_homographies=1, max_keypoints=4, threshold=0.1)
    subpixel = AdaptationConfig(num_homographies=1, max_keypoints=4, threshold=0.1, subpixel=True)
    keypoints, _ = heatmap_to_keypoints(heat, plain)
    assert keypoints.tolist() == [[10.0, 8.0]]
    refined, _ = heatmap_to_keypoints(heat, subpixel)
    assert abs(float(refined[0, 0]) - 10.3) < 0.3 and float(refined[0, 0]) > 10.0 and float(refined[0, 1]) < 8.0
    assert "subpixel" not in plain.to_dict() and subpixel.to_dict()["subpixel"] is True
    assert AdaptationConfig.from_dict(subpixel.to_dict()) == subpixel


def test_export_bakes_the_refinement_in_and_records_it(tmp_path, capsys):
    checkpoint = tmp_path / "featurenet.safetensors"
    shutil.copyfile(shipped_checkpoint("featurenet-elu"), checkpoint)
    out = tmp_path / "tx2-quadratic"
    assert main(["export", "--target", "tx2", "--checkpoint", str(checkpoint), "--refine", "quadratic", "-o", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["postprocess"]["refinement"] == "quadratic"
    assert manifest["parity"]["keypoints_identical"] >= manifest["parity"]["required_identical"]
    import onnx

    ops = {node.op_type for node in onnx.load(str(out / "model.onnx")).graph.node}
    assert "Log" in ops and ops <= load_profile("tx2").allowed_ops
    capsys.readouterr()
    assert main(["export", "--target", "tx2", "--checkpoint", str(checkpoint), "--refine", "median",
                 "-o", str(tmp_path / "bad")]) == 2
    assert "error: --refine" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_eval_runs_a_checkpoint_with_another_refinement(shared_data, tmp_path, capsys):
    data = shared_data / "hpatches_v_dogman"
    report = tmp_path / "report"
    assert main(["eval", "hpatches", "--data", str(data), "--model", "default", "--refine", "quadratic",
                 "--max-keypoints", "200", "-o", str(report)]) == 0
    results = json.loads((report / "results.json").read_text())
    assert results["models"][0]["settings"]["refinement"] == "quadratic"
    assert results["protocol"]["refinement"] == "quadratic"
    capsys.readouterr()
    assert main(["eval", "hpatches", "--data", str(data), "--model", "default", "--refine", "softargmax:4"]) == 2
    assert capsys.readouterr().err.startswith("error: --refine")


def test_position_loss_on_detections_only_skips_targets_without_a_student_peak():
    logits = _cell_logits(12.0, 11.0)  # one blob: a detection at (12, 11), nothing elsewhere
    targets = [torch.tensor([[12.3, 10.8], [20.0, 4.0]])]
    both, _ = position_loss(logits, targets, Refinement("centroid"))
    detected_only, _ = position_loss(logits, targets, Refinement("centroid"), only_detected=True)
    assert math.isclose(float(detected_only), 0.3 ** 2 + 0.2 ** 2, rel_tol=1e-3)  # the blob's target alone
    assert float(both) > float(detected_only)
