"""Comparison methods (thesis §4.6): bilinear, Malvar (2004) and Menon (2007) demosaicing,
and colour-channel warping with a planted from_reference dispersion model."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from _helpers import planted_dispersion_model
from scipy import ndimage

from labkit.cfa import CFA_LAYOUTS, mosaic
from labkit.errors import DataError
from reconstruction.baselines import BASELINES, baseline

SHAPE = (64, 80)
#: Border left out where an image is compared (mirrored padding and warping fill it).
BORDER = 4
#: Largest interior error on the smooth test image, measured 0.0061 (bilinear), 0.0070
#: (Malvar), 0.0104 (Menon) for every layout (channel amplitude ≈ 0.5–1.3 × 0.5).
SMOOTH_TOLERANCE = {"bilinear": 0.01, "malvar": 0.01, "menon": 0.015}


def grid(shape: tuple[int, int] = SHAPE) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return xx, yy


def smooth(x: np.ndarray, y: np.ndarray, phase: float = 0.0) -> np.ndarray:
    """1 + two tilted waves of period ≥ 45 px."""
    return (
        1.0
        + 0.3 * np.sin(2 * np.pi * (x / 61 + y / 73) + phase)
        + 0.2 * np.sin(2 * np.pi * (-x / 67 + y / 59) + 1.1 + phase)
    )


def interior(image: np.ndarray) -> np.ndarray:
    return image[BORDER:-BORDER, BORDER:-BORDER]


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
@pytest.mark.parametrize("method", sorted(BASELINES))
def test_constant_colour_is_reproduced_exactly(method: str, layout: str) -> None:
    """Every pixel, borders included, to float32 rounding; R ≠ G ≠ B, so a layout
    convention that differed from colour-demosaicing's would swap channels."""
    colour = np.array([0.3, 0.55, 0.8])
    image = np.broadcast_to(colour, (*SHAPE, 3))
    out = baseline(mosaic(image, layout), method, cfa=layout)
    assert out.shape == (*SHAPE, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, image, atol=1e-6)
    # down to one Bayer block, and odd sizes
    for shape in ((2, 2), (5, 7)):
        small = np.broadcast_to(colour, (*shape, 3))
        np.testing.assert_allclose(baseline(mosaic(small, layout), method, cfa=layout), small,
                                   atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
@pytest.mark.parametrize("method", sorted(BASELINES))
def test_smooth_image_is_reproduced_within_tolerance(method: str, layout: str) -> None:
    xx, yy = grid()
    image = np.dstack([0.7 * smooth(xx, yy, 0.4), smooth(xx, yy), 1.3 * smooth(xx, yy, -0.3)])
    out = baseline(mosaic(image, layout), method, cfa=layout)
    assert np.all(np.isfinite(out))
    assert np.abs(interior(out - image)).max() < SMOOTH_TOLERANCE[method]


def test_linear_ramps_are_exact_for_bilinear_and_malvar() -> None:
    """Both interpolate linear functions exactly (measured 6e-8, float32); Menon's
    directional choice leaves 4e-4."""
    xx, yy = grid()
    image = np.dstack(
        [0.2 + 0.01 * xx + 0.005 * yy, 0.5 + 0.003 * xx - 0.002 * yy, 0.4 + 0.004 * yy]
    )
    raw = mosaic(image, "GBRG")
    for method, tolerance in (("bilinear", 1e-6), ("malvar", 1e-6), ("menon", 1e-3)):
        error = np.abs(interior(baseline(raw, method, cfa="GBRG") - image)).max()
        assert error < tolerance, (method, error)


def test_correlated_detail_favours_malvar_and_menon() -> None:
    """An achromatic-structured wave of period 8.3 px: interior RMSE measured 0.041
    (bilinear), 0.028 (Malvar), 0.016 (Menon) — the methods really differ."""
    xx, yy = grid()
    image = (1 + 0.5 * np.sin(2 * np.pi * (xx / 9 + yy / 23)))[..., None] * [0.6, 1.0, 0.8]
    raw = mosaic(image, "GBRG")
    rmse = {
        m: float(np.sqrt(np.mean(interior(baseline(raw, m, cfa="GBRG") - image) ** 2)))
        for m in BASELINES
    }
    assert rmse["malvar"] < 0.8 * rmse["bilinear"]
    assert rmse["menon"] < 0.5 * rmse["bilinear"]


class UniformShift:
    """A colour-channel field with the same displacement (dx, dy) px everywhere."""

    kind = "test"

    def __init__(self, dx: float, dy: float) -> None:
        self.shift = np.array([dx, dy])

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.shift, (points.shape[0], 2)).copy()

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind}


SHIFTS = {"R": (0.8, -0.5), "B": (-0.6, 0.45)}


