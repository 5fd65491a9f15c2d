"""A stand-in reference network for measuring compression while no trained weights exist.

A freshly initialised FeatureNet is a poor yardstick: its activations shrink layer by layer against
BatchNorm statistics of (0, 1), so its heads put out near-constant maps that any compression leaves
"unchanged". `calibrated_random_featurenet` estimates the BatchNorm statistics on real images and gives the
offset branch small random weights, so activations have unit scale, heatmaps and descriptors follow the
image, and the deformable sampling is exercised. Its figures measure numerical drift only: it is never a
trained detector and its outputs must not be reported as accuracy.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from models.featurenet import FeatureNet, FeatureNetConfig

OFFSET_WEIGHT_STD = 0.02  # offsets of about a pixel from unit-scale features


def recalibrate_batchnorm(model: nn.Module, images: np.ndarray, batch: int = 4) -> nn.Module:
    """Replace every BatchNorm's running statistics by their cumulative average over ``images`` [N, 1, H, W]."""
    norms = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    saved = [(m.momentum, m.training) for m in norms]
    for norm in norms:
        norm.reset_running_stats()
        norm.momentum = None  # cumulative moving average over all batches
        norm.train()
    with torch.no_grad():
        for start in range(0, len(images), batch):
            model(torch.from_numpy(images[start : start + batch]))
    for norm, (momentum, training) in zip(norms, saved):
        norm.momentum = momentum
        norm.train(training)
    return model


def calibrated_random_featurenet(config: FeatureNetConfig, images: np.ndarray, seed: int = 0) -> FeatureNet:
    """Random FeatureNet (seeded) with image-calibrated BatchNorm statistics and non-zero offsets; eval mode."""
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        model = FeatureNet(config).eval()
        if config.deformable:
            nn.init.normal_(model.deform.offset_pw.weight, std=OFFSET_WEIGHT_STD)
    finally:
        torch.random.set_rng_state(generator_state)
    return recalibrate_batchnorm(model, images).eval()
