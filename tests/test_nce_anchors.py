"""InfoNCE anchored at the teacher's keypoints (`distill.nce_anchors = "keypoints"`)."""
from __future__ import annotations

import math

import pytest
import torch

from toolkit.training.distill_losses import DistillLossConfig, info_nce_loss, keypoint_positions
from toolkit.training.pairs import DUSTBIN, cell_labels_and_offsets


def test_keypoint_positions_read_back_the_labelled_points() -> None:
    points = torch.tensor([[17.25, 9.0], [3.0, 20.4], [30.0, 2.0]])
    labels, offsets = cell_labels_and_offsets(points, torch.ones(3), (24, 32))
    assert int((labels < DUSTBIN).sum()) == 3
    found = keypoint_positions(labels, offsets)
    order = sorted(range(3), key=lambda i: (int(points[i, 1] // 8), int(points[i, 0] // 8)))  # row-major cells
    assert torch.allclose(found, points[order], atol=1e-5)
    assert keypoint_positions(torch.full((3, 4), DUSTBIN)).shape == (0, 2)


def _one_hot_map(points: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """A [1, N, h, w] map whose bilinear sample at each point is exactly one-hot (points at cell centres)."""
    descriptors = torch.zeros(1, points.shape[0], height, width)
    for i, (x, y) in enumerate(points.tolist()):
        descriptors[0, i, int(y // 8), int(x // 8)] = 1.0
    return descriptors


def test_keypoint_anchors_have_the_closed_form_value() -> None:
    """Anchors at cell centres with one-hot descriptors, identity homography: each row's cross-entropy is
    log(1 + (N - 1) exp(-1 / T)), as for cell anchors."""
    points = torch.tensor([[11.5, 11.5], [27.5, 11.5], [11.5, 27.5], [35.5, 27.5]])
    descriptors = _one_hot_map(points, 5, 6)
    valid = torch.ones(1, 5, 6, dtype=torch.bool)
    config = DistillLossConfig(temperature=0.5, nce_anchors="keypoints")
    loss = info_nce_loss(descriptors, descriptors, torch.eye(3)[None], valid, config, anchors=[points])
    assert loss.item() == pytest.approx(math.log(1 + 3 * math.exp(-1 / 0.5)), rel=1e-5)


def test_keypoints_nearer_than_the_match_tolerance_are_not_negatives() -> None:
    """Two anchors 2 px apart read almost the same descriptor: as negatives they would add a large loss
    that no descriptor can remove; masked, the loss is that of two separate points."""
    far = torch.tensor([[11.5, 11.5], [27.5, 27.5]])
    near = torch.tensor([[11.5, 11.5], [13.5, 11.5], [27.5, 27.5]])
    descriptors = _one_hot_map(far, 5, 6)
    valid = torch.ones(1, 5, 6, dtype=torch.bool)
    config = DistillLossConfig(temperature=0.1, nce_anchors="keypoints")
    two = info_nce_loss(descriptors, descriptors, torch.eye(3)[None], valid, config, anchors=[far])
    three = info_nce_loss(descriptors, descriptors, torch.eye(3)[None], valid, config, anchors=[near])
    assert three.item() < two.item() + 0.1


def test_unknown_anchor_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="nce_anchors"):
        DistillLossConfig(nce_anchors="pixels")
