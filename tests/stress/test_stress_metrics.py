"""Numerical stress of the evaluation metrics (issue 7): near-zero denominators, intensities
from 1e-8 to 1e8 (and float64 to 1e±300), float32 against float64, tiny and odd images.

Known answer: an estimate ``Î = (1 + δ) I`` has MRAE = |δ| on every value above the floor,
GOF = 1, RMSE = |δ| · RMS(I), and registration factor 1 / (1 + δ) per band. Values at or
below the floor are counted as excluded, never divided by; every output is finite.
"""

from __future__ import annotations

import numpy as np
import pytest
from _stress import assert_finite
from hypothesis import given, settings
from hypothesis import strategies as st

from labkit.errors import DataError
from reconstruction.evaluate.metrics import colour_errors, registration_scale, spectral_errors

SHAPE = (16, 20, 5)


def planted(shape: tuple[int, ...] = SHAPE, seed: int = 0) -> np.ndarray:
    """A positive image (0.1 … 1)."""
    return np.random.default_rng(seed).uniform(0.1, 1.0, shape)


def check_spectral(result, n_values: int) -> None:
    """Every scalar of a SpectralErrors is finite; the excluded counts are in range."""
    values = [result.mrae, result.rmse_pixel, result.rmse_global, result.gof, result.floor]
    if result.ssim is not None:
        values.append(result.ssim)
    assert_finite(np.array(values, dtype=np.float64))
    assert_finite(result.mrae_map.compressed(), result.rmse_map.compressed())
    assert_finite(result.gof_map.compressed())
    assert 0 <= result.mrae_excluded < n_values


# -- near-zero denominators ----------------------------------------------------------------
@settings(deadline=None, max_examples=30, derandomize=True)
@given(
    zero_rows=st.integers(min_value=0, max_value=15),
    tiny_rows=st.integers(min_value=0, max_value=15),
    log_tiny=st.floats(min_value=-300.0, max_value=-4.0),
    delta=st.floats(min_value=-0.5, max_value=0.5),
)
def test_near_zero_true_values_are_excluded_and_counted(
    zero_rows: int, tiny_rows: int, log_tiny: float, delta: float
) -> None:
    truth = planted()
    truth[:zero_rows] = 0.0
    truth[zero_rows : zero_rows + tiny_rows] *= 10.0**log_tiny
    estimate = truth * (1 + delta)
    below = int(np.count_nonzero(np.abs(truth) <= 1e-3 * np.abs(truth).max()))
    if below == truth.size:
        with pytest.raises(DataError, match=r"undefined: every true value .* near-zero"):
            spectral_errors(truth, estimate, ssim=False)
        return
    result = spectral_errors(truth, estimate, ssim=False)
    check_spectral(result, truth.size)
    assert result.mrae_excluded == below
    assert result.mrae == pytest.approx(abs(delta), rel=1e-9, abs=1e-15)
    assert result.gof == pytest.approx(1.0, abs=1e-12)


def test_zero_estimate_is_a_total_miss_not_a_nan() -> None:
    truth = planted()
    result = spectral_errors(truth, np.zeros_like(truth), ssim=False)
    check_spectral(result, truth.size)
    assert result.mrae == pytest.approx(1.0) and result.gof == 0.0


@pytest.mark.parametrize("metric", [spectral_errors, colour_errors])
def test_all_zero_truth_is_refused(metric) -> None:
    truth = np.zeros((12, 12, 3))
    with pytest.raises(DataError, match=r"undefined: every true value"):
        metric(truth, planted((12, 12, 3)), ssim=False)


def test_colour_excluded_values_are_counted_per_channel() -> None:
    truth = planted((12, 14, 3))
    truth[:3, :, 0] = 0.0
    truth[:, :2, 2] = 1e-9
    result = colour_errors(truth, 1.1 * truth, ssim=False)
    assert result.mrae_excluded == (3 * 14, 0, 12 * 2)
    np.testing.assert_allclose(result.mrae, 0.1, rtol=1e-9)
    assert_finite(np.array(result.rmse), np.array(result.mrae))


