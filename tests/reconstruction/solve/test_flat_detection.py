"""Noise-aware flat-patch detection: the noise estimate and the texture statistic."""

import numpy as np
import pytest

from reconstruction.solve.patches import largest_step, noise_sigma, texture


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


def _corner_disk(size: int = 64, radius: float = 14.0) -> np.ndarray:
    """A level of 1 with a dark disk (0.2) centred beyond the patch's corner: its edge
    crosses the corner and covers about 3 % of the pixels."""
    rows, cols = np.mgrid[0:size, 0:size]
    inside = (rows + 4.0) ** 2 + (cols + 4.0) ** 2 <= radius**2
    return np.where(inside, 0.2, 1.0)


def test_an_edge_across_a_corner_is_a_step_though_the_95th_percentile_misses_it() -> None:
    """The disk chart's case: the edge is under 5 % of the differences, so the percentile
    reads the patch as flat (below the 1 % default); the largest step sees the full 0.8."""
    sigma = 0.002
    patch = _corner_disk() + np.random.default_rng(6).normal(0.0, sigma, (64, 64))
    assert texture(patch, sigma) < 0.01
    assert largest_step(patch, sigma) > 0.5


@pytest.mark.parametrize("sigma", [0.0005, 0.002, 0.02])
def test_largest_step_of_pure_noise_stays_within_its_allowance(sigma: float) -> None:
    """20 flat noisy patches (64 × 64): no step above the noise allowance."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        assert largest_step(1.0 + rng.normal(0.0, sigma, (64, 64)), sigma) == 0.0
    assert largest_step(np.ones((1, 1))) == 0.0
