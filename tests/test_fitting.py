"""First-principal-component slopes through the origin."""

from __future__ import annotations

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.fitting import principal_slope


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("slope", [0.013, 1.0, 57.0])
def test_planted_slope_with_noise_on_both_axes(rng, slope, dtype):
    x = rng.uniform(1, 100, 50_000)
    noisy_x = x + rng.normal(0, 0.2, x.size)
    noisy_y = slope * x + rng.normal(0, 0.2 * slope, x.size)
    fit = principal_slope(noisy_x.astype(dtype), noisy_y.astype(dtype))
    assert fit.slope == pytest.approx(slope, rel=1e-3)
    assert fit.count == x.size and fit.explained > 0.999


def test_units_do_not_matter(rng):
    x = rng.uniform(0, 1, 1000)
    y = 3 * x + rng.normal(0, 0.01, x.size)
    a = principal_slope(x, y).slope
    b = principal_slope(x * 1e6, y * 1e-3).slope
    assert b == pytest.approx(a * 1e-9, rel=1e-9)


def test_exact_line_has_zero_residual():
    x = np.arange(1.0, 11.0)
    fit = principal_slope(x, 2.5 * x)
    assert fit.slope == pytest.approx(2.5) and fit.residual_rms == pytest.approx(0, abs=1e-7)


@pytest.mark.parametrize(
    ("x", "y", "match"),
    [
        ([1.0], [2.0], "need at least"),
        ([1.0, np.nan], [1.0, 2.0], "NaN"),
        ([0.0, 0.0], [1.0, 2.0], "all zero"),
        ([1.0, 2.0], [1.0], "x has 2"),
    ],
)
def test_bad_input(x, y, match):
    with pytest.raises(DataError, match=match):
        principal_slope(np.array(x), np.array(y))
