"""The calibrated domain of a dispersion model: clamping, its report, and refusing."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from _helpers import planted_dispersion_model

from calibration.dispersion_model import DispersionModel
from calibration.model_domain import CalibratedRegion, domain_use
from labkit.errors import ConfigError, DataError
from reconstruction.model.operators import Dispersion, dispersion_samples


class SlopeField:
    """e = (a (λ − 600), 0.01 x): a shift linear in λ and in x, known everywhere."""

    kind = "test"

    def __init__(self, per_nm: float = 0.02) -> None:
        self.per_nm = per_nm

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        ex = self.per_nm * (points[:, 2] - 600.0)
        return np.column_stack([ex, 0.01 * points[:, 0]])

    def to_dict(self) -> dict:
        return {"kind": self.kind}


def grid_region(step: float = 100.0) -> CalibratedRegion:
    """Keypoints on a `step`-px grid over x 100–900, y 100–600 in six bands 450–687 nm."""
    x, y = np.meshgrid(np.arange(100, 901, step), np.arange(100, 601, step))
    waves = np.array([450.0, 500, 550, 600, 650, 687])
    n = x.size
    return CalibratedRegion.from_points(
        np.tile(x.ravel(), 6), np.tile(y.ravel(), 6), np.repeat(waves, n)
    )


def model_over(region: CalibratedRegion, shape=(700, 1000)) -> DispersionModel:
    return DispersionModel(
        type="test",
        variables="xylambda",
        direction="to_reference",
        reference=600.0,
        image_shape=shape,
        fields={"spectral": SlopeField()},
        region=region,
    )


def test_region_records_hull_range_and_spacing() -> None:
    region = grid_region(100.0)
    assert region.wavelength_nm == (450.0, 687.0)
    np.testing.assert_allclose(region.hull_xy.min(axis=0), [100, 100])
    np.testing.assert_allclose(region.hull_xy.max(axis=0), [900, 600])
    # the median distance to the nearest keypoint of the same band: the grid's step
    assert region.spacing_px == pytest.approx(100.0)
    assert grid_region(50.0).spacing_px == pytest.approx(50.0)
    again = CalibratedRegion.from_dict(region.to_dict(), "region")
    assert again.spacing_px == pytest.approx(region.spacing_px)
    assert again.wavelength_nm == region.wavelength_nm
    # files written before the spacing was recorded: the hull alone
    older = {k: v for k, v in region.to_dict().items() if k != "spacing_px"}
    assert CalibratedRegion.from_dict(older, "region").margin_px == 0.0
    with pytest.raises(ConfigError, match=r"region.spacing_px must be ≥ 0"):
        CalibratedRegion.from_dict({**region.to_dict(), "spacing_px": -1}, "region")
    with pytest.raises(ConfigError, match=r"region.wavelength_nm must be \[min, max\]"):
        CalibratedRegion.from_dict({**region.to_dict(), "wavelength_nm": [700, 400]}, "region")


def test_clamp_moves_only_what_lies_beyond_the_domain() -> None:
    region = grid_region()
    margin = region.margin_px
    x = np.array([500.0, 50.0, 100.0 - margin - 100.0, 1000.0])
    y = np.array([300.0, 300.0, 300.0, 800.0])
    w = np.array([400.0, 500.0, 700.0, 687.0])
    cx, cy, cw = region.clamp(x, y, w)
    np.testing.assert_allclose(cw, [450.0, 500.0, 687.0, 687.0])
    # inside, and 50 px out (within one spacing): untouched
    np.testing.assert_allclose([cx[0], cy[0], cx[1], cy[1]], [500, 300, 50, 300])
    # 100 px beyond the margin, straight left of the hull: moved back to the margin
    np.testing.assert_allclose([cx[2], cy[2]], [100.0 - margin, 300.0])
    # beyond a corner: onto the circle of the margin round the corner (900, 600)
    assert np.hypot(cx[3] - 900, cy[3] - 600) == pytest.approx(margin)
    direction = np.array([100.0, 200.0]) / np.hypot(100.0, 200.0)
    np.testing.assert_allclose([cx[3], cy[3]], [900, 600] + margin * direction)
    distance = region.distance_outside(np.array([500.0, 0.0, 1000.0]), np.array([300.0, 300, 800]))
    np.testing.assert_allclose(distance, [0.0, 100.0, np.hypot(100, 200)])


def test_a_clamped_model_is_constant_beyond_its_range() -> None:
    model = model_over(grid_region())
    inside = model.within_domain()
    assert model.extrapolation == "allow" and inside.extrapolation == "clamp"
    dx_raw, _ = model.displacement(500.0, 300.0, 400.0)
    dx_in, _ = inside.displacement(500.0, 300.0, 400.0)
    dx_edge, _ = model.displacement(500.0, 300.0, 450.0)
    assert dx_raw == pytest.approx(0.02 * (400 - 600))  # the fitted function, as asked
    assert dx_in == pytest.approx(dx_edge)  # clamped to 450 nm
    # position: x beyond the margin takes the margin's value (ey = 0.01 x)
    far = 900.0 + model.region.margin_px + 50.0
    _, ey = inside.displacement(far, 300.0, 600.0)
    assert ey == pytest.approx(0.01 * (900.0 + model.region.margin_px))
    # the file does not carry the choice: a loaded model is the model as fitted
    assert "extrapolation" not in model.to_dict()
    with pytest.raises(ConfigError, match="extrapolation must be allow or clamp"):
        replace(model, extrapolation="maybe")


def test_phi_of_a_band_beyond_the_range_is_the_edge_bands() -> None:
    """Φ at 400 nm of a model calibrated over 450–687 nm, clamped: exactly Φ at 450 nm."""
    model = model_over(grid_region())
    clamped = Dispersion(
        model.within_domain(),
        np.array([400.0]),
        origin=(200, 300),
        shape=(16, 16),
        interpolation="bilinear",
    )
    edge = Dispersion(
        model, np.array([450.0]), origin=(200, 300), shape=(16, 16), interpolation="bilinear"
    )
    raw = Dispersion(
        model, np.array([400.0]), origin=(200, 300), shape=(16, 16), interpolation="bilinear"
    )
    np.testing.assert_array_equal(clamped.taps.weights_x, edge.taps.weights_x)
    np.testing.assert_array_equal(clamped.taps.offsets_x, edge.taps.offsets_x)
    assert not np.array_equal(raw.taps.offsets_x, edge.taps.offsets_x)
    # spectral sampling stays inside the range of a clamped model
    samples = dispersion_samples(
        model.within_domain(), (400.0, 700.0), origin=(200, 300), shape=(16, 16), min_count=2
    )
    assert samples[0] == pytest.approx(450.0) and samples[-1] == pytest.approx(687.0)


def test_domain_use_reports_bands_and_area() -> None:
    model = model_over(grid_region())
    use = domain_use(model, wavelengths_nm=[400.0, 450.2, 600.0, 700.0])
    assert use.outside_nm == [400.0, 700.0]  # 450.2 lies within the 0.5 nm slack
    # image 1000×700, hull 100–900 × 100–600 widened by 100 px: only the four corners
    # lie beyond (a quarter circle short of each 100×100 square: 4 (1 − π/4) 10⁴ px²)
    assert use.area_outside == pytest.approx(4 * (1 - np.pi / 4) * 1e4 / 7e5, rel=0.15)
    assert use.max_outside_px == pytest.approx(np.hypot(100, 100), abs=1.0)
    # 50 nm beyond at 0.02 px/nm; a corner moves 41 px along the diagonal, so x by 29 px
    # and ey = 0.01 x by 0.29 px
    assert use.spectral_effect_px == pytest.approx(0.02 * 50)
    assert use.spatial_effect_px == pytest.approx(0.01 * (np.hypot(100, 100) - 100) / np.sqrt(2))
    message = use.message()
    assert "400.0 → 450.0, 700.0 → 687.0 nm (calibrated 450.0–687.0 nm" in message
    assert "(clamped)" in message and "differs by up to 1.00 px there" in message
    # the corners' clamping changes Φ by 0.29 px: said too
    assert "% of the image lies more than 100 px (one keypoint spacing)" in message
    plain = use.to_dict()
    assert plain["outside_nm"] == [400.0, 700.0] and plain["policy"] == "clamp"
    assert "extrapolated" in domain_use(model, wavelengths_nm=[400.0], policy="allow").message()
    with pytest.raises(
        DataError, match=r"400.0 nm .*clamp it to its domain with extrapolation='clamp'"
    ):
        domain_use(model, wavelengths_nm=[400.0], policy="refuse")
    with pytest.raises(DataError, match="unknown extrapolation 'sometimes'"):
        domain_use(model, policy="sometimes")


def test_a_model_over_the_whole_image_is_inside() -> None:
    model = planted_dispersion_model(
        {"spectral": SlopeField()},
        shape=(64, 80),
        direction="to_reference",
        wavelength_span=(400.0, 700.0),
    )
    use = domain_use(model, wavelengths_nm=[400.0, 550.0, 700.0])
    assert not use.outside and use.message() is None and use.area_outside == 0.0


def test_positions_beyond_the_margin_matter_only_when_the_field_changes_there() -> None:
    """A field constant in x and y: clamping positions changes nothing, so no warning;
    the log still records how much of the image lies beyond the keypoints."""

    class Constant(SlopeField):
        def evaluate(self, points: np.ndarray) -> np.ndarray:
            return np.column_stack([0.02 * (points[:, 2] - 600.0), np.zeros(len(points))])

    model = replace(model_over(grid_region()), fields={"spectral": Constant()})
    use = domain_use(model, wavelengths_nm=[500.0, 600.0])
    assert use.area_outside > 0 and use.spatial_effect_px == 0.0
    assert not use.outside and use.message() is None
    domain_use(model, wavelengths_nm=[500.0, 600.0], policy="refuse")  # nothing to refuse


def test_a_cropped_model_is_the_sensor_model_at_the_crops_place(tmp_path) -> None:
    """A model of the whole sensor used on a crop: at the crop's pixel (x, y) it gives the
    sensor's displacement at (x + col, y + row), its region moves with it, and it survives a
    save and load; a window outside the image is refused."""
    from _helpers import lens_model_file

    from calibration.dispersion_model import load_dispersion_model

    sensor = load_dispersion_model(lens_model_file(tmp_path / "lens.yaml", (96, 128)))
    crop = sensor.cropped((20, 34), (48, 64))
    assert crop.image_shape == (48, 64)
    assert crop.provenance["crop"] == {"origin": [20, 34], "shape": [48, 64],
                                       "image_shape": [96, 128]}  # fmt: skip
    yy, xx = np.mgrid[0:48:7, 0:64:9].astype(float)
    for wave in (450.0, 520.0, 650.0):
        np.testing.assert_array_equal(
            np.stack(crop.displacement(xx, yy, wave)),
            np.stack(sensor.displacement(xx + 34, yy + 20, wave)),
        )
    np.testing.assert_array_equal(crop.region.hull_xy, sensor.region.hull_xy - [34, 20])
    crop.save(tmp_path / "crop.yaml")
    again = load_dispersion_model(tmp_path / "crop.yaml")
    np.testing.assert_array_equal(
        np.stack(again.displacement(xx, yy, 500.0)), np.stack(crop.displacement(xx, yy, 500.0))
    )
    # clamping uses the moved region: a crop pixel maps to the sensor's clamped value
    clamped = crop.within_domain("clamp")
    np.testing.assert_allclose(
        np.stack(clamped.displacement(xx, yy, 700.0)),
        np.stack(sensor.within_domain("clamp").displacement(xx + 34, yy + 20, 700.0)),
    )
    with pytest.raises(DataError, match="does not lie inside the model's 96×128 px image"):
        sensor.cropped((60, 0), (48, 64))


def test_clamping_before_broadcasting_matches_point_by_point() -> None:
    """Positions given once for many wavelengths are clamped once: the same displacements
    as clamping every (x, y, λ) point, positions beyond the hull and λ beyond the range
    included; and a spectral Φ evaluated for all bands at once equals Φ band by band."""
    model = model_over(grid_region()).within_domain()
    x = np.linspace(-50.0, 1050.0, 12)[None, :, None]  # beyond the hull at both ends
    y = np.linspace(20.0, 680.0, 9)[:, None, None]
    waves = np.array([400.0, 450.0, 560.0, 700.0])[None, None, :]
    dx, dy = model.displacement(x, y, waves)
    grid = np.broadcast_arrays(x, y, waves)
    each = [
        model.displacement(float(a), float(b), float(c))
        for a, b, c in zip(*(g.ravel() for g in grid), strict=True)
    ]
    np.testing.assert_allclose(dx.ravel(), [e[0] for e in each], rtol=0, atol=1e-12)
    np.testing.assert_allclose(dy.ravel(), [e[1] for e in each], rtol=0, atol=1e-12)
    at_once = Dispersion(
        model,
        waves.ravel(),
        origin=(650, 950),
        shape=(16, 16),
        overhang_px=8,
        interpolation="cubic",
    )
    for j, w in enumerate(waves.ravel()):
        alone = Dispersion(
            model,
            np.array([w]),
            origin=(650, 950),
            shape=(16, 16),
            overhang_px=8,
            interpolation="cubic",
        )
        np.testing.assert_array_equal(at_once.taps.weights_x[j], alone.taps.weights_x[0])
        np.testing.assert_array_equal(at_once.taps.offsets_y[j], alone.taps.offsets_y[0])
    with pytest.raises(DataError, match="NaN or Inf"):
        model.displacement(np.array([np.nan]), 300.0, 500.0)