# -- intensities and precision ---------------------------------------------------------------
@settings(deadline=None, max_examples=30, derandomize=True)
@given(
    log_scale=st.floats(min_value=-300.0, max_value=300.0),
    delta=st.floats(min_value=0.001, max_value=0.5),
)
def test_metrics_are_scale_invariant_from_1e_minus_300_to_1e300(
    log_scale: float, delta: float
) -> None:
    """No overflow or underflow: relative metrics unchanged, RMSE scales (float64)."""
    scale = 10.0**log_scale
    truth = planted()
    estimate = truth * (1 + delta)
    result = spectral_errors(truth * scale, estimate * scale, register=True)
    check_spectral(result, truth.size)
    assert result.mrae == pytest.approx(0.0, abs=1e-12)  # registration undoes 1 + δ
    np.testing.assert_allclose(result.scale, 1 / (1 + delta), rtol=1e-12)
    plain = spectral_errors(truth * scale, estimate * scale, ssim=False)
    assert plain.mrae == pytest.approx(delta, rel=1e-9)
    rms = float(np.sqrt(np.mean(truth**2)))
    assert plain.rmse_global / scale == pytest.approx(delta * rms, rel=1e-9)
    assert plain.floor / scale == pytest.approx(1e-3 * truth.max(), rel=1e-12)
    colour = colour_errors(truth[..., :3] * scale, estimate[..., :3] * scale, ssim=False)
    np.testing.assert_allclose(colour.mrae, delta, rtol=1e-9)


@pytest.mark.parametrize("scale", [1e-8, 1.0, 1e8])
def test_float32_and_float64_images_agree(scale: float) -> None:
    rng = np.random.default_rng(3)
    truth = planted() * scale
    estimate = truth * (1 + 0.05 * rng.standard_normal(truth.shape))
    double = spectral_errors(truth, estimate, register=True)
    single = spectral_errors(truth.astype(np.float32), estimate.astype(np.float32), register=True)
    for name in ("mrae", "rmse_pixel", "rmse_global", "gof", "ssim"):
        assert getattr(single, name) == pytest.approx(getattr(double, name), rel=1e-3), name
    c64 = colour_errors(truth[..., :3], estimate[..., :3])
    c32 = colour_errors(truth[..., :3].astype(np.float32), estimate[..., :3].astype(np.float32))
    np.testing.assert_allclose(c32.rmse, c64.rmse, rtol=1e-3)
    np.testing.assert_allclose(c32.ssim, c64.ssim, rtol=1e-3)


@pytest.mark.parametrize("log_scale", [-300, -160, -8, 8, 160, 300])
def test_registration_scale_recovers_planted_factors(log_scale: int) -> None:
    truth = planted((30, 4)) * 10.0**log_scale
    factors = np.array([0.5, 1.0, 2.0, 1e3])
    result = registration_scale(truth, truth / factors)
    assert_finite(result)
    np.testing.assert_allclose(result, factors, rtol=1e-12)


# -- tiny, odd and flat images ----------------------------------------------------------------
@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 2, 3), (3, 5, 3), (7, 9, 3), (1, 100, 3)])
def test_small_images_need_ssim_off_and_then_work(shape: tuple[int, int, int]) -> None:
    truth = planted(shape)
    with pytest.raises(DataError, match=r"at least 11 × 11 px|positive dynamic range"):
        spectral_errors(truth, 1.01 * truth)
    result = spectral_errors(truth, 1.01 * truth, ssim=False)
    check_spectral(result, truth.size)
    assert result.mrae == pytest.approx(0.01, rel=1e-9)
    colour = colour_errors(truth, 1.01 * truth, ssim=False)
    np.testing.assert_allclose(colour.mrae, 0.01, rtol=1e-9)


def test_constant_truth_needs_a_data_range_for_ssim() -> None:
    truth = np.full((12, 12, 3), 0.4)
    with pytest.raises(DataError, match=r"positive dynamic range.*constant"):
        spectral_errors(truth, truth)
    result = spectral_errors(truth, truth, data_range=1.0)
    check_spectral(result, truth.size)
    assert result.ssim == pytest.approx(1.0) and result.mrae == 0.0


@pytest.mark.slow
@settings(deadline=None, max_examples=60, derandomize=True)
@given(
    rows=st.integers(min_value=11, max_value=40),
    cols=st.integers(min_value=11, max_value=40),
    bands=st.integers(min_value=1, max_value=12),
    log_scale=st.floats(min_value=-8.0, max_value=8.0),
    zero_fraction=st.floats(min_value=0.0, max_value=0.9),
    seed=st.integers(min_value=0, max_value=2**16),
)
def test_random_images_give_finite_metrics(
    rows: int, cols: int, bands: int, log_scale: float, zero_fraction: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    truth = planted((rows, cols, bands), seed) * 10.0**log_scale
    truth[rng.uniform(size=truth.shape) < zero_fraction] = 0.0
    estimate = truth + 0.01 * 10.0**log_scale * rng.standard_normal(truth.shape)
    if np.ptp(truth) == 0 or not truth.any():
        return
    result = spectral_errors(truth, estimate, register=bool(seed % 2))
    check_spectral(result, truth.size)
    assert 0.0 <= result.gof <= 1.0 and -1.0 <= result.ssim <= 1.0
