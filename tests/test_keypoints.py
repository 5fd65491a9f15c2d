"""Post-processing shared by PyTorch and the exported graph, on cases with a known answer."""
from __future__ import annotations

import torch

from models.keypoints import (extract_keypoints, heatmap_from_logits, keypoint_scores, max_pool_nms, refine_keypoints,
                              sample_descriptors, top_k_keypoints)


def test_heatmap_places_each_cell_channel_at_its_pixel():
    logits = torch.full((1, 65, 3, 4), -10.0)
    logits[:, 64] = 10.0  # dustbin everywhere ...
    logits[0, 64, 1, 2] = -10.0
    logits[0, 8 * 5 + 3, 1, 2] = 10.0  # ... except cell (1, 2), which fires at row 5, column 3 inside it
    heatmap = heatmap_from_logits(logits)
    assert heatmap.shape == (1, 1, 24, 32)
    peak = int(torch.argmax(heatmap))
    assert divmod(peak, 32) == (1 * 8 + 5, 2 * 8 + 3)


def test_heatmap_equals_softmax_then_pixel_shuffle():
    logits = torch.randn(2, 65, 5, 7) * 4
    reference = torch.nn.functional.pixel_shuffle(torch.softmax(logits, dim=1)[:, :-1], 8)
    assert torch.allclose(heatmap_from_logits(logits), reference, rtol=1e-6, atol=1e-8)


def test_projection_after_sampling_equals_sampling_the_projected_map():
    # A 1x1 conv is linear and bilinear weights sum to one, so projecting K samples equals sampling the
    # projected map; only where the normalisation happens differs, which the unnormalised map removes.
    features = torch.randn(16, 3, 4)
    weight, bias = torch.randn(32, 16), torch.randn(32)
    projected = torch.einsum("dc,chw->dhw", weight, features) + bias[:, None, None]
    keypoints = torch.tensor([[5.0, 6.0], [19.5, 11.5], [13.25, 17.75], [30.0, 22.0]])
    sparse = sample_descriptors(features, keypoints, (weight, bias))
    assert sparse.shape == (4, 32)
    assert torch.allclose(sparse, sample_descriptors(projected, keypoints), atol=1e-5)


def test_nms_keeps_local_maxima_only():
    heat = torch.zeros(1, 1, 20, 20)
    heat[0, 0, 5, 5], heat[0, 0, 6, 6], heat[0, 0, 15, 15] = 0.9, 0.5, 0.4
    kept = max_pool_nms(heat, radius=2)[0, 0]
    assert kept[5, 5] == 0.9 and kept[6, 6] == 0 and kept[15, 15] == 0.4


def test_top_k_returns_x_then_y_best_first():
    scores = torch.zeros(10, 13)
    scores[2, 11], scores[7, 4] = 0.8, 0.6
    keypoints, values = top_k_keypoints(scores, 2)
    assert keypoints.tolist() == [[11.0, 2.0], [4.0, 7.0]]
    assert values.tolist() == [0.800000011920929, 0.6000000238418579]


def test_descriptor_sampling_hits_cell_centres_and_interpolates():
    coarse = torch.nn.functional.normalize(torch.randn(16, 3, 4), dim=0)
    # Cell (row 1, col 2) is centred on pixel (x, y) = (2*8 + 3.5, 1*8 + 3.5).
    at_centre = sample_descriptors(coarse, torch.tensor([[19.5, 11.5]]))
    assert torch.allclose(at_centre[0], coarse[:, 1, 2], atol=1e-6)
    halfway = sample_descriptors(coarse, torch.tensor([[23.5, 11.5]]))
    expected = torch.nn.functional.normalize(coarse[:, 1, 2] + coarse[:, 1, 3], dim=0)
    assert torch.allclose(halfway[0], expected, atol=1e-6)


