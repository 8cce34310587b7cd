"""The dispersion operator Φ (thesis §3.2.5): adjoint, planted shifts, a fitted lens model,
spectral sampling of dispersion, and bad input."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from _helpers import planted_dispersion_model
from _problems import ConstantField, RadialField
from scipy.ndimage import map_coordinates

from calibration.dispersion_model import DispersionModel
from calibration.keypoints import DispersionKeypoints
from calibration.polynomial import fit_polynomial_model
from labkit.errors import DataError
from labkit.sim.lens import Lens
from reconstruction.model.operators import dot_test
from reconstruction.model.operators.dispersion import Dispersion, dispersion_samples

SHAPE = (48, 64)
WAVES = [(1 / 23, 1 / 31, 0.3, 0.5), (-1 / 17, 1 / 29, 1.1, 0.3), (1 / 13, -1 / 41, 2.0, 0.2)]


def smooth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth analytic image: 1 + tilted sine waves of period ≥ 13 px."""
    out = np.ones(np.broadcast_shapes(np.shape(x), np.shape(y)))
    for u, v, phase, amplitude in WAVES:
        out += amplitude * np.sin(2 * np.pi * (u * x + v * y) + phase)
    return out


def grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return xx, yy


def spectral_model(
    field: Any, *, direction: str = "to_reference", shape: tuple[int, int] = SHAPE
) -> DispersionModel:
    return planted_dispersion_model(
        {"spectral": field}, shape=shape, direction=direction, wavelength_span=(400.0, 700.0)
    )


def channel_model(fields: dict[str, Any], *, direction: str = "to_reference") -> DispersionModel:
    return planted_dispersion_model(fields, shape=SHAPE, direction=direction)


# -- 1. adjoint -------------------------------------------------------------------------
@pytest.mark.parametrize("interpolation", ["bilinear", "cubic"])
@pytest.mark.parametrize("boundary", ["clamp", "periodic"])
@pytest.mark.parametrize(("dtype", "tolerance"), [(np.float64, 1e-10), (np.float32, 1e-5)])
@pytest.mark.parametrize(("origin", "shape"), [((0, 0), None), ((7, 11), (21, 30))])
def test_dot_test(
    dtype: type, tolerance: float, origin, shape, boundary: str, interpolation: str
) -> None:
    """⟨Φx, y⟩ = ⟨x, Φᵀy⟩ with shifts of up to 2.2 px, border clamping included."""
    model = spectral_model(RadialField(0.03))
    op = Dispersion(
        model,
        np.array([420.0, 510.0, 600.0, 690.0]),
        origin=origin,
        shape=shape,
        boundary=boundary,
        interpolation=interpolation,
    )
    assert op.domain_shape == op.range_shape
    assert op.max_shift_px > 1.0
    result = dot_test(op, rng=np.random.default_rng(3), dtype=dtype)
    assert result.relative_error <= tolerance
    x = np.random.default_rng(4).standard_normal(op.domain_shape).astype(dtype)
    assert op.forward(x).dtype == dtype
    assert op.adjoint(x).dtype == dtype


