"""Operators M (mosaic), Ω (spectral → raw colour) and the priors' difference operators."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import normalised_colour

from labkit.cfa import CFA_LAYOUTS, mosaic
from labkit.errors import DataError
from labkit.spectra import Spectra
from reconstruction.model.operators import dot_test
from reconstruction.model.operators.colour import SpectralToColour
from reconstruction.model.operators.mosaic import Mosaic
from reconstruction.model.operators.priors import (
    Gradient,
    Laplacian,
    SpectralDifference,
    SpectralGradient,
    SpectralRoughness,
    smoothest_metamer,
)

SHAPE = (5, 7)  # odd on purpose: the Bayer tiling is cropped
BANDS = 6


def _operators(boundary="periodic"):
    rng = np.random.default_rng(7)
    shape3 = (*SHAPE, BANDS)
    return [
        SpectralToColour(SHAPE, rng.uniform(0, 1, (3, BANDS))),
        Gradient(shape3, boundary=boundary),
        SpectralGradient(shape3, boundary=boundary),
        Laplacian(shape3, boundary=boundary),
    ]


ALL_OPERATORS = (
    [Mosaic(SHAPE, cfa) for cfa in CFA_LAYOUTS]
    + _operators("periodic")
    + _operators("neumann")
    + [SpectralDifference((*SHAPE, BANDS))]
    + [SpectralRoughness((*SHAPE, BANDS), np.arange(1.0, 1.0 + 3 * BANDS).reshape(3, BANDS))]
    + [
        Mosaic(SHAPE, cfa) @ SpectralToColour(SHAPE, np.arange(3 * BANDS).reshape(3, BANDS))
        for cfa in CFA_LAYOUTS
    ]
)


def _label(op) -> str:
    tag = getattr(op, "cfa", None) or getattr(op, "boundary", None)
    tag = tag or getattr(getattr(op, "outer", None), "cfa", "")
    return f"{op.name}-{tag}" if tag else op.name


IDS = [_label(op) for op in ALL_OPERATORS]


# --- 1. adjoints -----------------------------------------------------------------------


@pytest.mark.parametrize("op", ALL_OPERATORS, ids=IDS)
def test_dot_test_float64(op, rng):
    for _ in range(3):
        assert dot_test(op, rng=rng).relative_error <= 1e-10


@pytest.mark.parametrize("op", ALL_OPERATORS, ids=IDS)
def test_dot_test_float32_keeps_dtype(op, rng):
    assert dot_test(op, rng=rng, dtype=np.float32).relative_error <= 1e-5
    x = rng.standard_normal(op.domain_shape).astype(np.float32)
    assert op.forward(x).dtype == np.float32
    y = rng.standard_normal(op.range_shape).astype(np.float32)
    assert op.adjoint(y).dtype == np.float32


@pytest.mark.parametrize("boundary", ["periodic", "neumann"])
def test_laplacian_is_gradient_gram(boundary, rng):
    shape = (*SHAPE, 3)
    grad, lap = Gradient(shape, boundary=boundary), Laplacian(shape, boundary=boundary)
    u = rng.standard_normal(shape)
    np.testing.assert_allclose(lap.forward(u), grad.adjoint(grad.forward(u)), atol=1e-12)


# --- 2. mosaic -------------------------------------------------------------------------


@pytest.mark.parametrize("cfa", CFA_LAYOUTS)
def test_mosaic_picks_the_filter_channel(cfa, rng):
    image = rng.standard_normal((*SHAPE, 3))
    op = Mosaic(SHAPE, cfa)
    raw = op.forward(image)
    np.testing.assert_array_equal(raw, mosaic(image, cfa))
    # explicit known answer: channel of pixel (y, x) is the layout letter at (y % 2, x % 2)
    letters = {"R": 0, "G": 1, "B": 2}
    for y in range(SHAPE[0]):
        for x in range(SHAPE[1]):
            channel = letters[cfa[2 * (y % 2) + (x % 2)]]
            assert raw[y, x] == image[y, x, channel]
    # Mᵀ scatters back into that channel only, so M Mᵀ = I
    back = op.adjoint(raw)
    np.testing.assert_array_equal(op.forward(back), raw)
    assert np.count_nonzero(back) == raw.size
    np.testing.assert_array_equal(back.sum(axis=2), raw)


def test_rggb_top_left_block():
    image = np.zeros((2, 2, 3))
    image[..., 0], image[..., 1], image[..., 2] = 1.0, 2.0, 3.0
    np.testing.assert_array_equal(Mosaic((2, 2), "RGGB").forward(image), [[1, 2], [2, 3]])
    np.testing.assert_array_equal(Mosaic((2, 2), "gbrg").forward(image), [[2, 3], [1, 2]])


def test_mosaic_rejects_bad_layout_and_shape():
    with pytest.raises(DataError, match="RGGB"):
        Mosaic(SHAPE, "RGBG")
    with pytest.raises(DataError, match="rows, cols"):
        Mosaic((4, 0), "RGGB")
    with pytest.raises(DataError, match="expects shape"):
        Mosaic(SHAPE, "RGGB").forward(np.zeros((*SHAPE, 4)))


# --- 3. spectral → colour --------------------------------------------------------------


def _linear_response():
    """Q_c(λ) = a_c + b_c λ on 380–780 nm, labelled B, G, R (out of order on purpose)."""
    wl = np.linspace(380.0, 780.0, 81)
    a = np.array([0.1, 0.4, 0.7])  # R, G, B
    b = np.array([1e-3, -2e-4, 5e-4])
    values = a[None, :] + b[None, :] * wl[:, None]
    return Spectra(wl, values[:, ::-1], ("B", "G", "R")), a, b


def test_from_response_flat_spectrum_is_the_trapezoid_integral():
    response, a, b = _linear_response()
    bands = np.array([400.0, 410.0, 430.0, 460.0, 500.0, 560.0, 640.0, 700.0])  # uneven
    op = SpectralToColour.from_response((2, 3), bands, response)
    colour = op.forward(np.ones((2, 3, bands.size)))
    # the trapezoid rule is exact for a linear response: ∫ a + bλ dλ over 400–700 nm
    lo, hi = bands[0], bands[-1]
    exact = a * (hi - lo) + b * (hi**2 - lo**2) / 2
    np.testing.assert_allclose(colour, np.broadcast_to(exact, (2, 3, 3)), rtol=1e-12)


def test_from_response_matches_independent_trapezoid(rng):
    wl = np.linspace(380.0, 720.0, 35)
    q = rng.uniform(0.0, 1.0, (wl.size, 3))
    response = Spectra(wl, q, ("R", "G", "B"))
    bands = np.linspace(400.0, 700.0, 16)
    spectrum = rng.uniform(0.5, 2.0, bands.size)
    op = SpectralToColour.from_response((1, 1), bands, response)
    got = op.forward(np.broadcast_to(spectrum, (1, 1, bands.size)).copy())[0, 0]
    want = [np.trapezoid(np.interp(bands, wl, q[:, c]) * spectrum, bands) for c in range(3)]
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_from_response_must_cover_the_bands():
    response, _, _ = _linear_response()
    with pytest.raises(DataError, match=r"380–780 nm.*360–700 nm"):
        SpectralToColour.from_response(SHAPE, np.linspace(360.0, 700.0, 10), response)
    with pytest.raises(DataError, match="R, G, B"):
        two = Spectra(np.array([400.0, 700.0]), np.ones((2, 2)), ("X", "Y"))
        SpectralToColour.from_response(SHAPE, np.linspace(400.0, 700.0, 4), two)
    with pytest.raises(DataError, match=r"\(3, bands\)"):
        SpectralToColour(SHAPE, np.ones((BANDS, 3)))


# --- 4. difference operators: known answers --------------------------------------------


def test_gradient_of_a_ramp():
    rows, cols = SHAPE
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    u = np.stack([3 * x + 5 * y, -2 * x + y], axis=-1)  # two channels
    g = Gradient((rows, cols, 2)).forward(u)
    assert g.shape == (rows, cols, 2, 2)
    for c, (sx, sy) in enumerate([(3, 5), (-2, 1)]):
        np.testing.assert_allclose(g[:, :-1, c, 0], sx)
        np.testing.assert_allclose(g[:-1, :, c, 1], sy)
        # periodic wrap: the last difference jumps back to the first column/row
        np.testing.assert_allclose(g[:, -1, c, 0], -sx * (cols - 1))
        np.testing.assert_allclose(g[-1, :, c, 1], -sy * (rows - 1))
    gn = Gradient((rows, cols, 2), boundary="neumann").forward(u)
    np.testing.assert_allclose(gn[:, :-1, :, 0], g[:, :-1, :, 0])
    np.testing.assert_allclose(gn[:-1, :, :, 1], g[:-1, :, :, 1])
    np.testing.assert_array_equal(gn[:, -1, :, 0], 0.0)
    np.testing.assert_array_equal(gn[-1, :, :, 1], 0.0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_periodic_differences_are_rolls(rng, dtype):
    """Forward and adjoint periodic differences along every axis equal their np.roll
    definitions exactly, in the input's precision, and so do the gradient and its adjoint."""
    from reconstruction.model.operators.priors import difference, difference_adjoint

    u = rng.normal(size=(5, 6, 3)).astype(dtype)
    for axis in range(u.ndim):
        forward = difference(u, axis, "periodic")
        assert forward.dtype == dtype
        np.testing.assert_array_equal(forward, np.roll(u, -1, axis=axis) - u)
        np.testing.assert_array_equal(
            difference_adjoint(u, axis, "periodic"), np.roll(u, 1, axis=axis) - u
        )
    gradient = Gradient(u.shape)
    expected = np.stack([np.roll(u, -1, axis=1) - u, np.roll(u, -1, axis=0) - u], axis=-1)
    np.testing.assert_array_equal(gradient.forward(u), expected)
    g = rng.normal(size=(*u.shape, 2)).astype(dtype)
    adjoint = (np.roll(g[..., 0], 1, axis=1) - g[..., 0]) + (
        np.roll(g[..., 1], 1, axis=0) - g[..., 1]
    )
    np.testing.assert_array_equal(gradient.adjoint(g), adjoint)


