"""Correction by warping (Rudakova–Monasse baseline): planted fields on analytic images,
round trips through a lens' forward and inverse dispersion, model checks, dtype, memory."""

from __future__ import annotations

import tracemalloc
from typing import Any

import numpy as np
import pytest
from _helpers import planted_dispersion_model
from skimage.registration import phase_cross_correlation

from calibration.dispersion_model import DispersionModel
from calibration.warp import (
    _model_field,
    correct_channels,
    correct_spectral,
    from_reference_displacement,
    warp,
)
from labkit.errors import DataError
from labkit.sim import Lens

SHAPE = (96, 128)
#: (u, v) cycles/px, phase, amplitude of the analytic test image's waves.
WAVES = [(1 / 23, 1 / 31, 0.3, 0.5), (-1 / 17, 1 / 29, 1.1, 0.3), (1 / 13, -1 / 41, 2.0, 0.2)]
#: Border (px) left out of comparisons: beyond it, `nearest` fills positions outside.
BORDER = 6


def smooth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth analytic image: 1 + sum of tilted sine waves."""
    out = np.ones(np.broadcast_shapes(np.shape(x), np.shape(y)))
    for u, v, phase, amplitude in WAVES:
        out += amplitude * np.sin(2 * np.pi * (u * x + v * y) + phase)
    return out


def grid(shape: tuple[int, int] = SHAPE) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return xx, yy


def interior(image: np.ndarray) -> np.ndarray:
    return image[BORDER:-BORDER, BORDER:-BORDER]


class LinearField:
    """d(p, λ) = m(λ) (p − c) + t(λ), with m, t linear in λ − 600 nm (spectral), or
    constant (colour channel: points (n, 2))."""

    kind = "test"

    def __init__(self, magnification: float, shift: tuple[float, float], centre=(60.0, 45.0)):
        self.magnification = magnification
        self.shift = np.asarray(shift, dtype=np.float64)
        self.centre = np.asarray(centre, dtype=np.float64)

    def scale(self, points: np.ndarray) -> np.ndarray:
        if points.shape[1] == 3:
            return (points[:, 2] - 600.0)[:, None] / 100.0
        return np.ones((points.shape[0], 1))

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        s = self.scale(points)
        return s * (self.magnification * (points[:, :2] - self.centre) + self.shift)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}

    def band_image(self, scale: float) -> np.ndarray:
        """The band image of `smooth` under this field: B(p + d(p)) = smooth(p)."""
        m, t = scale * self.magnification, scale * self.shift
        xx, yy = grid()
        # p + m (p − c) + t = q  ⇒  p = (q + m c − t) / (1 + m)
        px = (xx + m * self.centre[0] - t[0]) / (1 + m)
        py = (yy + m * self.centre[1] - t[1]) / (1 + m)
        return smooth(px, py)


def spectral_model(
    field: LinearField, *, direction: str = "from_reference", shape=SHAPE
) -> DispersionModel:
    return planted_dispersion_model(
        {"spectral": field}, shape=shape, direction=direction, wavelength_span=(450.0, 650.0)
    )


def channel_model(fields: dict[str, LinearField], *, direction: str = "from_reference"):
    return planted_dispersion_model(fields, shape=SHAPE, direction=direction)


def residual_shift(reference: np.ndarray, image: np.ndarray) -> float:
    """|shift| between two images' interiors by upsampled cross-correlation, px."""
    shift, _, _ = phase_cross_correlation(
        interior(reference) - 1, interior(image) - 1, upsample_factor=200, normalization=None
    )
    return float(np.hypot(*shift))


# -- 5. warp ----------------------------------------------------------------------------