# -- 2. planted constant displacement ------------------------------------------------------
@pytest.mark.parametrize(("origin", "shape"), [((0, 0), None), ((5, 9), (20, 25))])
def test_constant_shift_samples_linear_image_exactly(origin, shape) -> None:
    """Output(q) = input(q + e), e = (0.25, −0.5): exact for a linear image (bilinear
    interpolation reproduces linear functions); border samples are clamped."""
    e = (0.25, -0.5)
    model = spectral_model(ConstantField(e))
    op = Dispersion(
        model, np.array([500.0, 650.0]), origin=origin, shape=shape, interpolation="bilinear"
    )
    rows, cols = op.patch_shape
    xx, yy = grid((rows, cols))
    gx, gy = xx + origin[1], yy + origin[0]  # full-image coordinates

    def linear(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.3 + 0.02 * x - 0.035 * y

    latent = np.stack([linear(gx, gy), 2.0 * linear(gx, gy)], axis=-1)
    out = op.forward(latent)
    expected = linear(gx + e[0], gy + e[1])
    # interior: q + e inside the patch (x + 0.25 ≤ cols − 1, y − 0.5 ≥ 0)
    inner = (slice(1, None), slice(0, -1))
    assert np.max(np.abs(out[..., 0][inner] - expected[inner])) <= 1e-12
    assert np.max(np.abs(out[..., 1][inner] - 2.0 * expected[inner])) <= 1e-12
    # first row: y − 0.5 is clamped to the patch's first row
    clamped = linear(gx[0, :-1] + e[0], gy[0, :-1])
    assert np.max(np.abs(out[0, :-1, 0] - clamped)) <= 1e-12
    assert op.max_shift_px == pytest.approx(np.hypot(*e))


def test_cubic_weights_reproduce_quadratics_and_integer_shifts() -> None:
    """Keys' cubic convolution (a = −½) is exact for quadratics, and an integer shift
    moves pixels without mixing them; its weights sum to 1."""
    e = (0.37, -0.81)
    op = Dispersion(spectral_model(ConstantField(e)), np.array([500.0]), interpolation="cubic")
    xx, yy = grid(SHAPE)

    def quadratic(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.4 + 0.02 * x - 0.01 * y + 3e-4 * x * x - 2e-4 * x * y + 5e-4 * y * y

    out = op.forward(quadratic(xx, yy)[..., None])[..., 0]
    inner = (slice(2, -2), slice(2, -3))  # all 16 neighbours inside the patch
    assert np.max(np.abs(out[inner] - quadratic(xx + e[0], yy + e[1])[inner])) <= 1e-12
    assert np.allclose(op.matrices[0].sum(axis=1), 1.0, atol=1e-14)

    whole = Dispersion(
        spectral_model(ConstantField((2.0, -1.0))),
        np.array([500.0]),
        interpolation="cubic",
        boundary="periodic",
    )
    image = np.random.default_rng(0).standard_normal((*SHAPE, 1))
    assert np.array_equal(whole.forward(image), np.roll(image, (1, -2), axis=(0, 1)))


def test_cubic_shift_is_closer_to_a_pure_shift_than_bilinear() -> None:
    """A pure sub-pixel shift of a band-limited image (periods 5–13 px): bilinear weights
    also blur it (RMS error 0.18 for two unit sine waves); cubic ones are 4.6× closer."""
    e = (0.5, 0.3)
    waves = [(1 / 5, 1 / 13, 0.2), (-1 / 7, 1 / 9, 1.3)]

    def image(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return sum(np.sin(2 * np.pi * (u * x + v * y) + p) for u, v, p in waves)

    xx, yy = grid(SHAPE)
    expected = image(xx + e[0], yy + e[1])
    inner = (slice(3, -3), slice(3, -3))
    error = {}
    for interpolation in ("bilinear", "cubic"):
        op = Dispersion(
            spectral_model(ConstantField(e)), np.array([500.0]), interpolation=interpolation
        )
        out = op.forward(image(xx, yy)[..., None])[..., 0]
        error[interpolation] = float(np.sqrt(np.mean((out - expected)[inner] ** 2)))
    assert error["bilinear"] > 0.15
    assert error["cubic"] < error["bilinear"] / 4


def test_unknown_interpolation_is_refused() -> None:
    with pytest.raises(DataError, match=r"unknown interpolation 'nearest'.*'bilinear' or 'cubic'"):
        Dispersion(
            spectral_model(ConstantField((0.1, 0.1))), np.array([500.0]), interpolation="nearest"
        )


def test_colour_channel_model_shifts_r_and_b_only() -> None:
    """Problem (3.27): channels R, G, B; G (the reference) passes unchanged."""
    model = channel_model({"R": ConstantField((0.5, 0.0)), "B": ConstantField((0.0, 1.0))})
    op = Dispersion(model, None, interpolation="bilinear")
    assert op.channels == ("R", "G", "B")
    xx, yy = grid(SHAPE)
    image = smooth(xx, yy)
    out = op.forward(np.stack([image, image, image], axis=-1))
    np.testing.assert_array_equal(out[..., 1], image)
    np.testing.assert_allclose(out[:, :-1, 0], 0.5 * (image[:, :-1] + image[:, 1:]), atol=1e-12)
    np.testing.assert_allclose(out[:-1, :, 2], image[1:, :], atol=1e-12)
    assert dot_test(op, rng=np.random.default_rng(5)).relative_error <= 1e-10


# -- 3. a model fitted to a simulated lens ---------------------------------------------------
LENS_SHAPE = (64, 80)
LENS = Lens(LENS_SHAPE, max_shift_px=2.5)
#: Comparison margin, px: > the largest shift (2.2 px), so no sample is clamped.
MARGIN = 4


def fit_lens_model() -> DispersionModel:
    """A to_reference polynomial model fitted to exact keypoints of LENS (7 bands)."""
    gy, gx = np.mgrid[2 : LENS_SHAPE[0] : 6, 2 : LENS_SHAPE[1] : 6].astype(np.float64)
    gx, gy = gx.ravel(), gy.ravel()
    parts = []
    for w in np.arange(400.0, 701.0, 50.0):
        dx, dy = LENS.displacement(gx, gy, w)
        parts.append((gx, gy, dx, dy, np.full(gx.shape, w)))
    x, y, dx, dy, w = (np.concatenate(c) for c in zip(*parts, strict=True))
    keypoints = DispersionKeypoints(
        x, y, dx, dy, reference=LENS.reference_nm, image_shape=LENS_SHAPE, wavelength_nm=w
    )
    return fit_polynomial_model(
        keypoints, direction="to_reference", max_degree_xy=3, rng=np.random.default_rng(0)
    )


@pytest.fixture(scope="module")
def lens_model() -> DispersionModel:
    return fit_lens_model()


def test_fitted_lens_model_reproduces_lens_warp(lens_model: DispersionModel) -> None:
    """Φ L matches the band images the lens forms, B_λ(q) = L(q + e(q, λ)) with
    e(q, λ) = lens.to_reference(q, s(λ)) − q. Measured max interior errors: 0.020 against
    the analytic band image (bilinear interpolation error on waves of period ≥ 13 px, as
    for calibration.warp), 2.7e-4 against bilinear sampling at the true positions (model
    error ≈ 1e-3 px); without Φ (identity) 0.50."""
    wavelengths = np.array([420.0, 500.0, 600.0, 680.0])
    op = Dispersion(lens_model, wavelengths, interpolation="bilinear")
    xx, yy = grid(LENS_SHAPE)
    latent = np.repeat(smooth(xx, yy)[..., None], len(wavelengths), axis=-1)
    out = op.forward(latent)
    inner = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
    worst_analytic = worst_bilinear = worst_identity = 0.0
    for k, w in enumerate(wavelengths):
        tx, ty = LENS.to_reference(xx, yy, float(LENS.spectral_factor(w)), iterations=10)
        band = smooth(tx, ty)
        sampled = map_coordinates(latent[..., k], [ty, tx], order=1, mode="nearest")
        worst_analytic = max(worst_analytic, np.abs(out[..., k] - band)[inner].max())
        worst_bilinear = max(worst_bilinear, np.abs(out[..., k] - sampled)[inner].max())
        worst_identity = max(worst_identity, np.abs(latent[..., k] - band)[inner].max())
    assert worst_analytic < 0.025
    assert worst_bilinear < 5e-4
    assert worst_identity > 0.4
    # 600 nm is the reference: Φ is (numerically) the identity there
    np.testing.assert_allclose(out[..., 2], latent[..., 2], atol=1e-3)
    assert op.max_shift_px == pytest.approx(2.2, abs=0.1)


# -- 4. spectral sampling ----------------------------------------------------------------
def test_samples_without_dispersion_are_min_count() -> None:
    model = spectral_model(ConstantField((0.0, 0.0)))
    samples = dispersion_samples(model, (400.0, 700.0), origin=(0, 0), shape=SHAPE, min_count=5)
    np.testing.assert_allclose(samples, np.linspace(400.0, 700.0, 5))


def test_one_pixel_spread_needs_eleven_samples() -> None:
    """e goes from 0 at 600 nm to (0.6, 0.8) (1 px) at 700 nm over [600, 700] nm: the
    thesis' n = ⌈1 / 0.1⌉ + 1 = 11, each step 0.1 px."""
    model = spectral_model(ConstantField((0.6, 0.8), per_nm=True))
    samples = dispersion_samples(model, (600.0, 700.0), origin=(0, 0), shape=SHAPE, min_count=3)
    assert len(samples) == 11
    assert len(dispersion_samples(model, (600.0, 700.0), shape=SHAPE, min_count=20)) == 20


def quadrant_steps(model: DispersionModel, samples: np.ndarray, origin, shape) -> np.ndarray:
    """|e(λ_k+1) − e(λ_k)| at the patch's quadrant centres, (4, n − 1), px."""
    qx = origin[1] - 0.5 + shape[1] * np.array([0.25, 0.75, 0.25, 0.75])
    qy = origin[0] - 0.5 + shape[0] * np.array([0.25, 0.25, 0.75, 0.75])
    ex, ey = model.displacement(qx[:, None], qy[:, None], samples[None, :])
    return np.hypot(np.diff(ex, axis=1), np.diff(ey, axis=1))


def test_sample_spacing_keeps_consecutive_shifts_small(lens_model: DispersionModel) -> None:
    """Consecutive samples shift the image by ≤ 0.1 px at the quadrant centres.

    Uniform e linear in λ, reference 600 nm inside [400, 700] nm: end vectors of 2 px and
    1 px pointing opposite ways, spread 3 px → 31 samples, every step 0.1 px (the thesis'
    mean length, 1.5 px, would give 16 samples and 0.2 px steps). A magnification change
    (e varies over the patch): steps ≤ 0.1 px averaged over the quadrant centres (the
    largest quadrant's steps 0.11 px). The simulated lens (nonlinear in λ): mean step
    0.095 px over all quadrants and pairs; the largest, 0.20 px, at the blue end where
    glass dispersion is steepest."""
    origin, shape = (4, 6), (40, 50)
    uniform = spectral_model(ConstantField((0.6, 0.8), per_nm=True))
    samples = dispersion_samples(uniform, (400.0, 700.0), origin=origin, shape=shape, min_count=3)
    assert len(samples) == 31
    assert quadrant_steps(uniform, samples, origin, shape).max() <= 0.1 + 1e-12
    radial = spectral_model(RadialField(0.05))
    samples = dispersion_samples(radial, (400.0, 700.0), origin=origin, shape=shape, min_count=3)
    steps = quadrant_steps(radial, samples, origin, shape).mean(axis=0)
    assert steps.max() <= 0.1 + 1e-12
    assert steps.min() > 0.09  # not oversampled
    samples = dispersion_samples(lens_model, (400.0, 700.0), origin=(0, 0), min_count=3)
    assert quadrant_steps(lens_model, samples, (0, 0), LENS_SHAPE).mean() <= 0.1


# -- 5. bad input -------------------------------------------------------------------------
def test_from_reference_model_is_refused() -> None:
    model = spectral_model(ConstantField((0.2, 0.1)), direction="from_reference")
    with pytest.raises(DataError, match="--direction to_reference"):
        Dispersion(model, np.array([500.0]), interpolation="bilinear")


@pytest.mark.parametrize(
    ("origin", "shape"), [((0, 0), (49, 64)), ((40, 0), (10, 10)), ((-1, 0), (5, 5))]
)
def test_patch_outside_the_model_image_is_refused(origin, shape) -> None:
    model = spectral_model(ConstantField((0.2, 0.1)))
    with pytest.raises(DataError, match="not inside"):
        Dispersion(model, np.array([500.0]), origin=origin, shape=shape, interpolation="bilinear")
    with pytest.raises(DataError, match="not inside"):
        dispersion_samples(model, (400.0, 700.0), origin=origin, shape=shape, min_count=3)


def test_wavelengths_must_match_the_model_kind() -> None:
    with pytest.raises(DataError, match="wavelengths_nm"):
        Dispersion(spectral_model(ConstantField((0.2, 0.1))), None, interpolation="bilinear")
    with pytest.raises(DataError, match="wavelengths_nm=None"):
        Dispersion(
            channel_model({"R": ConstantField((0.5, 0.0))}),
            np.array([500.0]),
            interpolation="bilinear",
        )
    with pytest.raises(DataError, match="channel"):
        Dispersion(channel_model({"R": ConstantField((0.5, 0.0))}), None, interpolation="bilinear")
    op = Dispersion(
        spectral_model(ConstantField((0.2, 0.1))),
        np.array([500.0, 600.0]),
        interpolation="bilinear",
    )
    with pytest.raises(DataError, match="expects shape"):
        op.forward(np.zeros((*SHAPE, 3)))


def test_keys_taps_are_the_kernel_at_the_four_offsets() -> None:
    """The cubic stencil's weights, each evaluated on its own piece of the kernel, are
    :func:`keys_kernel` at the offsets −1, 0, 1, 2 to the bit, integer sample points (a
    fraction of 0) included, and sum to 1."""
    from reconstruction.model.operators.dispersion import _keys_taps, keys_kernel

    fraction = np.concatenate([[0.0, 0.5, 1 - 2**-52], np.random.default_rng(0).random(1000)])
    taps = _keys_taps(fraction)
    expected = keys_kernel(fraction - np.arange(-1, 3)[:, None])
    np.testing.assert_array_equal(taps, expected)
    np.testing.assert_allclose(taps.sum(axis=0), 1.0, rtol=0, atol=1e-15)
