"""Numerical stress of the calibration fits (issue 7): polynomial degrees up to 12 with few
points, nearly coincident and tightly clustered keypoints at coordinates in the thousands
of pixels, thin-plate spline smoothing at both ends of its range, and the principal-
component slope of :mod:`labkit.fitting` over 600 decades of magnitude.

Known answers: a field that lies in the model space (affine in (x, y), linear in λ, or a
planted Legendre polynomial of degree ≤ 12) is reproduced exactly wherever the fit has
enough points; a spline with w → 0 interpolates its keypoints and with w → ∞ is the
least-squares affine fit; proportional data give their slope. Too few points, or
positions that span no area, raise a :class:`DataError` naming the problem. Every
reported condition number is finite and below 1e10 (after normalisation).
"""

from __future__ import annotations

import numpy as np
import pytest
from _stress import assert_finite
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration import _polybasis as pb
from calibration._normalise import Normaliser
from calibration.keypoints import DispersionKeypoints
from calibration.polynomial import fit_polynomial_model
from calibration.spline import GRID_HIGH, GRID_LOW, _decompose, fit_spline_model
from labkit.errors import DataError
from labkit.fitting import principal_slope

SHAPE = (2048, 2448)
WAVELENGTHS = (450.0, 550.0, 650.0)
CONDITION_BOUND = 1e10