@pytest.mark.parametrize("boundary", ["periodic", "neumann"])
def test_laplacian_of_a_quadratic(boundary):
    rows, cols = 6, 8
    y, x = np.mgrid[0:rows, 0:cols].astype(float)
    u = (x**2 + 2 * y**2 + 3 * x * y + x)[..., None]
    lap = Laplacian((rows, cols, 1), boundary=boundary).forward(u)[..., 0]
    # (3.20): 4u − neighbours = −(∂²x + ∂²y) = −(2 + 4)
    np.testing.assert_allclose(lap[1:-1, 1:-1], -6.0, atol=1e-12)


def test_spectral_gradient_known_answers(rng):
    rows, cols, k = 4, 5, 4
    f = rng.standard_normal((rows, cols))
    flat = np.repeat(f[..., None], k, axis=2)  # constant along λ
    for boundary in ("periodic", "neumann"):
        op = SpectralGradient((rows, cols, k), boundary=boundary)
        out = op.forward(flat)
        assert out.shape == (rows, cols, k - 1, 2)
        np.testing.assert_array_equal(out, 0.0)
    # linear in λ: ∇λ∇xy (b·f) = ∇xy f in every band pair
    ramp = f[..., None] * np.arange(k)
    out = SpectralGradient((rows, cols, k)).forward(ramp)
    grad_f = Gradient((rows, cols, 1)).forward(f[..., None])
    np.testing.assert_allclose(out, np.repeat(grad_f, k - 1, axis=2), atol=1e-12)
    d = SpectralGradient((rows, cols, k)).spectral_matrix
    np.testing.assert_array_equal(d @ np.arange(k), np.ones(k - 1))


