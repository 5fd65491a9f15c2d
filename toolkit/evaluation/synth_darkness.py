"""Darkness for `toolkit eval synth`: five ever darker versions of the reference, pixel-registered with it.

Each step is `vo_runtime.lowlight.OnboardLight` (the VO's own low-light simulation) with stronger settings:
gamma and gain, then vignetting and a light riding on the camera (a spot that stays put in the image), Poisson
shot noise counted after the darkening plus Gaussian read noise, and a longer motion blur. The blur kernel is
made symmetric about its centre (``centred_blur``), so it smears without shifting and the identity holds.
"""
from __future__ import annotations

import numpy as np

from vo_runtime.lowlight import OnboardLight

# Easy to hard: on the dev set (docs/evaluation.md) the mean grey level goes 99 (reference) -> 44, 25, 18, 11,
# 7, darker at every step in each of its 60 sequences. The first step lights the scene evenly (spot = ambient,
# no vignetting: gamma, gain and noise only), the second adds vignetting, the later ones the camera's own
# light. Blur lengths are px at the rendered size (1: none).
DARK_STEPS: tuple[OnboardLight, ...] = (
    OnboardLight(gamma=1.2, ambient=0.5, spot=0.5, vignette=1.0, photons_per_level=16.0, read_sigma=1.0,
                 blur_px=(1.0, 1.0), centred_blur=True),
    OnboardLight(gamma=1.4, ambient=0.35, spot=0.35, vignette=0.75, photons_per_level=10.0, read_sigma=1.5,
                 blur_px=(2.0, 2.0), centred_blur=True),
    OnboardLight(gamma=1.6, ambient=0.08, spot=0.4, vignette=0.6, photons_per_level=6.0, read_sigma=2.0,
                 blur_px=(3.0, 3.0), centred_blur=True),
    OnboardLight(gamma=1.8, ambient=0.04, spot=0.28, vignette=0.5, photons_per_level=4.0, read_sigma=2.0,
                 blur_px=(4.0, 4.0), centred_blur=True),
    OnboardLight(gamma=2.0, ambient=0.02, spot=0.2, vignette=0.45, photons_per_level=3.0, read_sigma=2.5,
                 blur_px=(5.0, 5.0), centred_blur=True),
)


def darkness_targets(reference: np.ndarray, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """(target HxW uint8, identity 3x3) for each of `DARK_STEPS`, easiest first; noise and blur direction
    seeded from ``rng`` (one seed per step, drawn in order)."""
    seeds = rng.integers(0, 2**63 - 1, size=len(DARK_STEPS))
    return [(step(reference, int(seed)), np.eye(3)) for step, seed in zip(DARK_STEPS, seeds)]