@pytest.mark.parametrize(("order", "tolerance"), [(1, 0.025), (3, 1e-3)])
def test_constant_field_resamples_the_shifted_image(order: int, tolerance: float) -> None:
    """out(p) = image(p + d): measured max interior error 0.018 (bilinear) and 5e-5
    (cubic) on waves of period ≥ 13 px and amplitude ≤ 0.5."""
    xx, yy = grid()
    image = smooth(xx, yy).astype(np.float32)
    out = warp(image, 0.37, -0.21, order=order)
    assert out.dtype == np.float32
    assert np.all(np.isfinite(out))
    expected = smooth(xx + 0.37, yy - 0.21)
    assert np.abs(interior(out - expected)).max() < tolerance
    # a whole-pixel field is an exact copy
    np.testing.assert_array_equal(warp(image, 2.0, -1.0)[2:-2, 3:-3], image[1:-3, 5:-1])


def test_warp_by_a_lens_field_then_by_its_inverse_returns_the_original() -> None:
    """Forward: the lens' from_reference field; back: q ↦ to_reference(q) − q (measured
    max interior error 3e-4 with cubic splines, 0.04 bilinear)."""
    lens = Lens(SHAPE, max_shift_px=3.0, radial_profile="nonmonotonic")
    xx, yy = grid()
    image = smooth(xx, yy)
    dx, dy = lens.displacement(xx, yy, 450.0)
    assert np.hypot(dx, dy).max() > 1.5
    dispersed = warp(image, dx, dy, order=3)
    s = float(lens.spectral_factor(450.0))
    qx, qy = lens.to_reference(xx, yy, s)
    restored = warp(dispersed, qx - xx, qy - yy, order=3)
    assert restored.dtype == np.float64
    assert np.abs(interior(restored - image)).max() < 2e-3
    assert np.abs(interior(dispersed - image)).max() > 0.1  # the field did something


def test_warp_checks_its_inputs() -> None:
    image = np.ones(SHAPE)
    with pytest.raises(DataError, match="2-D"):
        warp(np.ones((4, 4, 3)), 0.0, 0.0)
    with pytest.raises(DataError, match="do not match"):
        warp(image, np.zeros((3, 3)), 0.0)
    bad = np.zeros(SHAPE)
    bad[5, 5] = np.nan
    with pytest.raises(DataError, match="dx holds NaN"):
        warp(image, bad, 0.0)
    with pytest.raises(DataError, match="NaN"):
        warp(bad, 0.0, 0.0)
    with pytest.raises(DataError, match="order"):
        warp(image, 0.0, 0.0, order=7)
    # far outside the image: nearest border values, never NaN
    assert np.all(np.isfinite(warp(image, 500.0, -500.0)))


# -- 6. correct_spectral / correct_channels -------------------------------------------


def test_correct_spectral_aligns_every_band_with_the_reference() -> None:
    """Bands dispersed by a known field (shift and magnification growing with |λ − 600|)
    are warped back onto the reference geometry: measured residual shift 0 at the
    0.005 px resolution of the check, max interior error 6e-5 (cubic), 0.02 (bilinear)."""
    field = LinearField(0.004, (0.8, -0.5))
    wavelengths = np.array([450.0, 500.0, 550.0, 600.0, 650.0])
    cube = np.dstack([field.band_image((w - 600.0) / 100.0) for w in wavelengths])
    cube = cube.astype(np.float32)
    xx, yy = grid()
    truth = smooth(xx, yy)
    assert residual_shift(truth, cube[..., 0]) > 1.0  # 450 nm: 1.2 px shift before
    corrected = correct_spectral(cube, wavelengths, spectral_model(field), order=3)
    assert corrected.dtype == np.float32 and corrected.shape == cube.shape
    assert np.all(np.isfinite(corrected))
    for band in range(wavelengths.size):
        assert residual_shift(truth, corrected[..., band]) < 0.02
        assert np.abs(interior(corrected[..., band] - truth)).max() < 2e-3
    np.testing.assert_array_equal(corrected[..., 3], cube[..., 3])  # the reference band
    # the same with a model evaluated at every pixel
    exact = correct_spectral(cube, wavelengths, spectral_model(field), field_step_px=1)
    bilinear = correct_spectral(cube, wavelengths, spectral_model(field))
    np.testing.assert_allclose(exact, bilinear, atol=1e-5)