def test_spectral_difference_known_answers(rng):
    rows, cols, k = 3, 4, 5
    op = SpectralDifference((rows, cols, k))
    f = rng.standard_normal((rows, cols))
    assert op.range_shape == (rows, cols, k - 1)
    np.testing.assert_array_equal(op.forward(np.repeat(f[..., None], k, axis=2)), 0.0)
    ramp = f[..., None] * np.arange(k)  # slope f per band
    np.testing.assert_allclose(op.forward(ramp), np.repeat(f[..., None], k - 1, axis=2))
    # DᵀD is the path-graph Laplacian along λ: [1, −1, …], [−1, 2, −1], …, [… −1, 1]
    d = op.spectral_matrix
    expected = 2 * np.eye(k) - np.eye(k, k, 1) - np.eye(k, k, -1)
    expected[0, 0] = expected[-1, -1] = 1
    np.testing.assert_array_equal(d.T @ d, expected)
    u = rng.standard_normal((rows, cols, k))
    np.testing.assert_allclose(op.adjoint(op.forward(u)), u @ expected, atol=1e-12)
    with pytest.raises(DataError, match="channels ≥ 2"):
        SpectralDifference((rows, cols, 1))


def test_difference_operators_reject_bad_input():
    with pytest.raises(DataError, match="boundary"):
        Gradient((*SHAPE, 2), boundary="reflect")
    with pytest.raises(DataError, match="channels ≥ 2"):
        SpectralGradient((*SHAPE, 1))
    with pytest.raises(DataError, match="rows, cols, channels"):
        Laplacian(SHAPE)
    with pytest.raises(DataError, match="circulant"):
        Laplacian((*SHAPE, 1), boundary="neumann").fourier_symbol()


# --- 5. Fourier symbols ----------------------------------------------------------------


def _fft_apply(symbol, u):
    """ifft2(symbol · fft2(u)) over the spatial axes, real part."""
    return np.fft.ifft2(symbol * np.fft.fft2(u, axes=(0, 1)), axes=(0, 1)).real