def test_extract_keypoints_counts_valid_rows_and_drops_the_border():
    logits = torch.full((1, 65, 4, 4), -10.0)
    logits[:, 64] = 10.0
    logits[0, 64, 0, 0], logits[0, 0, 0, 0] = -10.0, 10.0  # pixel (0, 0): inside the 4-px border
    logits[0, 64, 2, 1], logits[0, 8 * 3 + 4, 2, 1] = -10.0, 10.0  # pixel (x=12, y=19)
    descriptors = torch.nn.functional.normalize(torch.randn(1, 32, 4, 4), dim=1)
    out = extract_keypoints(logits, descriptors, max_keypoints=5, nms_radius=2, threshold=0.5, border=4)
    assert int(out["num_valid"][0]) == 1
    assert out["keypoints"][0].tolist() == [12.0, 19.0]
    assert out["descriptors"].shape == (5, 32)


def test_refinement_moves_a_peak_to_the_centroid_of_its_window():
    heat = torch.zeros(1, 1, 16, 16)
    heat[0, 0, 5, 7] = 0.6  # peak at x=7, y=5 ...
    heat[0, 0, 5, 8] = 0.3  # ... with mass to its right ...
    heat[0, 0, 4, 7] = 0.1  # ... and a little above
    heat[0, 0, 9, 3] = 0.5  # a lone peak stays where it is
    refined = refine_keypoints(heat, torch.tensor([[7.0, 5.0], [3.0, 9.0], [0.0, 0.0]]))
    assert torch.allclose(refined[0], torch.tensor([7.0 + 0.3, 5.0 - 0.1]), atol=1e-6)
    assert torch.equal(refined[1], torch.tensor([3.0, 9.0]))
    assert torch.equal(refined[2], torch.tensor([0.0, 0.0]))  # an empty window (padding rows) does not move


def _logits_for(heatmap: torch.Tensor) -> torch.Tensor:
    """[H, W] pixel probabilities (each 8x8 cell summing below 1) -> [1, 65, H/8, W/8] logits reproducing them."""
    height, width = heatmap.shape
    cells = heatmap.reshape(height // 8, 8, width // 8, 8).permute(1, 3, 0, 2).reshape(64, height // 8, width // 8)
    dustbin = 1.0 - cells.sum(0, keepdim=True)
    return torch.log(torch.cat([cells, dustbin]).clamp_min(1e-9))[None]


def test_mass_ranks_a_spread_keypoint_above_a_sharp_but_weaker_one():
    heat = torch.zeros(32, 32)
    heat[9:12, 9:12] = 0.09  # a keypoint the network is sure of but places only to within a pixel: mass 0.81
    heat[10, 10] = 0.12      # (peak 0.12, mass 0.84)
    heat[22, 21] = 0.3       # a sharp but weaker one: peak 0.3, mass 0.3
    scores = keypoint_scores(heat[None, None], 3)[0, 0]
    assert torch.isclose(scores[10, 10], torch.tensor(0.84)) and torch.isclose(scores[22, 21], torch.tensor(0.3))
    assert scores[9, 9] == 0 and scores[10, 11] == 0  # not a peak of the heatmap: no candidate
    assert torch.equal(keypoint_scores(heat[None, None], 1)[0, 0], heat)
    assert keypoint_scores(heat[None, None], 3, threshold=0.2)[0, 0, 10, 10] == 0  # its peak 0.12 is below
    descriptors = torch.nn.functional.normalize(torch.randn(1, 8, 4, 4), dim=1)
    logits = _logits_for(heat)
    peak = extract_keypoints(logits, descriptors, max_keypoints=2, nms_radius=4, border=4, score_window=1)
    mass_ranked = extract_keypoints(logits, descriptors, max_keypoints=2, nms_radius=4, border=4, score_window=3)
    assert peak["keypoints"].tolist() == [[21.0, 22.0], [10.0, 10.0]]
    assert mass_ranked["keypoints"].tolist() == [[10.0, 10.0], [21.0, 22.0]]  # same points, refined alike
    assert torch.allclose(mass_ranked["scores"], torch.tensor([0.84, 0.3]), atol=1e-5)


def test_a_sharp_peak_is_one_point_not_a_plateau_of_equal_window_sums():
    # Probabilities below float32's resolution around a confident peak give its eight neighbours the same
    # window sum as the peak; only the peak may become a keypoint.
    heat = torch.full((1, 1, 24, 24), 1e-12)
    heat[0, 0, 12, 11] = 0.9
    scores = max_pool_nms(keypoint_scores(heat, 3), 2)[0, 0]
    assert (scores > 0.5).sum() == 1 and scores[12, 11] > 0.5

