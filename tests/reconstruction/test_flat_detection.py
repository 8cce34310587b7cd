"""Noise-aware flat-patch detection: the noise estimate and the texture statistic."""

import numpy as np
import pytest

from reconstruction.patches import noise_sigma, texture


def _shaded(shape=(128, 160)) -> np.ndarray:
    """A smooth vignetted level around 1 with a vertical step edge: no texture, one edge."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    level = 1.0 - 0.3 * ((rows / shape[0] - 0.5) ** 2 + (cols / shape[1] - 0.5) ** 2)
    level[:, cols[0] >= shape[1] // 2] *= 0.5
    return level


@pytest.mark.parametrize("sigma", [0.002, 0.01, 0.05])
def test_noise_sigma_recovers_planted_noise_within_15_percent(sigma: float) -> None:
    rng = np.random.default_rng(3)
    raw = _shaded() + rng.normal(0.0, sigma, (128, 160))
    assert noise_sigma(raw) == pytest.approx(sigma, rel=0.15)


def test_noise_sigma_of_a_clean_image_is_tiny_and_small_images_give_zero() -> None:
    assert noise_sigma(_shaded()) < 1e-4
    assert noise_sigma(np.ones((16, 16))) == 0.0


def test_texture_above_noise_separates_noisy_flat_from_textured() -> None:
    """0.2 % noise alone reads as 0.6 % plain texture (above no threshold of 0.5 %), and as
    nothing above the noise; a 5 %-contrast pattern stays textured."""
    rng = np.random.default_rng(4)
    sigma = 0.002
    flat = 1.0 + rng.normal(0.0, sigma, (48, 48))
    cols = np.mgrid[0:48, 0:48][1]
    pattern = 1.0 + 0.05 * np.sin(2 * np.pi * cols / 12) + rng.normal(0.0, sigma, (48, 48))
    assert texture(flat) > 0.005
    assert texture(flat, sigma) < 1e-3
    assert texture(pattern, sigma) > 0.03