def test_fourier_symbols_match_direct_operators(rng):
    rows, cols, k = 6, 9, 4
    u = rng.standard_normal((rows, cols, k))
    grad = Gradient((rows, cols, k))
    s = grad.fourier_symbol()
    assert s.shape == (rows, cols, 2)
    via_fft = np.stack([_fft_apply(s[..., None, d], u) for d in range(2)], axis=-1)
    np.testing.assert_allclose(via_fft, grad.forward(u), atol=1e-12)

    sgrad = SpectralGradient((rows, cols, k))
    s2 = sgrad.fourier_symbol()
    du = u @ sgrad.spectral_matrix.T
    via_fft = np.stack([_fft_apply(s2[..., None, d], du) for d in range(2)], axis=-1)
    np.testing.assert_allclose(via_fft, sgrad.forward(u), atol=1e-12)

    lap = Laplacian((rows, cols, k))
    s3 = lap.fourier_symbol()
    assert s3.shape == (rows, cols) and np.isrealobj(s3)
    np.testing.assert_allclose(_fft_apply(s3[..., None], u), lap.forward(u), atol=1e-12)
    # ∇ᵀ∇ = Laplacian in Fourier too: |s_x|² + |s_y|²
    np.testing.assert_allclose((np.abs(s) ** 2).sum(axis=-1), s3, atol=1e-12)
    # explicit shape argument
    assert grad.fourier_symbol((3, 4)).shape == (3, 4, 2)


# --- 6. spectral roughness (the smoothness term beyond the thesis) ---------------------


def test_smoothest_metamer_known_answers(rng):
    """R C keeps every colour, is a projector, and no other metamer is smoother; with as
    many channels as bands there are no metamers (the identity)."""
    c = normalised_colour()  # the rig's camera over its bands
    k = c.shape[1]
    rc = smoothest_metamer(c)
    np.testing.assert_allclose(c @ rc, c, atol=1e-12)  # colour kept
    np.testing.assert_allclose(rc @ rc, rc, atol=1e-12)  # a projector
    np.testing.assert_allclose(smoothest_metamer(5.0 * c), rc, atol=1e-12)  # scale-free
    d = np.diff(np.eye(k), axis=0)
    null = np.linalg.svd(c)[2][3:].T
    for _ in range(5):
        s = rc @ rng.standard_normal(k)
        other = s + null @ rng.standard_normal(k - 3)  # another spectrum of the same colour
        np.testing.assert_allclose(c @ other, c @ s, atol=1e-12)
        assert np.linalg.norm(d @ s) <= np.linalg.norm(d @ other)
    # a colour matrix that only sees spectral differences: a constant spectrum is black
    with pytest.raises(DataError, match="constant spectrum"):
        smoothest_metamer(d[:3])
    np.testing.assert_array_equal(smoothest_metamer(c[:, :3]), np.eye(3))


def test_spectral_roughness_known_answers(rng):
    """‖S x‖² = ‖D_λ(x − x̄)‖² + N‖D_λ P x̄‖² (the cross term sums to zero); a flat image
    of the smoothest metamer of any colour has zero roughness; away from DC, S = D_λ."""
    c = normalised_colour()
    rows, cols, k = 6, 8, c.shape[1]
    op = SpectralRoughness((rows, cols, k), c)
    x = rng.uniform(size=(rows, cols, k))
    mean = x.mean(axis=(0, 1))
    d = np.diff(np.eye(k), axis=0)
    p = np.eye(k) - smoothest_metamer(c)
    expected = np.sum(np.diff(x - mean, axis=2) ** 2) + rows * cols * np.sum((d @ p @ mean) ** 2)
    assert np.sum(op.forward(x) ** 2) == pytest.approx(expected, rel=1e-12)
    flat = np.broadcast_to(smoothest_metamer(c) @ rng.uniform(size=k), (rows, cols, k))
    np.testing.assert_allclose(op.forward(flat), 0.0, atol=1e-13)
    zero_mean = x - mean
    np.testing.assert_allclose(op.forward(zero_mean), np.diff(zero_mean, axis=2), atol=1e-13)
    # its Fourier pieces sum to SᵀS per frequency
    spectrum = np.fft.fft2(x, axes=(0, 1))
    normal = sum(
        symbol[..., None] * (spectrum @ matrix.T)
        for symbol, matrix in op.fourier_pieces((rows, cols))
    )
    via_fft = np.fft.ifft2(normal, axes=(0, 1)).real
    np.testing.assert_allclose(via_fft, op.adjoint(op.forward(x)), atol=1e-12)