def affine_field(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A planted field in both model spaces: affine in (x, y) px, linear in λ nm; px."""
    band = (w - 550.0) / 100.0
    return 0.5 + 1e-3 * x - 2e-4 * y + 0.3 * band, -0.3 + 2e-4 * x + 5e-4 * y - 0.2 * band


def keypoints(
    x: np.ndarray, y: np.ndarray, w: np.ndarray, *, noise: float = 0.0, seed: int = 0
) -> DispersionKeypoints:
    """Spectral keypoints of :func:`affine_field` at (x, y, λ), plus Gaussian noise (px)."""
    dx, dy = affine_field(x, y, w)
    rng = np.random.default_rng(seed)
    dx = dx + rng.normal(0.0, noise, dx.shape) if noise else dx
    dy = dy + rng.normal(0.0, noise, dy.shape) if noise else dy
    return DispersionKeypoints(
        x, y, dx, dy, reference=550.0, image_shape=SHAPE, wavelength_nm=w
    )  # fmt: skip


def in_bands(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The positions (x, y) repeated in every band of :data:`WAVELENGTHS`."""
    count = len(WAVELENGTHS)
    return np.tile(x, count), np.tile(y, count), np.repeat(WAVELENGTHS, len(x))


def fit(kind: str, kp: DispersionKeypoints):
    """Fit a polynomial (degrees up to 12) or spline model."""
    if kind == "polynomial":
        return fit_polynomial_model(kp, max_degree_xy=12)
    return fit_spline_model(kp)


def condition(model) -> float:
    """The condition number a fitted model reports."""
    sel = model.selection
    return float(sel["condition_number"] if "condition_number" in sel else sel["condition"])


def check_reproduces(model, x: np.ndarray, y: np.ndarray, w: np.ndarray, tol: float) -> None:
    """The model equals :func:`affine_field` at (x, y, λ) to `tol` px; finite; bounded cond."""
    dx, dy = model.displacement(x, y, w)
    assert_finite(dx, dy)
    tx, ty = affine_field(x, y, w)
    error = float(np.sqrt(np.max((dx - tx) ** 2 + (dy - ty) ** 2)))
    assert error <= tol, f"largest error {error:.3g} px > {tol:g}"
    assert 1.0 <= condition(model) < CONDITION_BOUND


# -- polynomial degrees up to 12 with few points ------------------------------------------
@pytest.mark.parametrize("degree", [0, 1, 4, 8, 12])
def test_underdetermined_polynomial_is_refused(degree: int) -> None:
    m = pb.n_terms_xy(degree)
    X = np.ones((m - 1, m)) if m > 1 else np.ones((0, 1))
    with pytest.raises(DataError, match=rf"{m - 1} data points cannot determine {m} coefficients"):
        pb.solve_lstsq(X, np.ones((len(X), 2)))


@pytest.mark.parametrize("extra", [0, 5, 91])
@pytest.mark.parametrize("degree", [2, 6, 9, 12])
def test_planted_polynomial_up_to_degree_12_is_recovered(degree: int, extra: int) -> None:
    """Legendre coefficients of a planted polynomial, at pixel coordinates 0 … 2448, come
    back exactly from as few points as coefficients; the condition number stays < 1e10."""
    rng = np.random.default_rng(degree + extra)
    m = pb.n_terms_xy(degree)
    xy = np.column_stack([rng.uniform(0, SHAPE[1], m + extra), rng.uniform(0, SHAPE[0], m + extra)])
    normaliser = Normaliser.fit(xy, rng.normal(size=xy.shape))
    u = normaliser.inputs(xy)
    X = pb.design_matrix(pb.Domain.fit(u)(u), pb.exponent_table(degree))
    truth = rng.normal(size=(m, 2))
    coef, cond = pb.solve_lstsq(X, X @ truth)
    assert_finite(coef)
    assert cond < CONDITION_BOUND
    np.testing.assert_allclose(coef, truth, rtol=0, atol=1e-6)


@pytest.mark.parametrize("kind", ["polynomial", "spline"])
@pytest.mark.parametrize("per_band", [4, 5, 8])
def test_few_keypoints_reproduce_an_affine_field_exactly(kind: str, per_band: int) -> None:
    """4–8 keypoints per band, degrees tried up to 12: the planted field, everywhere."""
    rng = np.random.default_rng(per_band)
    x, y, w = in_bands(rng.uniform(0, SHAPE[1], per_band), rng.uniform(0, SHAPE[0], per_band))
    model = fit(kind, keypoints(x, y, w))
    qx, qy = rng.uniform(0, SHAPE[1], 200), rng.uniform(0, SHAPE[0], 200)
    check_reproduces(model, qx, qy, rng.uniform(450, 650, 200), tol=1e-7)
    if kind == "polynomial":  # the degrees the points cannot support were skipped, with why
        assert model.selection["skipped"]
        assert all("coefficients" in s["reason"] or "singular" in s["reason"]
                   for s in model.selection["skipped"])  # fmt: skip


@pytest.mark.parametrize(
    ("per_band", "message"),
    [(2, r"band 450 nm has 2 keypoint\(s\); each band needs at least 3"), (1, "at least 3")],
)
def test_too_few_keypoints_per_band_are_refused(per_band: int, message: str) -> None:
    x, y, w = in_bands(np.linspace(100, 2000, per_band), np.linspace(300, 1500, per_band))
    with pytest.raises(DataError, match=message):
        fit_polynomial_model(keypoints(x, y, w), max_degree_xy=12)


@pytest.mark.slow
@settings(deadline=None, max_examples=40, derandomize=True)
@given(
    per_band=st.integers(min_value=3, max_value=40),
    bands=st.integers(min_value=3, max_value=6),
    max_degree=st.integers(min_value=0, max_value=12),
    seed=st.integers(min_value=0, max_value=2**16),
)
def test_random_small_keypoint_sets_fit_or_refuse_clearly(
    per_band: int, bands: int, max_degree: int, seed: int
) -> None:
    """Any few-point configuration: a finite model with a bounded condition number that
    reproduces the affine field once degree 1 is validated, or a clear DataError."""
    rng = np.random.default_rng(seed)
    waves = np.linspace(420.0, 680.0, bands)
    x = np.tile(rng.uniform(0, SHAPE[1], per_band), bands)
    y = np.tile(rng.uniform(0, SHAPE[0], per_band), bands)
    w = np.repeat(waves, per_band)
    try:
        model = fit_polynomial_model(keypoints(x, y, w), max_degree_xy=max_degree)
    except DataError as error:
        assert "no polynomial dispersion model can be fitted" in str(error)
        return
    dx, dy = model.displacement(x, y, w)
    assert_finite(dx, dy)
    assert condition(model) < CONDITION_BOUND
    sel = model.selection
    if sel["degree_xy"] >= 1 and sel["degree_lambda"] >= 1:
        check_reproduces(model, x, y, w, tol=1e-6)


# -- nearly coincident and clustered keypoints ------------------------------------------------
@pytest.mark.parametrize("kind", ["polynomial", "spline"])
@pytest.mark.parametrize("offset", [1e-3, 1e-9, 0.0])
def test_nearly_coincident_keypoints(kind: str, offset: float) -> None:
    """Every keypoint duplicated `offset` px away: exact without noise; with 0.01 px noise
    the duplicates disagree, and the fit is finite, bounded and within the noise."""
    rng = np.random.default_rng(7)
    bx, by = rng.uniform(0, SHAPE[1], 10), rng.uniform(0, SHAPE[0], 10)
    x, y, w = in_bands(np.concatenate([bx, bx + offset]), np.concatenate([by, by + offset]))
    check_reproduces(fit(kind, keypoints(x, y, w)), x, y, w, tol=1e-7)
    noisy = fit(kind, keypoints(x, y, w, noise=0.01, seed=3))
    check_reproduces(noisy, x, y, w, tol=0.05)


@pytest.mark.parametrize("kind", ["polynomial", "spline"])
@pytest.mark.parametrize("box_px", [1000.0, 10.0, 1e-2, 1e-5])
def test_clusters_far_from_the_origin_are_normalised(kind: str, box_px: float) -> None:
    """12 keypoints in a box of `box_px` at (2400, 2000) px: exact, condition < 1e10."""
    rng = np.random.default_rng(11)
    x, y, w = in_bands(2400 + rng.uniform(0, box_px, 12), 2000 + rng.uniform(0, box_px, 12))
    check_reproduces(fit(kind, keypoints(x, y, w)), x, y, w, tol=1e-7)


@pytest.mark.parametrize("kind", ["polynomial", "spline"])
@pytest.mark.parametrize(
    "layout", ["coincident", "collinear"], ids=["all at one point", "on one line"]
)
def test_positions_spanning_no_area_are_refused(kind: str, layout: str) -> None:
    t = np.linspace(0.0, 1.0, 12)
    if layout == "coincident":
        x, y = np.full(12, 1234.5), np.full(12, 987.25)
    else:
        x, y = 100 + 2000 * t, 50 + 1500 * t
    with pytest.raises(DataError, match=r"span no area|on a line or a point|degenerate"):
        fit(kind, keypoints(*in_bands(x, y)))


@pytest.mark.slow
@settings(deadline=None, max_examples=30, derandomize=True)
@given(
    log_offset=st.floats(min_value=-12.0, max_value=1.0),
    log_box=st.floats(min_value=-4.0, max_value=3.4),
    kind=st.sampled_from(["polynomial", "spline"]),
    noise=st.sampled_from([0.0, 0.01]),
)
def test_random_clusters_and_duplicates(
    log_offset: float, log_box: float, kind: str, noise: float
) -> None:
    rng = np.random.default_rng(int(1e3 * (log_offset - log_box)) % 2**16)
    box = 10.0**log_box
    bx, by = 2000 + rng.uniform(0, box, 10), 1500 + rng.uniform(0, box, 10)
    shift = 10.0**log_offset
    x, y, w = in_bands(np.concatenate([bx, bx + shift]), np.concatenate([by, by - shift]))
    model = fit(kind, keypoints(x, y, w, noise=noise, seed=1))
    check_reproduces(model, x, y, w, tol=1e-6 if noise == 0 else 0.05)


# -- spline smoothing at both ends -------------------------------------------------------------
def smooth_field(u: np.ndarray) -> np.ndarray:
    """A non-affine field (n, 2) of normalised inputs u (n, 3)."""
    return np.column_stack([np.sin(u[:, 0]) + u[:, 2] ** 2, np.cos(u[:, 1]) * u[:, 2]])


@pytest.mark.parametrize("dim", [2, 3])
def test_spline_smoothing_ends_interpolate_and_flatten(dim: int) -> None:
    """w = machine ε interpolates the keypoints; w = 1e10 is the least-squares affine fit."""
    rng = np.random.default_rng(dim)
    u = rng.normal(size=(60, dim))
    d = smooth_field(np.column_stack([u, np.zeros((60, 3 - dim))]))
    dec = _decompose(u, d, "stress")
    basis = np.column_stack([np.ones(len(u)), u])
    # w → 0: f(u_i) = K c + P a reproduces d
    c, a = dec.solve(d, GRID_LOW)
    assert_finite(c, a)
    np.testing.assert_allclose(dec.kernel @ c + basis @ a, d, rtol=0, atol=1e-6)
    assert dec.condition(GRID_LOW) > 1.0
    # w → ∞: no kernel part left, the affine part is the least-squares plane
    c, a = dec.solve(d, GRID_HIGH)
    assert_finite(c, a)
    assert np.abs(c).max() < 1e-8
    plane, *_ = np.linalg.lstsq(basis, d, rcond=None)
    np.testing.assert_allclose(a, plane, rtol=0, atol=1e-8)
    assert dec.condition(GRID_HIGH) == pytest.approx(1.0, abs=1e-6)


def test_gcv_on_exact_data_interpolates_and_keeps_affine_fields_exact() -> None:
    """A smooth noise-free field sampled densely is interpolated (tiny w); affine data are
    reproduced exactly (at any w: they have no kernel part). Condition < 1e10."""
    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.linspace(100, 2300, 8), np.linspace(100, 1900, 6))
    x, y, w = in_bands(gx.ravel(), gy.ravel())
    affine = fit_spline_model(keypoints(x, y, w))
    check_reproduces(affine, rng.uniform(100, 2300, 50), rng.uniform(100, 1900, 50),
                     rng.uniform(450, 650, 50), tol=1e-7)  # fmt: skip
    curved_dx = np.sin(x / 400.0) + (w - 550) / 200
    curved = DispersionKeypoints(
        x, y, curved_dx, np.cos(y / 300.0), reference=550.0, image_shape=SHAPE, wavelength_nm=w
    )
    model = fit_spline_model(curved)
    assert model.selection["smoothing"] < 1e-3
    dx, dy = model.displacement(x, y, w)
    assert_finite(dx, dy)
    np.testing.assert_allclose(dx, curved_dx, atol=1e-6)
    assert condition(model) < CONDITION_BOUND