def shifted_channels() -> tuple[np.ndarray, np.ndarray]:
    """(truth, dispersed): in the dispersed image the feature at p in G is at p + d_c in
    channel c (from_reference), i.e. channel c is truth_c(q − d_c)."""
    xx, yy = grid()
    truth = np.dstack([0.7 * smooth(xx, yy), smooth(xx, yy), 1.3 * smooth(xx, yy)])
    dispersed = truth.copy()
    for index, channel in ((0, "R"), (2, "B")):
        dx, dy = SHIFTS[channel]
        dispersed[..., index] = (0.7, 1.0, 1.3)[index] * smooth(xx - dx, yy - dy)
    return truth, dispersed


def residual_shift(reference: np.ndarray, image: np.ndarray) -> float:
    """|d| such that image(p) ≈ reference(p + d) over the interior, px: Gauss–Newton
    (Lucas–Kanade) on the smooth reference, a few steps."""
    gy, gx = np.gradient(reference)
    xx, yy = grid(reference.shape)
    d = np.zeros(2)
    for _ in range(4):
        moved = ndimage.map_coordinates(reference, [yy + d[1], xx + d[0]], order=3)
        g = np.stack([interior(gx).ravel(), interior(gy).ravel()], axis=1)
        step, *_ = np.linalg.lstsq(g, interior(image - moved).ravel(), rcond=None)
        d += step
    return float(np.hypot(*d))


@pytest.mark.parametrize("method", sorted(BASELINES))
def test_warping_moves_red_and_blue_back_onto_green(method: str) -> None:
    """A planted uniform-shift model (R: (0.8, −0.5) px, B: (−0.6, 0.45) px). Measured
    shift of R / B against the truth: 0.91–0.94 / 0.72–0.74 px before warping, 0.009–0.036
    px after (bilinear 0.012 / 0.012, Malvar 0.024 / 0.009, Menon 0.036 / 0.025: the
    demosaicers' own errors; warping the true channels alone leaves 0.004 px); interior
    error after: ≤ 0.0065."""
    truth, dispersed = shifted_channels()
    raw = mosaic(dispersed, "GBRG")
    model = planted_dispersion_model(
        {c: UniformShift(*d) for c, d in SHIFTS.items()}, shape=SHAPE, direction="from_reference"
    )
    plain = baseline(raw, method, cfa="GBRG")
    corrected = baseline(raw, method, cfa="GBRG", dispersion=model)
    assert corrected.dtype == np.float32 and np.all(np.isfinite(corrected))
    np.testing.assert_array_equal(corrected[..., 1], plain[..., 1])  # G is the reference
    for index, channel in ((0, "R"), (2, "B")):
        before = residual_shift(truth[..., index], plain[..., index])
        after = residual_shift(truth[..., index], corrected[..., index])
        assert before == pytest.approx(np.hypot(*SHIFTS[channel]), abs=0.05)
        assert after < 0.05, (channel, after)
        error = np.abs(interior(corrected[..., index] - truth[..., index])).max()
        assert error < 0.01, (channel, error)


def test_unknown_methods_and_bad_inputs_are_refused() -> None:
    raw = np.ones(SHAPE)
    with pytest.raises(DataError, match="unknown baseline method 'ari'; use one of bilinear, "
                       "malvar, menon"):  # fmt: skip
        baseline(raw, "ari", cfa="GBRG")
    with pytest.raises(DataError, match="unknown CFA layout"):
        baseline(raw, "malvar", cfa="RGBX")
    with pytest.raises(DataError, match=r"\(rows, cols\) Bayer mosaic"):
        baseline(np.ones((*SHAPE, 3)), "bilinear", cfa="GBRG")
    bad = raw.copy()
    bad[2, 3] = np.nan
    with pytest.raises(DataError, match="NaN"):
        baseline(bad, "menon", cfa="GBRG")
    to_reference = planted_dispersion_model(
        {"R": UniformShift(0.5, 0.5)}, shape=SHAPE, direction="to_reference"
    )
    # a to_reference model is inverted: shifting by (0.5, 0.5) back = (−0.5, −0.5) forth
    from_reference = planted_dispersion_model(
        {"R": UniformShift(-0.5, -0.5)}, shape=SHAPE, direction="from_reference"
    )
    np.testing.assert_allclose(
        baseline(raw, "bilinear", cfa="GBRG", dispersion=to_reference),
        baseline(raw, "bilinear", cfa="GBRG", dispersion=from_reference),
        atol=1e-6,
    )
    wrong_size = planted_dispersion_model(
        {"R": UniformShift(0.5, 0.5)}, shape=(32, 40), direction="from_reference"
    )
    with pytest.raises(DataError, match="calibrated on 40×32 px"):
        baseline(raw, "bilinear", cfa="GBRG", dispersion=wrong_size)
