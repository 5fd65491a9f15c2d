"""Simulated darkness for testing a sequence in low light: a global darkening, or an onboard light.

Two kinds, both deterministic per frame (the seed is the frame's index in the sequence, so a run from a later
first frame sees the same noise on the same frame):

- `GlobalDark` (``--lowlight GAMMA,SIGMA[,GAIN]``, preset ``dark`` = 2,3,0.3): every pixel through
  ``255 GAIN (I/255)^GAMMA`` plus Gaussian noise of SIGMA grey levels: the whole scene dimmer.
- `OnboardLight` (preset ``onboard``): the way a drone meets a dark vessel: the only light rides on the
  camera, so a bright spot stays put in the image while the scene moves through it, the rest falls to a dim
  ambient level, the lens vignettes the corners, the sensor adds Poisson shot noise (photons counted after
  the darkening, so the dark parts are the noisiest relative to their signal) and Gaussian read noise, and the
  long exposure smears each frame along a (seeded) motion direction.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Union

import cv2
import numpy as np

from vo_runtime.errors import VORuntimeError


@dataclass(frozen=True)
class GlobalDark:
    """Gamma darkening and gain, then Gaussian sensor noise of ``sigma`` grey levels."""

    gamma: float = 2.0
    sigma: float = 3.0
    gain: float = 0.3

    def __post_init__(self) -> None:
        if not (self.gamma > 0 and self.sigma >= 0 and 0 < self.gain <= 1):
            raise VORuntimeError("--lowlight needs GAMMA > 0, SIGMA >= 0 and 0 < GAIN <= 1")

    def __call__(self, gray: np.ndarray, seed: int) -> np.ndarray:
        """HxW uint8 in and out."""
        scaled = 255.0 * self.gain * (gray.astype(np.float32) / 255.0) ** self.gamma
        noisy = scaled + np.random.default_rng(seed).normal(0.0, self.sigma, size=gray.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    def describe(self) -> str:
        return f"global dark (gamma {self.gamma:g}, noise {self.sigma:g}, gain {self.gain:g})"


@dataclass(frozen=True)
class OnboardLight:
    """A light on the drone: spot, ambient, vignetting, shot + read noise, motion blur (see the module text).

    Grey levels ``I`` become ``255 * (ambient + (spot - ambient) * s(r)) * v(r) * (I/255)^gamma`` with ``s`` a
    Gaussian spot of width ``spot_width`` (of the image diagonal) centred ``spot_offset`` below the centre
    (a light mounted under the lens), and ``v = cos^4`` vignetting that leaves ``vignette`` at the corners.
    """

    gamma: float = 1.6
    ambient: float = 0.05        # gain of the scene the light does not reach
    spot: float = 0.7            # gain at the spot's centre
    spot_width: float = 0.28     # Gaussian sigma, share of the image diagonal
    spot_offset: float = 0.08    # the spot's centre below the image centre, share of the height
    vignette: float = 0.55       # brightness left in the corners
    photons_per_level: float = 4.0   # shot noise: electrons per grey level (fewer: noisier)
    read_sigma: float = 2.0      # Gaussian read noise, grey levels
    blur_px: tuple[float, float] = (1.0, 5.0)  # motion blur length range, pixels (frame-seeded)
    # The anti-aliased line of a short blur kernel is not symmetric about its centre, so it also shifts the
    # image by up to half a pixel (measured: 0.5 px at lengths 2 and 5, 0.16 px on average), in a direction drawn
    # per frame: a jitter no camera has. Centred (the default since 2026-12-03): the line averaged with itself
    # turned by 180 degrees, so the smear is centred on the frame's pose, as an exposure's is on its mid-point,
    # and pixel-registered pairs (`toolkit eval synth`) stay registered. False: the tables made before.
    centred_blur: bool = True

    def __call__(self, gray: np.ndarray, seed: int) -> np.ndarray:
        """HxW uint8 in and out."""
        rng = np.random.default_rng(seed)
        height, width = gray.shape
        lit = self._illumination(height, width) * (gray.astype(np.float32) / 255.0) ** self.gamma * 255.0
        lit = self._motion_blur(lit, rng)
        electrons = rng.poisson(np.maximum(lit, 0.0) * self.photons_per_level)
        noisy = electrons / self.photons_per_level + rng.normal(0.0, self.read_sigma, size=lit.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    def _illumination(self, height: int, width: int) -> np.ndarray:
        """The gain map, the same for every frame of a size: computed once (5 ms at 752x480)."""
        return _illumination_map(self, height, width)

    def _gain_map(self, height: int, width: int) -> np.ndarray:
        y, x = np.mgrid[0:height, 0:width].astype(np.float32)
        diagonal = math.hypot(width, height)
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        spot_r2 = ((x - cx) ** 2 + (y - cy - self.spot_offset * height) ** 2) / (self.spot_width * diagonal) ** 2
        gain = self.ambient + (self.spot - self.ambient) * np.exp(-0.5 * spot_r2)
        # cos^4 falloff with the angle chosen so the corners keep `vignette`
        corner = math.acos(self.vignette ** 0.25)
        angle = np.sqrt((x - cx) ** 2 + (y - cy) ** 2) / (0.5 * diagonal) * corner
        return (gain * np.cos(angle) ** 4).astype(np.float32)

    def _motion_blur(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        length = float(rng.uniform(*self.blur_px))
        if length < 1.5:
            return image
        size = int(math.ceil(length)) | 1
        kernel = np.zeros((size, size), np.float32)
        direction = rng.uniform(0.0, math.pi)
        half = (length - 1.0) / 2.0
        centre = size // 2
        start = (centre - half * math.cos(direction), centre - half * math.sin(direction))
        end = (centre + half * math.cos(direction), centre + half * math.sin(direction))
        cv2.line(kernel, tuple(int(round(v * 16)) for v in start), tuple(int(round(v * 16)) for v in end), 1.0,
                 thickness=1, lineType=cv2.LINE_AA, shift=4)
        if self.centred_blur:
            kernel = kernel + kernel[::-1, ::-1]
        return cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)

    def describe(self) -> str:
        return "onboard light (spot on the camera, vignetting, shot + read noise, motion blur)"


@functools.lru_cache(maxsize=4)
def _illumination_map(light: OnboardLight, height: int, width: int) -> np.ndarray:
    gain = light._gain_map(height, width)
    gain.setflags(write=False)  # shared between frames
    return gain


PRESETS = {"dark": GlobalDark(2.0, 3.0, 0.3), "onboard": OnboardLight()}
Darkening = Union[GlobalDark, OnboardLight]  # Python 3.8 (JetPack 5) has no X | Y at run time


def parse_lowlight(text: str | None) -> Darkening | None:
    """``--lowlight``: a preset name (``dark``, ``onboard``) or ``GAMMA,SIGMA[,GAIN]``; None for None."""
    if text is None:
        return None
    if text in PRESETS:
        return PRESETS[text]
    try:
        values = [float(v) for v in text.split(",")]
        if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
            raise ValueError
    except ValueError:
        raise VORuntimeError(f"--lowlight takes a preset ({', '.join(PRESETS)}) or GAMMA,SIGMA[,GAIN] as finite "
                             f"numbers (e.g. 2,3,0.3), got {text!r}") from None
    gamma, sigma, gain = values if len(values) == 3 else (*values, 1.0)  # GAIN defaults to 1, as documented
    return GlobalDark(gamma, sigma, gain)