# -- the principal-component slope (HDR factors, channel sensitivities) -----------------------
@settings(deadline=None, max_examples=40, derandomize=True)
@given(
    log_scale=st.floats(min_value=-300.0, max_value=290.0),
    log_slope=st.floats(min_value=-9.0, max_value=9.0),
)
def test_principal_slope_is_exact_at_any_magnitude(log_scale: float, log_slope: float) -> None:
    """Proportional data from 1e-300 to 1e299: the slope to 1e-12, no overflow/underflow."""
    x = 10.0**log_scale * np.random.default_rng(0).uniform(1.0, 2.0, 500)
    slope = 10.0**log_slope
    fit_ = principal_slope(x, slope * x)
    assert fit_.slope == pytest.approx(slope, rel=1e-12)
    assert fit_.residual_rms < 1e-7 and fit_.explained == pytest.approx(1.0)


@pytest.mark.parametrize("scale", [1e-8, 1.0, 1e8])
def test_principal_slope_float32_agrees_with_float64(scale: float) -> None:
    rng = np.random.default_rng(1)
    x = rng.uniform(100, 4000, 10**5) * scale
    y = 3.7 * x + rng.normal(0, 5 * scale, x.shape)
    double = principal_slope(x, y).slope
    single = principal_slope(x.astype(np.float32), y.astype(np.float32)).slope
    assert single == pytest.approx(double, rel=1e-3)
    assert double == pytest.approx(3.7, rel=1e-3)


@pytest.mark.parametrize(
    ("x", "y", "message"),
    [
        (np.zeros(5), np.ones(5), "all zero"),
        (np.ones(5), np.zeros(5), "all zero"),
        (np.array([1.0, np.nan]), np.ones(2), "NaN or Inf"),
        (np.array([1.0, np.inf]), np.ones(2), "NaN or Inf"),
        (np.ones(1), np.ones(1), "need at least 2"),
        (np.array([1.0, -1.0]), np.array([1.0, 1.0]), "vertical"),
    ],
)
def test_principal_slope_refuses_degenerate_pairs(x, y, message: str) -> None:
    with pytest.raises(DataError, match=message):
        principal_slope(x, y)
