"""Known-answer tests of the spectral core (labkit.spectra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.spectra import (
    COLORCHECKER_PATCHES,
    Spectra,
    camera_response,
    colorchecker_reflectances,
    integration_matrix,
    measured_transmission,
    parametric_transmission,
    spectral_to_raw,
    spectral_to_srgb,
    trapezoid_weights,
    uhp_lamp,
    wavelength_grid,
    write_response_csv,
)

MERCURY_LINES_NM = (404.7, 435.8, 546.1, 578.0)


def _crossings(wavelengths: np.ndarray, values: np.ndarray, level: float) -> tuple[float, float]:
    """First rising and last falling wavelength where `values` crosses `level` (linear interp)."""
    above = np.flatnonzero(values >= level)
    i, j = above[0], above[-1]
    assert i > 0 and j < len(values) - 1, "the passband must lie inside the grid"
    rise = np.interp(level, values[i - 1 : i + 1], wavelengths[i - 1 : i + 1])
    fall = np.interp(level, values[j : j + 2][::-1], wavelengths[j : j + 2][::-1])
    return float(rise), float(fall)


# -- wavelength_grid ----------------------------------------------------------------------


def test_wavelength_grid_is_inclusive_and_evenly_spaced() -> None:
    grid = wavelength_grid(400.0, 700.0, 10.0)
    assert grid.shape == (31,)
    assert grid[0] == 400.0 and grid[-1] == 700.0
    np.testing.assert_allclose(np.diff(grid), 10.0, rtol=0, atol=1e-12)
    fine = wavelength_grid(380.0, 780.0, 1.0)
    assert fine.shape == (401,) and fine[-1] == 780.0
    np.testing.assert_array_equal(fine, np.arange(380.0, 781.0))


@pytest.mark.parametrize(("start", "stop", "step"), [(700, 400, 10), (400, 400, 1), (400, 700, 0)])
def test_wavelength_grid_rejects_empty(start: float, stop: float, step: float) -> None:
    with pytest.raises(DataError, match="empty"):
        wavelength_grid(start, stop, step)


# -- Spectra ------------------------------------------------------------------------------


def _linear_spectra() -> Spectra:
    w = np.array([400.0, 450.0, 500.0, 600.0])
    values = np.column_stack([2.0 * w - 100.0, -0.5 * w + 400.0])  # two linear spectra
    return Spectra(w, values, ("up", "down"))


def test_resample_is_exact_on_linear_data() -> None:
    data = _linear_spectra()
    target = np.array([400.0, 401.5, 433.3, 475.0, 512.25, 599.9, 600.0])
    out = data.resample(target)
    np.testing.assert_allclose(out["up"], 2.0 * target - 100.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out["down"], -0.5 * target + 400.0, rtol=0, atol=1e-9)
    assert out.labels == ("up", "down")


def test_resample_extrapolation_modes() -> None:
    data = _linear_spectra()
    target = np.array([350.0, 400.0, 500.0, 600.0, 650.0])
    zero = data.resample(target, extrapolate="zero")
    np.testing.assert_allclose(zero["up"], [0.0, 700.0, 900.0, 1100.0, 0.0], atol=1e-9)
    constant = data.resample(target, extrapolate="constant")
    np.testing.assert_allclose(constant["up"], [700.0, 700.0, 900.0, 1100.0, 1100.0], atol=1e-9)
    np.testing.assert_allclose(constant["down"], [200.0, 200.0, 150.0, 100.0, 100.0], atol=1e-9)
    inside = data.resample(np.array([400.0, 600.0]), extrapolate="error")
    np.testing.assert_allclose(inside["up"], [700.0, 1100.0], atol=1e-9)
    with pytest.raises(DataError, match=r"400–600 nm"):
        data.resample(target, extrapolate="error")


def test_spectra_validation_errors() -> None:
    with pytest.raises(DataError, match="strictly increasing"):
        Spectra(np.array([400.0, 400.0, 500.0]), np.ones(3), ("a",))
    with pytest.raises(DataError, match="NaN or Inf"):
        Spectra(np.array([400.0, 500.0]), np.array([1.0, np.nan]), ("a",))
    with pytest.raises(DataError, match="2 labels for 1 spectra"):
        Spectra(np.array([400.0, 500.0]), np.ones(2), ("a", "b"))
    with pytest.raises(KeyError, match="no spectrum named 'c'"):
        _linear_spectra()["c"]


# -- trapezoid rule -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "grid",
    [
        wavelength_grid(400.0, 700.0, 10.0),
        wavelength_grid(380.0, 780.0, 1.0),
        np.array([400.0, 403.0, 411.0, 430.0, 470.0, 520.0, 600.0, 650.0, 700.0]),
    ],
    ids=["10nm", "1nm", "uneven"],
)
def test_trapezoid_integrates_square_within_error_bound(grid: np.ndarray) -> None:
    w = trapezoid_weights(grid)
    a, b = grid[0], grid[-1]
    exact = (b**3 - a**3) / 3.0
    got = float(w @ grid**2)
    # trapezoid error = Σ h³ f''/12 per interval with f'' = 2 (exact for a quadratic)
    bound = float(np.sum(np.diff(grid) ** 3) * 2.0 / 12.0)
    assert got >= exact, "the trapezoid rule overestimates a convex function"
    assert got - exact == pytest.approx(bound, rel=1e-9), (
        f"x² error {got - exact} should equal the trapezoid bound {bound}"
    )
    # a linear function is integrated exactly
    linear = float(w @ (3.0 * grid + 7.0))
    assert linear == pytest.approx(1.5 * (b**2 - a**2) + 7.0 * (b - a), rel=1e-12)
    assert w.sum() == pytest.approx(b - a, rel=1e-12)


def test_trapezoid_weights_hand_values() -> None:
    np.testing.assert_allclose(
        trapezoid_weights(np.array([400.0, 410.0, 430.0, 460.0])), [5.0, 15.0, 25.0, 15.0]
    )
    with pytest.raises(DataError):
        trapezoid_weights(np.array([400.0]))


# -- spectral → raw -------------------------------------------------------------------------


def _hand_response() -> Spectra:
    w = np.array([400.0, 420.0, 440.0])
    values = np.array([[0.0, 1.0, 2.0], [1.0, 1.0, 0.0], [2.0, 1.0, 4.0]])  # rows = λ
    return Spectra(w, values, ("R", "G", "B"))


def test_integration_matrix_matches_hand_trapezoid() -> None:
    bands = np.array([400.0, 410.0, 430.0])
    # response resampled onto the bands: 400 → row 0; 410 → mean of rows 0, 1; 430 → rows 1, 2
    sampled = np.array([[0.0, 1.0, 2.0], [0.5, 1.0, 1.0], [1.5, 1.0, 2.0]])
    weights = np.array([5.0, 15.0, 10.0])  # trapezoid weights of the bands
    expected = sampled * weights[:, None]
    omega = integration_matrix(bands, _hand_response())
    np.testing.assert_allclose(omega, expected, rtol=1e-12)

    image = np.array([[1.0, 2.0, 3.0], [0.5, 0.0, 4.0]])  # two pixels, three bands
    raw = spectral_to_raw(image, bands, _hand_response())
    # pixel 0: R = 1·0·5 + 2·0.5·15 + 3·1.5·10 = 60; G = 5 + 30 + 30 = 65; B = 10 + 30 + 60 = 100
    # pixel 1: R = 0 + 0 + 4·1.5·10 = 60;  G = 2.5 + 40 = 42.5; B = 5 + 80 = 85
    np.testing.assert_allclose(raw, [[60.0, 65.0, 100.0], [60.0, 42.5, 85.0]], rtol=1e-12)


def test_spectral_to_raw_errors() -> None:
    with pytest.raises(DataError, match="400–440 nm"):
        spectral_to_raw(np.ones((2, 3)), np.array([390.0, 410.0, 430.0]), _hand_response())
    with pytest.raises(DataError, match="400–440 nm"):
        integration_matrix(np.array([400.0, 450.0]), _hand_response())
    with pytest.raises(DataError, match="3 bands but 2 wavelengths"):
        spectral_to_raw(np.ones((2, 3)), np.array([400.0, 420.0]), _hand_response())


# -- datasets -------------------------------------------------------------------------------


def test_nikon_response() -> None:
    response = camera_response("Nikon 5100 (NPL)")
    assert response.labels == ("R", "G", "B")
    assert response.domain == (380.0, 780.0)
    np.testing.assert_allclose(response.values.max(axis=0), 1.0, atol=1e-6)
    peaks = response.wavelengths[response.values.argmax(axis=0)]
    assert peaks[2] < peaks[1] < peaks[0], f"B < G < R peak wavelengths, got {peaks}"


def test_unknown_response_names_the_choices() -> None:
    with pytest.raises(DataError, match="Nikon 5100"):
        camera_response("No Such Camera")


def test_response_csv_round_trip(tmp_path: Path) -> None:
    response = camera_response("Nikon 5100 (NPL)")
    path = tmp_path / "response.csv"
    write_response_csv(response, path)
    assert path.read_text().splitlines()[0] == "wavelength_nm,R,G,B"
    back = camera_response(path)
    assert back.labels == ("R", "G", "B")
    np.testing.assert_allclose(back.wavelengths, response.wavelengths, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.values, response.values, rtol=1e-5, atol=1e-9)  # %.6g


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("wavelength,R,G,B\n400,1,1,1\n410,1,1,1\n", "header"),
        ("wavelength_nm,R,G\n400,1,1\n410,1,1\n", "header"),
        ("wavelength_nm,R,G,B\n400,1,x,1\n410,1,1,1\n", "non-numeric"),
        ("wavelength_nm,R,G,B\n400,1,1,1\n", "at least two rows"),
        ("wavelength_nm,R,G,B\n400,1,-1,1\n410,1,1,1\n", "≥ 0"),
        ("wavelength_nm,R,G,B\n410,1,1,1\n400,1,1,1\n", "increasing"),
    ],
    ids=["header-name", "header-columns", "non-numeric", "one-row", "negative", "decreasing"],
)
def test_malformed_response_csv_names_the_file(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad_response.csv"
    path.write_text(text)
    with pytest.raises(DataError, match=match) as info:
        camera_response(path)
    assert str(path) in str(info.value), f"message should name {path}: {info.value}"


def test_missing_response_csv(tmp_path: Path) -> None:
    path = tmp_path / "nope.csv"
    with pytest.raises(DataError, match="does not exist") as info:
        camera_response(path)
    assert str(path) in str(info.value)


def test_measured_colorchecker() -> None:
    chart = colorchecker_reflectances("measured")
    assert chart.labels == COLORCHECKER_PATCHES and len(chart.labels) == 24
    band = (chart.wavelengths >= 450) & (chart.wavelengths <= 650)
    white = chart["white 9.5 (.05 D)"][band].mean()
    black = chart["black 2 (1.5 D)"][band].mean()
    assert 0.9 <= white <= 1.1, f"white patch mean reflectance 450–650 nm = {white}"
    assert black < 0.06, f"black patch mean reflectance 450–650 nm = {black}"
    greys = [chart[name][band].mean() for name in COLORCHECKER_PATCHES[18:]]
    assert np.all(np.diff(greys) < 0), f"the neutral row must darken left to right: {greys}"


def test_colour_science_colorchecker() -> None:
    chart = colorchecker_reflectances("BabelColor Average")
    assert chart.labels == COLORCHECKER_PATCHES
    band = (chart.wavelengths >= 450) & (chart.wavelengths <= 650)
    assert 0.8 <= chart["white 9.5 (.05 D)"][band].mean() <= 1.0
    with pytest.raises(DataError, match="unknown ColorChecker source"):
        colorchecker_reflectances("nope")


# -- filters ------------------------------------------------------------------------------


def test_measured_550_filter_peak_and_fwhm() -> None:
    grid = wavelength_grid(380.0, 780.0, 0.5)
    t = measured_transmission("550 nm", grid)
    peak = grid[t.argmax()]
    assert 540.0 <= peak <= 556.0, f"550 nm filter peaks at {peak} nm"
    rise, fall = _crossings(grid, t, t.max() / 2)
    assert 8.0 <= fall - rise <= 16.0, f"550 nm filter FWHM {fall - rise:.2f} nm"
    assert rise < peak < fall


def test_measured_442_filter_secondary_peak_and_floor() -> None:
    grid = wavelength_grid(380.0, 780.0, 1.0)
    t = measured_transmission("442 nm", grid, optical_density=4.0)
    peak = t.max()
    assert 435.0 <= grid[t.argmax()] <= 450.0
    near_390 = t[(grid >= 385) & (grid <= 395)]
    assert near_390.min() > 0.05 * peak, (
        f"secondary passband near 390 nm must be kept (> 5 % of peak), got {near_390.min():.4f}"
    )
    far = (grid >= 480) & (grid <= 760)
    np.testing.assert_array_equal(t[far], 1e-4)  # blocked: exactly 10**-OD
    t3 = measured_transmission("442 nm", grid, optical_density=3.0)
    np.testing.assert_array_equal(t3[far], 1e-3)


def test_measured_filter_unknown_column() -> None:
    with pytest.raises(DataError, match="no measured filter '451 nm'"):
        measured_transmission("451 nm", np.array([400.0, 500.0]))


@pytest.mark.parametrize(("centre", "fwhm", "od"), [(550.0, 10.0, 4.0), (432.5, 25.0, 3.0)])
def test_parametric_transmission_half_maximum_and_floor(
    centre: float, fwhm: float, od: float
) -> None:
    grid = wavelength_grid(350.0, 800.0, 0.01)
    t = parametric_transmission(grid, centre_nm=centre, fwhm_nm=fwhm, optical_density=od, peak=0.8)
    assert t.max() == pytest.approx(0.8, rel=1e-9)
    rise, fall = _crossings(grid, t, 0.4)
    assert abs(rise - (centre - fwhm / 2)) < 0.1, f"lower half maximum at {rise} nm"
    assert abs(fall - (centre + fwhm / 2)) < 0.1, f"upper half maximum at {fall} nm"
    far = np.abs(grid - centre) > 2 * fwhm
    np.testing.assert_allclose(t[far], 10.0**-od, rtol=1e-12)
    with pytest.raises(DataError):
        parametric_transmission(grid, centre_nm=centre, fwhm_nm=0.0)


# -- light and colour -----------------------------------------------------------------------


def test_uhp_lamp_peaks_at_a_mercury_line() -> None:
    grid = wavelength_grid(380.0, 780.0, 1.0)
    lamp = uhp_lamp(grid)
    assert lamp.labels == ("projector",)
    assert lamp.values.max() == pytest.approx(1.0)
    peak = grid[lamp.values[:, 0].argmax()]
    distance = min(abs(peak - line) for line in MERCURY_LINES_NM)
    assert distance <= 1.0, f"lamp peak {peak} nm is not at a mercury line {MERCURY_LINES_NM}"
    assert np.all(lamp.values > 0)


def test_flat_spectrum_is_near_white() -> None:
    grid = wavelength_grid(380.0, 780.0, 1.0)
    rgb = spectral_to_srgb(np.ones((2, len(grid))), grid)
    assert rgb.shape == (2, 3)
    assert np.all(rgb > 0.9), f"flat unit spectrum → sRGB {rgb[0]}"
    assert np.all(rgb <= 1.0)
    dark = spectral_to_srgb(np.zeros(len(grid)), grid)
    np.testing.assert_allclose(dark, 0.0, atol=1e-12)


# -- regressions of fixed bugs ---------------------------------------------------------------


def test_wavelength_grid_never_exceeds_stop() -> None:
    grid = wavelength_grid(400.0, 700.0, 7.0)
    assert grid[0] == 400.0
    assert grid[-1] <= 700.0, f"grid ends at {grid[-1]} nm, past the requested 700 nm"


def test_spectral_to_raw_of_integer_image() -> None:
    bands = np.array([400.0, 410.0, 430.0])
    raw = spectral_to_raw(np.array([[1, 2, 3]]), bands, _hand_response())
    np.testing.assert_allclose(raw, [[60.0, 65.0, 100.0]], rtol=1e-12)
