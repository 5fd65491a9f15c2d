"""Photometric augmentation (SuperPoint's brightness, contrast, noise, motion blur) and low-light simulation.

Every function takes a CPU ``torch.Generator`` so that a training sample is a pure function of its
seed: a resumed run sees exactly the images the uninterrupted run saw.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class AugmentConfig:
    brightness: float = 0.15  # additive shift uniform in [-b, b]
    contrast: tuple[float, float] = (0.6, 1.5)  # gain around the image mean (the paper's random contrast)
    noise_std: float = 0.03  # Gaussian noise with a std uniform in [0, noise_std]
    motion_blur_prob: float = 0.4
    motion_blur_max_kernel: int = 9  # odd; line kernels of length 3..max at a random angle
    lowlight_prob: float = 0.4
    lowlight_gamma: tuple[float, float] = (1.5, 3.0)  # darkening curve x -> x^gamma
    lowlight_gain: tuple[float, float] = (0.15, 0.6)  # exposure scale after the gamma
    lowlight_photons: tuple[float, float] = (30.0, 400.0)  # photons at full scale: shot noise strength
    lowlight_read_noise: float = 0.01  # Gaussian read noise std (max)
    lowlight_rebrighten_prob: float = 0.5  # digital gain back to a normal level, which amplifies the noise


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator))


def _chance(generator: torch.Generator, probability: float) -> bool:
    return float(torch.rand((), generator=generator)) < probability


def motion_blur_kernel(length: int, angle: float) -> torch.Tensor:
    """A normalised [length, length] line kernel through the centre at ``angle`` radians."""
    kernel = torch.zeros(length, length)
    centre = (length - 1) / 2
    for t in torch.linspace(-centre, centre, 4 * length):
        x = round(centre + float(t) * math.cos(angle))
        y = round(centre + float(t) * math.sin(angle))
        kernel[y, x] = 1.0
    return kernel / kernel.sum()


def motion_blur(image: torch.Tensor, length: int, angle: float) -> torch.Tensor:
    """[1, H, W] -> [1, H, W] blurred along a line (camera shake during the exposure)."""
    kernel = motion_blur_kernel(length, angle).to(image)[None, None]
    pad = length // 2
    padded = F.pad(image[None], (pad, pad, pad, pad), mode="reflect")
    return F.conv2d(padded, kernel)[0]


def simulate_low_light(image: torch.Tensor, config: AugmentConfig, generator: torch.Generator) -> torch.Tensor:
    """Darken a well-exposed [1, H, W] image in [0, 1] like an under-exposed sensor frame.

    Gamma darkening and an exposure gain, then Poisson shot noise and Gaussian read noise at the
    darkened level, 8-bit quantisation, and sometimes a digital gain back up (amplified noise).
    """
    gamma = _uniform(generator, *config.lowlight_gamma)
    gain = _uniform(generator, *config.lowlight_gain)
    dark = gain * image.clamp(0, 1) ** gamma
    photons = _uniform(generator, *config.lowlight_photons)
    noisy = torch.poisson(dark * photons, generator=generator) / photons
    read_std = _uniform(generator, 0.0, config.lowlight_read_noise)
    noisy = noisy + read_std * torch.randn(noisy.shape, generator=generator)
    noisy = torch.round(noisy.clamp(0, 1) * 255) / 255
    if _chance(generator, config.lowlight_rebrighten_prob):
        noisy = noisy * min(1.0 / max(gain, 1e-3), 4.0)
    return noisy.clamp(0, 1)


def photometric_augment(image: torch.Tensor, config: AugmentConfig, generator: torch.Generator) -> torch.Tensor:
    """Random low light, brightness, contrast, motion blur and noise on one [1, H, W] image in [0, 1]."""
    out = image
    if _chance(generator, config.lowlight_prob):
        out = simulate_low_light(out, config, generator)
    out = out + _uniform(generator, -config.brightness, config.brightness)
    mean = out.mean()
    out = (out - mean) * _uniform(generator, *config.contrast) + mean
    if _chance(generator, config.motion_blur_prob):
        longest = max(3, config.motion_blur_max_kernel)
        length = 3 + 2 * int(torch.randint(0, (longest - 3) // 2 + 1, (), generator=generator))
        out = motion_blur(out, length, _uniform(generator, 0.0, math.pi))
    std = _uniform(generator, 0.0, config.noise_std)
    out = out + std * torch.randn(out.shape, generator=generator)
    return out.clamp(0, 1)