def test_correct_channels_warps_red_and_blue_onto_green() -> None:
    fields = {"R": LinearField(0.003, (0.6, -0.3)), "B": LinearField(-0.002, (-0.45, 0.25))}
    xx, yy = grid()
    truth = smooth(xx, yy)
    rgb = np.dstack([fields["R"].band_image(1.0), truth, fields["B"].band_image(1.0)])
    corrected = correct_channels(rgb, channel_model(fields), order=3)
    assert corrected.dtype == np.float64
    np.testing.assert_array_equal(corrected[..., 1], truth)
    for channel in (0, 2):
        assert residual_shift(truth, corrected[..., channel]) < 0.02
        assert np.abs(interior(corrected[..., channel] - truth)).max() < 2e-3
    as_float32 = correct_channels(rgb.astype(np.float32), channel_model(fields))
    assert as_float32.dtype == np.float32 and np.all(np.isfinite(as_float32))


def test_models_of_the_wrong_kind_direction_or_size_are_refused() -> None:
    field = LinearField(0.0, (0.5, 0.5))
    cube = np.ones((*SHAPE, 2), np.float32)
    rgb = np.ones((*SHAPE, 3), np.float32)
    wavelengths = [500.0, 600.0]
    with pytest.raises(DataError, match="correct_spectral"):
        correct_channels(rgb, spectral_model(field))
    with pytest.raises(DataError, match="correct_channels"):
        correct_spectral(cube, wavelengths, channel_model({"R": field}))
    with pytest.raises(DataError, match=r"calibrated on 64×48 px.*128×96 px"):
        correct_spectral(cube, wavelengths, spectral_model(field, shape=(48, 64)))
    with pytest.raises(DataError, match="2 bands but 3 wavelengths"):
        correct_spectral(cube, [500.0, 550.0, 600.0], spectral_model(field))

    class NanField(LinearField):
        def evaluate(self, points: np.ndarray) -> np.ndarray:
            out = super().evaluate(points)
            out[points[:, 1] > 50] = np.nan
            return out

    with pytest.raises(DataError, match="displacement field holds NaN"):
        correct_spectral(cube, wavelengths, spectral_model(NanField(0.0, (0.5, 0.5))))
    cube[3, 4, 1] = np.nan
    with pytest.raises(DataError, match=r"band 1 \(600 nm\).*NaN"):
        correct_spectral(cube, wavelengths, spectral_model(field))


