"""Simulated darkness: the global preset and the onboard light are seeded, registered and shaped as stated."""
from __future__ import annotations

import numpy as np
import pytest

from vo_runtime import VORuntimeError
from vo_runtime.cli import main
from vo_runtime.lowlight import GlobalDark, OnboardLight, parse_lowlight


def _scene(height: int = 120, width: int = 160) -> np.ndarray:
    rng = np.random.default_rng(3)
    image = np.full((height, width), 128, np.uint8)
    for _ in range(40):
        y, x = rng.integers(0, height - 10), rng.integers(0, width - 10)
        image[y:y + 8, x:x + 8] = rng.integers(0, 255)
    return image


def test_presets_and_numbers_parse():
    assert parse_lowlight(None) is None
    assert parse_lowlight("dark") == GlobalDark(2.0, 3.0, 0.3)
    assert parse_lowlight("2,3") == GlobalDark(2.0, 3.0, 1.0)
    assert isinstance(parse_lowlight("onboard"), OnboardLight)
    for bad in ("bright", "2", "2,nan", "1,2,3,4", "2,3,1.5", "-1,3"):
        with pytest.raises(VORuntimeError, match="--lowlight"):
            parse_lowlight(bad)


@pytest.mark.parametrize("darkening", [GlobalDark(), OnboardLight()], ids=["dark", "onboard"])
def test_seeded_darker_and_registered(darkening):
    image = _scene()
    first, again, other = darkening(image, seed=7), darkening(image, seed=7), darkening(image, seed=8)
    assert first.dtype == np.uint8 and first.shape == image.shape
    assert first.tobytes() == again.tobytes() and first.tobytes() != other.tobytes()
    assert first.mean() < 0.5 * image.mean()
    # registered: the darkened frame correlates best with the original at zero shift (no geometric change)
    a = (first - first.mean()).astype(np.float64)
    scores = {}
    for dy in (-2, 0, 2):
        for dx in (-2, 0, 2):
            b = np.roll(image.astype(np.float64), (dy, dx), axis=(0, 1))
            scores[(dy, dx)] = float(np.sum(a * (b - b.mean())))
    assert max(scores, key=scores.get) == (0, 0)


def test_onboard_light_is_a_spot_on_the_camera_with_vignetting_and_shot_noise():
    light = OnboardLight(blur_px=(1.0, 1.0), read_sigma=0.0)
    flat = np.full((200, 300), 200, np.uint8)
    out = light(flat, seed=0).astype(np.float64)
    centre = out[100:140, 130:170].mean()   # the spot sits a little below the centre
    corner = out[:20, :20].mean()
    assert centre > 4 * corner
    gain = light._illumination(200, 300)
    assert gain[0, 0] < 0.25 * gain.max() and gain.max() <= light.spot
    # Poisson noise: its variance grows with the level (the spot is noisier in grey levels than the dark sides)
    bright = light(np.full((64, 64), 255, np.uint8), seed=1).astype(np.float64)[24:40, 24:40]
    dim = light(np.full((64, 64), 60, np.uint8), seed=1).astype(np.float64)[24:40, 24:40]
    assert bright.var() > 2 * dim.var()


def test_cli_takes_the_presets(shared_data, tmp_path, capsys):
    for preset in ("dark", "onboard"):
        assert main(["--features", "orb", "--images", str(shared_data / "tum_fr2_desk_snippet"), "--lowlight",
                     preset, "--max-frames", "6", "--no-progress"]) == 0
    assert main(["--features", "orb", "--images", str(shared_data / "tum_fr2_desk_snippet"), "--lowlight",
                 "sunny", "--no-progress"]) == 2
    assert "preset (dark, onboard)" in capsys.readouterr().err
