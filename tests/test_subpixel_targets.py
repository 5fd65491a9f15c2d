"""Sub-pixel keypoint targets of the distill recipe (`distill.subpixel_targets`), on cases with a known answer."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from toolkit.training.distill_losses import subpixel_detector_loss
from toolkit.training.losses import detector_loss
from toolkit.training.pairs import cell_labels, cell_labels_and_offsets


def test_each_cell_keeps_the_offset_of_its_best_keypoint():
    keypoints = torch.tensor([[3.25, 2.0], [3.4, 2.1], [12.7, 9.9]])
    labels, offsets = cell_labels_and_offsets(keypoints, torch.tensor([0.5, 0.9, 0.3]), (16, 16))
    assert labels.tolist() == [[2 * 8 + 3, 64], [64, 2 * 8 + 5]]  # (3.4, 2.1) beats (3.25, 2.0) at pixel (3, 2)
    assert torch.allclose(offsets[:, 0, 0], torch.tensor([0.4, 0.1]), atol=1e-6)
    assert torch.allclose(offsets[:, 1, 1], torch.tensor([-0.3, -0.1]), atol=1e-6)  # (12.7, 9.9) -> pixel (13, 10)
    assert offsets[:, 0, 1].abs().sum() == 0 and offsets[:, 1, 0].abs().sum() == 0  # no keypoint, no offset
    assert torch.equal(labels, cell_labels(keypoints, torch.tensor([0.5, 0.9, 0.3]), (16, 16)))


def test_zero_offsets_give_the_hard_label_cross_entropy():
    torch.manual_seed(0)
    logits, labels = torch.randn(2, 65, 3, 4), torch.randint(0, 65, (2, 3, 4))
    valid = torch.rand(2, 3, 4) > 0.3
    zero = torch.zeros(2, 2, 3, 4)
    assert torch.allclose(subpixel_detector_loss(logits, labels, zero, valid), detector_loss(logits, labels, valid))


def test_an_offset_splits_the_target_bilinearly_inside_the_cell():
    torch.manual_seed(1)
    logits = torch.randn(1, 65, 1, 1)
    log_p = F.log_softmax(logits, dim=1)[0, :, 0, 0]
    # Pixel (x 3, y 2), a quarter pixel right and half a pixel down: 3/8 on it, 1/8 right, 3/8 below, 1/8 diagonal.
    loss = subpixel_detector_loss(logits, torch.full((1, 1, 1), 19), torch.tensor([0.25, 0.5]).reshape(1, 2, 1, 1))
    expected = -(0.375 * log_p[19] + 0.125 * log_p[20] + 0.375 * log_p[27] + 0.125 * log_p[28])
    assert torch.isclose(loss, expected)
    # Pixel (x 7, y 0) leaning right and up: both neighbours lie in other cells, so all weight stays on it.
    loss = subpixel_detector_loss(logits, torch.full((1, 1, 1), 7), torch.tensor([0.25, -0.5]).reshape(1, 2, 1, 1))
    assert torch.isclose(loss, -log_p[7])


def test_the_loss_is_lowest_when_the_heatmap_centroid_is_the_keypoint():
    # Minimising over the 65 logits of one cell reproduces the bilinear weights, whose centroid is the offset.
    logits = torch.zeros(1, 65, 1, 1, requires_grad=True)
    optimiser = torch.optim.Adam([logits], lr=0.1)
    for _ in range(500):
        optimiser.zero_grad()
        subpixel_detector_loss(logits, torch.full((1, 1, 1), 27), torch.tensor([-0.3, 0.2]).reshape(1, 2, 1, 1)).backward()
        optimiser.step()
    p = torch.softmax(logits.detach()[0, :, 0, 0], 0)[:64].reshape(8, 8)  # [y, x]
    ys, xs = torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij")
    centroid = torch.stack([(p * xs).sum(), (p * ys).sum()]) / p.sum()
    assert torch.allclose(centroid, torch.tensor([3 - 0.3, 3 + 0.2]), atol=0.02)
