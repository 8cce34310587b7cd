"""Band selection (thesis §3.3.2) and the spectral basis operator B (§3.3.3)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erfinv

from labkit.errors import DataError
from labkit.spectra import Spectra, camera_response
from reconstruction.model.operators import dot_test
from reconstruction.model.operators.basis import (
    BandSelection,
    SpectralBasis,
    choose_bands,
    gaussian_sigma_nm,
)

NIKON_CENTRES = 424.375 + 33.75 * np.arange(8)


def gaussian(w: np.ndarray, mean: float, sd: float) -> np.ndarray:
    return np.exp(-0.5 * ((w - mean) / sd) ** 2)


# --- 1. dot test -----------------------------------------------------------------------------


@pytest.mark.parametrize("kernel", ["gaussian", "sinc"])
@pytest.mark.parametrize(
    "samples",
    [np.arange(380.0, 781.0, 1.0), NIKON_CENTRES, np.arange(380.0, 781.0, 50.0)],
    ids=["fine", "centres", "downsampled"],
)
def test_dot_test(rng, kernel, samples):
    op = SpectralBasis((5, 4), NIKON_CENTRES, samples, kernel=kernel)
    assert op.name == "B"
    assert op.domain_shape == (5, 4, 8) and op.range_shape == (5, 4, samples.size)
    assert dot_test(op, rng=rng).relative_error <= 1e-10
    assert dot_test(op, rng=rng, dtype=np.float32).relative_error <= 1e-5
    assert op.forward(rng.standard_normal(op.domain_shape).astype(np.float32)).dtype == np.float32


def test_forward_applies_the_matrix_per_pixel(rng):
    op = SpectralBasis((3, 2), NIKON_CENTRES, np.arange(400.0, 700.0, 5.0))
    x = rng.standard_normal(op.domain_shape)
    np.testing.assert_allclose(op.forward(x)[2, 1], op.matrix @ x[2, 1], rtol=1e-12)


# --- 2. choose_bands -------------------------------------------------------------------------


def test_choose_bands_on_gaussians_matches_hand_values():
    # Two Gaussian channels on a long 1 nm grid (DFT bin 1/10001 cycles/nm).
    w = np.arange(0.0, 10001.0)
    narrow_sd, wide_sd = 20.0, 40.0
    response = Spectra(
        w, np.stack([gaussian(w, 5000, narrow_sd), gaussian(w, 5100, wide_sd)], 1), ("a", "b")
    )
    selection = choose_bands(response)
    # Support: |λ − μ| ≤ sd·sqrt(2 ln 20) for each channel, union, snapped to the 1 nm grid.
    half = np.sqrt(2 * np.log(20.0))
    lo, hi = 5000 - narrow_sd * half, 5100 + wide_sd * half  # 4975.52, 5198.06
    assert selection.support_nm[0] == pytest.approx(lo, abs=1.0)
    assert selection.support_nm[1] == pytest.approx(hi, abs=1.0)
    # Bandlimit: |Q̂(f)|² ∝ exp(−4π²sd²f²) holds erf(2π sd f) of its power below f, so the
    # narrow channel decides: f = erfinv(0.95)/(2π·20) = 0.011029 cycles/nm (± 2 %: DFT bin
    # quantisation 1e-4 and the excluded zero-frequency bin).
    expected = erfinv(0.95) / (2 * np.pi * narrow_sd)
    assert selection.bandlimit_cycles_per_nm == pytest.approx(expected, rel=0.02)
    # Centres: Nyquist spacing, floor(width/spacing)+1 of them, centred in the support.
    spacing = 0.5 / selection.bandlimit_cycles_per_nm
    assert selection.spacing_nm == pytest.approx(spacing)
    np.testing.assert_allclose(np.diff(selection.centres_nm), spacing)
    width = selection.support_nm[1] - selection.support_nm[0]
    assert selection.n_bands == int(width // spacing) + 1 == 6
    assert np.mean(selection.centres_nm) == pytest.approx(np.mean(selection.support_nm))


def test_choose_bands_bandlimit_is_the_first_dft_bin_reaching_the_power_fraction():
    # A pure cosine of 5 cycles over the grid: all non-DC power sits in bin 5.
    w = np.arange(400.0, 800.0, 4.0)  # 100 samples, bin = 1/400 cycles/nm
    values = 1.0 + 0.5 * np.cos(2 * np.pi * 5 * np.arange(100) / 100)
    selection = choose_bands(Spectra(w, values, ("c",)))
    assert selection.bandlimit_cycles_per_nm == pytest.approx(5 / 400)
    assert selection.support_nm == (400.0, 796.0)  # never below 5 % of the peak


def test_choose_bands_on_nikon_5100():
    selection = choose_bands(camera_response("Nikon 5100 (NPL)"))
    assert isinstance(selection, BandSelection)
    # Thesis: 418–667 nm, 35.5 nm spacing, 8 bands (its copy of the data); ours:
    assert selection.support_nm == (415.0, 670.0)
    assert 380.0 <= selection.support_nm[0] < selection.support_nm[1] <= 720.0
    assert selection.bandlimit_cycles_per_nm == pytest.approx(6 / 405)  # DFT bin 6 of 81·5 nm
    assert selection.spacing_nm == pytest.approx(33.75)
    assert selection.n_bands == 8
    np.testing.assert_allclose(selection.centres_nm, NIKON_CENTRES)


# --- 3. B: kernel, reproduction, extrapolation -----------------------------------------------


def test_gaussian_kernel_matches_the_bandlimit():
    # σ such that erf(2πσ · 1/(2Δv)) = 0.95, i.e. σ = erfinv(0.95)·Δv/π ≈ 0.4411 Δv.
    assert gaussian_sigma_nm(33.75) == pytest.approx(0.441148 * 33.75, rel=1e-5)
    op = SpectralBasis((1, 1), NIKON_CENTRES, NIKON_CENTRES)
    m = op.matrix
    sigma = op.sigma_nm
    peak = 33.75 / (sigma * np.sqrt(2 * np.pi))  # (3.12) scaled by Δv
    np.testing.assert_allclose(np.diag(m)[1:-1], peak, rtol=1e-12)
    assert peak == pytest.approx(0.9044, abs=1e-4)
    np.testing.assert_allclose(
        np.diag(m, 1)[1:-1], peak * np.exp(-0.5 * (33.75 / sigma) ** 2), rtol=1e-12
    )
    inner = m[:, 1:-1]  # the outer columns also carry the extrapolation weights
    np.testing.assert_allclose(inner[1:-1], inner[1:-1].T, atol=1e-15)
    assert m[1, 0] == pytest.approx(m[0, 1] + peak * np.exp(-0.5 * (2 * 33.75 / sigma) ** 2))


def test_sinc_kernel_at_the_centres_is_the_identity():
    op = SpectralBasis((1, 1), NIKON_CENTRES, NIKON_CENTRES, kernel="sinc")
    np.testing.assert_allclose(op.matrix, np.eye(8), atol=1e-12)


def test_constant_coefficients_give_the_poisson_ripple():
    # Δv Σ_n N(t − nΔv; σ²) = 1 + 2 Σ_k exp(−2π²σ²k²/Δv²) cos(2πk t/Δv)  (Poisson summation).
    w = np.arange(380.0, 781.0)
    op = SpectralBasis((1, 1), NIKON_CENTRES, w)
    sigma, dv = op.sigma_nm, op.spacing_nm
    t = w - NIKON_CENTRES[0]
    k = np.arange(1, 6)[:, None]
    expected = 1 + 2 * np.sum(
        np.exp(-2 * np.pi**2 * sigma**2 * k**2 / dv**2) * np.cos(2 * np.pi * k * t / dv), 0
    )
    np.testing.assert_allclose(op.matrix.sum(axis=1), expected, rtol=1e-12)
    assert np.ptp(expected) / 2 == pytest.approx(2 * np.exp(-2 * np.pi**2 * 0.441148**2), 0.01)


@pytest.mark.parametrize(("kernel", "tolerance"), [("gaussian", 0.04), ("sinc", 0.01)])
def test_b_reproduces_a_smooth_spectrum(kernel, tolerance):
    # Least-squares projection onto the Nikon centres, evaluated at 1 nm within their range.
    # Measured relative RMS: Gaussian 3.35 % (the ±4.3 % kernel ripple), sinc 0.48 %.
    w = np.arange(NIKON_CENTRES[0], NIKON_CENTRES[-1] + 0.5, 1.0)
    spectrum = 1.0 + 0.5 * np.sin(2 * np.pi * (w - 400.0) / 300.0)
    op = SpectralBasis((1, 1), NIKON_CENTRES, w, kernel=kernel)
    coefficients, *_ = np.linalg.lstsq(op.matrix, spectrum, rcond=None)
    fitted = op.forward(coefficients[None, None, :])[0, 0]
    error = np.sqrt(np.mean((fitted - spectrum) ** 2) / np.mean(spectrum**2))
    assert error <= tolerance


@pytest.mark.parametrize(("kernel", "rtol"), [("gaussian", 1e-12), ("sinc", 1e-3)])
def test_constant_extrapolation_equals_explicit_padding(rng, kernel, rtol):
    # B equals (3.10) applied to the coefficients padded with copies of their end values.
    w = np.arange(360.0, 831.0, 1.0)  # colour-integration grid, beyond the centres
    op = SpectralBasis((1, 1), NIKON_CENTRES, w, kernel=kernel)
    dv = op.spacing_nm
    pad = 300 if kernel == "gaussian" else 8000
    padded_centres = NIKON_CENTRES[0] + dv * np.arange(-pad, 8 + pad)
    coefficients = rng.uniform(0.5, 1.5, 8)
    padded = np.concatenate([[coefficients[0]] * pad, coefficients, [coefficients[-1]] * pad])
    offsets = w[:, None] - padded_centres[None, :]
    if kernel == "gaussian":
        sigma = op.sigma_nm
        k = dv / (sigma * np.sqrt(2 * np.pi)) * np.exp(-0.5 * (offsets / sigma) ** 2)
    else:
        k = np.sinc(offsets / dv)
    reference = k @ padded
    # The operator truncates the padding at 12 σ (Gaussian: negligible) or 2000 spacings
    # beyond the samples (sinc: the alternating tail leaves ≈ 1e-4).
    got = op.forward(coefficients[None, None, :])[0, 0]
    np.testing.assert_allclose(got, reference, rtol=rtol)


def test_far_outside_only_the_end_coefficient_matters(rng):
    w = np.arange(300.0, 901.0, 1.0)
    op = SpectralBasis((1, 1), NIKON_CENTRES, w)
    far = (w < NIKON_CENTRES[0] - 10 * op.sigma_nm) | (w > NIKON_CENTRES[-1] + 10 * op.sigma_nm)
    a = rng.uniform(0.5, 1.5, 8)
    b = a.copy()
    b[1:-1] = rng.uniform(0.5, 1.5, 6)  # change only the interior coefficients
    fa = op.forward(a[None, None, :])[0, 0]
    fb = op.forward(b[None, None, :])[0, 0]
    np.testing.assert_array_equal(fa[far], fb[far])
    # ... and there the spectrum is the end value times the (Δv-periodic) kernel sum.
    ones = op.forward(np.ones((1, 1, 8)))[0, 0]
    low = far & (w < 500)
    np.testing.assert_allclose(fa[low], a[0] * ones[low], rtol=1e-14)


def test_downsampling_uses_the_sinc_lowpass():
    # (3.11): samples coarser than the centres → B = B_{b→N} B_{b→b}.
    coarse = np.arange(380.0, 781.0, 50.0)
    op = SpectralBasis((1, 1), NIKON_CENTRES, coarse)
    at_centres = SpectralBasis((1, 1), NIKON_CENTRES, NIKON_CENTRES).matrix
    assert op.matrix.shape == (coarse.size, 8)
    # A constant spectrum at the centres stays constant (the sinc partition of unity).
    np.testing.assert_allclose(op.matrix.sum(1), at_centres.sum(1)[1], rtol=1e-3)


# --- 4. bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "centres",
    [
        [500.0, 450.0, 600.0],  # not increasing
        [400.0, 400.0, 450.0],  # repeated
        [400.0, 450.0, 520.0],  # uneven
        [500.0],  # too few
        [np.nan, 450.0, 500.0],
    ],
)
def test_bad_centres(centres):
    with pytest.raises(DataError):
        SpectralBasis((2, 2), np.array(centres), np.arange(400.0, 600.0))


@pytest.mark.parametrize(
    "samples",
    [
        np.arange(-10.0, 500.0, 5.0),  # negative wavelengths
        np.array([400.0, 5000.0]),  # 4.3 µm beyond the centres
        np.array([500.0, 450.0]),  # decreasing
        np.array([]),
    ],
)
def test_bad_samples(samples):
    with pytest.raises(DataError):
        SpectralBasis((2, 2), NIKON_CENTRES, samples)


def test_bad_kernel_and_shape():
    with pytest.raises(DataError):
        SpectralBasis((2, 2), NIKON_CENTRES, NIKON_CENTRES, kernel="box")
    with pytest.raises(DataError):
        SpectralBasis((0, 2), NIKON_CENTRES, NIKON_CENTRES)


def test_bad_responses():
    w = np.arange(400.0, 700.0, 5.0)
    with pytest.raises(DataError):  # empty: no wavelengths at all
        choose_bands(Spectra(np.array([]), np.zeros((0, 3)), ("R", "G", "B")))
    with pytest.raises(DataError, match="no channels"):
        choose_bands(Spectra(w, np.zeros((w.size, 0)), ()))
    with pytest.raises(DataError, match="zero everywhere"):
        choose_bands(Spectra(w, np.zeros((w.size, 3)), ("R", "G", "B")))
    with pytest.raises(DataError):
        choose_bands(camera_response("Nikon 5100 (NPL)"), support_fraction=1.5)
    with pytest.raises(DataError):
        choose_bands(camera_response("Nikon 5100 (NPL)"), power_fraction=0.0)