def test_to_reference_models_are_inverted_for_warping() -> None:
    """A to_reference field d_to is inverted by fixed-point iteration: the band position q
    of p solves q + d_to(q) = p (analytic here, to 1e-6 px), and correcting bands
    dispersed by d_to restores the reference geometry as a from_reference model does."""
    field = LinearField(0.004, (0.8, -0.5))
    xx, yy = grid()
    wavelengths = np.array([450.0, 600.0, 650.0])
    to_model = spectral_model(field, direction="to_reference")
    for wavelength in wavelengths:
        s = (wavelength - 600.0) / 100.0
        m, t = s * field.magnification, s * field.shift
        dx, dy = from_reference_displacement(to_model, xx, yy, wavelength)
        qx = (xx + m * field.centre[0] - t[0]) / (1 + m)
        qy = (yy + m * field.centre[1] - t[1]) / (1 + m)
        assert np.abs(dx - (qx - xx)).max() < 1e-6 and np.abs(dy - (qy - yy)).max() < 1e-6
    # band images: B(q) = truth(q + d_to(q))
    truth = smooth(xx, yy)
    cube = np.empty((*SHAPE, wavelengths.size))
    for band, wavelength in enumerate(wavelengths):
        s = (wavelength - 600.0) / 100.0
        d = s * (field.magnification * (np.dstack([xx, yy]) - field.centre) + field.shift)
        cube[..., band] = smooth(xx + d[..., 0], yy + d[..., 1])
    assert residual_shift(truth, cube[..., 0]) > 1.0
    corrected = correct_spectral(cube, wavelengths, to_model, order=3)
    for band in range(wavelengths.size):
        assert residual_shift(truth, corrected[..., band]) < 0.02
        assert np.abs(interior(corrected[..., band] - truth)).max() < 2e-3
    # colour channels likewise (a colour field has no λ factor)
    d = field.magnification * (np.dstack([xx, yy]) - field.centre) + field.shift
    red = smooth(xx + d[..., 0], yy + d[..., 1])
    rgb = np.dstack([red, truth, truth])
    colour = correct_channels(rgb, channel_model({"R": field}, direction="to_reference"), order=3)
    assert residual_shift(truth, red) > 0.5
    assert residual_shift(truth, colour[..., 0]) < 0.02

    class FoldingField(LinearField):
        def evaluate(self, points: np.ndarray) -> np.ndarray:
            return 3.0 * (points[:, :2] - self.centre)  # |∇d| > 1: no contraction

    with pytest.raises(DataError, match="could not invert"):
        correct_spectral(
            cube, wavelengths, spectral_model(FoldingField(0.0, (0, 0)), direction="to_reference")
        )


def test_interpolated_model_field_matches_the_exact_one() -> None:
    """The model on an 8 px grid with cubic splines vs at every pixel, for a smooth
    non-polynomial field of up to 3.5 px varying over ~70 px (measured 5e-5 px): < 1e-4 px."""

    class SmoothField:
        kind = "test"

        def evaluate(self, points: np.ndarray) -> np.ndarray:
            x, y, w = points.T
            s = (w - 600.0) / 150.0
            dx = 3.0 * s * np.tanh((x - 130.0) / 70.0) * np.exp(-(((y - 90.0) / 160.0) ** 2))
            dy = 2.0 * s * np.sin(y / 45.0) * np.cos(x / 90.0)
            return np.column_stack([dx, dy])

        def to_dict(self) -> dict[str, Any]:
            return {}

    model = spectral_model(SmoothField(), shape=(200, 260))
    coarse = _model_field(model, (200, 260), 8, wavelength_nm=450.0)(0, 200)
    exact = _model_field(model, (200, 260), 1, wavelength_nm=450.0)(0, 200)
    assert np.hypot(*exact).max() > 2.0
    for a, b in zip(coarse, exact, strict=True):
        assert np.abs(a - b).max() < 1e-4, np.abs(a - b).max()
    # blocks of rows agree with the whole
    part = _model_field(model, (200, 260), 8, wavelength_nm=450.0)(37, 90)
    np.testing.assert_allclose(part[0], coarse[0][37:90], atol=1e-12)


def test_correct_spectral_memory_is_bounded_by_the_result() -> None:
    """A 31-band cube: the peak allocation is the result plus a few single-band temporaries
    (measured: 6.1 float64 bands, the whole band being one block here; a full-size band
    is resampled in blocks of 2^18 px, which leaves about 3 bands)."""
    rows, cols, bands = 192, 240, 31
    rng = np.random.default_rng(0)
    cube = rng.random((rows, cols, bands), dtype=np.float32)
    wavelengths = np.linspace(400.0, 700.0, bands)
    model = spectral_model(LinearField(0.002, (0.5, -0.4)), shape=(rows, cols))
    tracemalloc.start()
    try:
        corrected = correct_spectral(cube, wavelengths, model, order=3)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert corrected.dtype == np.float32
    band = rows * cols * 8
    assert peak < cube.nbytes + 7 * band, f"peak: result + {(peak - cube.nbytes) / band:.1f} bands"
