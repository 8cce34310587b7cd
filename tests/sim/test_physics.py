"""Acceptance tests of the simulated rig's physics, each against a known answer.

Sensor: linearity, Poisson–Gaussian noise, dark current, saturation and blooming.
Optics and renderer: disk centroids move by the lens' dispersion, flat fields stay flat,
disk areas are exact. Camera: determinism and GenICam-style features.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from labkit.cfa import mosaic
from labkit.errors import ConfigError, DeviceError
from labkit.rig import rig_from_dict
from labkit.sim import (
    CellGrid,
    Lens,
    Scene,
    Sensor,
    SensorModel,
    SimCamera,
    SimulatedRig,
    disk_pattern,
    flat_field,
    render_irradiance,
)
from labkit.spectra import camera_response, trapezoid_weights, uhp_lamp, wavelength_grid

WAVELENGTHS = wavelength_grid(380.0, 780.0, 1.0)


@pytest.fixture(scope="module")
def response():
    return camera_response("Nikon 5100 (NPL)")


@pytest.fixture(scope="module")
def lamp() -> np.ndarray:
    return uhp_lamp(WAVELENGTHS).values[:, 0]


def _monochromatic(wavelength_nm: float, power: float = 1.0e5) -> np.ndarray:
    """A light that is nonzero at one sample of the 1 nm grid only."""
    light = np.zeros_like(WAVELENGTHS)
    light[np.flatnonzero(np.isclose(WAVELENGTHS, wavelength_nm))] = power
    assert np.count_nonzero(light) == 1
    return light


def _sensor(shape: tuple[int, int], *, seed: int = 3, **overrides: float) -> Sensor:
    """A sensor with the rig's default physics, no shutter jitter, and `overrides`."""
    rows, cols = shape
    params = {"exposure_jitter_s": 0.0, **overrides}
    return Sensor(SensorModel(width=cols, height=rows, **params), seed=seed)


# == sensor =====================================================================================


@pytest.fixture(scope="module")
def flat_irradiance(response, lamp) -> dict[float, np.ndarray]:
    """Flat-field GBRG mosaics (e⁻/s) per reflectance, scaled so white G = 1e5 e⁻/s."""
    shape = TestLinearity.SHAPE
    lens = Lens(shape, max_shift_px=0.0)
    images = {}
    for rho in (1.0, *TestLinearity.REFLECTANCES):
        scene = flat_field(shape, reflectance=rho)
        rgb = render_irradiance(scene, lens, response, {"l": lamp}, WAVELENGTHS)["l"]
        images[rho] = mosaic(rgb, "GBRG").astype(np.float64)
    scale = 1.0e5 / images[1.0][0, 0]  # GBRG: (0, 0) is a G pixel
    return {rho: (img * scale).astype(np.float32) for rho, img in images.items()}


class TestLinearity:
    """Mean signal (counts − black) ∝ exposure × radiance within 0.5 % below saturation."""

    SHAPE = (64, 64)
    EXPOSURES_S = (0.01, 0.02, 0.03, 0.045, 0.06)
    REFLECTANCES = (0.2, 0.5, 0.9)
    FRAMES = 4

    def _signal(self, sensor: Sensor, irradiance: np.ndarray, exposure_s: float, seed: int):
        """Mean (counts − black) over the G pixels and FRAMES frames, DN."""
        rng = np.random.default_rng(seed)
        green = sensor.channels == 1
        total = 0.0
        for _ in range(self.FRAMES):
            counts, actual = sensor.expose(irradiance, exposure_s, rng=rng)
            assert actual == exposure_s, "no shutter jitter was configured"
            total += counts[green].astype(np.float64).mean()
        return total / self.FRAMES - sensor.model.black_level_dn

    def test_renderer_is_linear_in_reflectance(self, flat_irradiance) -> None:
        for rho in self.REFLECTANCES:
            np.testing.assert_allclose(flat_irradiance[rho], rho * flat_irradiance[1.0], rtol=1e-6)

    def test_linear_in_exposure(self, flat_irradiance) -> None:
        sensor = _sensor(self.SHAPE)
        green = sensor.channels == 1
        x = np.array(self.EXPOSURES_S)
        y = np.array(
            [self._signal(sensor, flat_irradiance[1.0], t, 10 + i) for i, t in enumerate(x)]
        )
        assert y.max() < 0.8 * sensor.model.full_well_e * sensor.model.gain_dn_per_e
        slope = float(x @ y / (x @ x))  # least squares through the origin
        deviation = np.abs(y / (slope * x) - 1.0).max()
        assert deviation < 0.005, (
            f"signal vs exposure deviates {deviation:.2%} (> 0.5 %) from a line"
        )
        rate = (flat_irradiance[1.0] * sensor.prnu_map + sensor.dark_map)[green].mean()
        expected = sensor.model.gain_dn_per_e * rate
        assert slope == pytest.approx(expected, rel=0.005), "slope ≠ gain · mean e⁻/s (0.5 %)"

    def test_linear_in_radiance(self, flat_irradiance) -> None:
        sensor = _sensor(self.SHAPE)
        exposure = self.EXPOSURES_S[-1]
        x = np.array(self.REFLECTANCES)
        y = np.array(
            [
                self._signal(sensor, flat_irradiance[rho], exposure, 20 + i)
                for i, rho in enumerate(x)
            ]
        )
        slope = float(x @ y / (x @ x))
        deviation = np.abs(y / (slope * x) - 1.0).max()
        assert deviation < 0.005, f"signal vs reflectance deviates {deviation:.2%} (> 0.5 %)"


class TestNoise:
    """Per-pixel temporal variance matches the Poisson–Gaussian model within 5 %."""

    SHAPE = (32, 32)
    FRAMES = 256
    EXPOSURE_S = 0.01

    @pytest.mark.parametrize(
        ("mean_e", "gain_db"),
        [(2000.0, 0.0), (2000.0, 6.0), (10.0, 0.0)],
        ids=["mid-0dB", "mid-6dB", "low-poisson"],
    )
    def test_variance_matches_model(self, mean_e: float, gain_db: float) -> None:
        sensor = _sensor(self.SHAPE)
        model = sensor.model
        dark_e = model.dark_current_e_per_s * self.EXPOSURE_S
        irradiance = np.full(self.SHAPE, (mean_e - dark_e) / self.EXPOSURE_S, np.float32)
        rng = np.random.default_rng(99)
        frames = np.stack(
            [
                sensor.expose(irradiance, self.EXPOSURE_S, rng=rng, gain_db=gain_db)[0]
                for _ in range(self.FRAMES)
            ]
        ).astype(np.float64)
        mu = sensor.mean_electrons(irradiance, self.EXPOSURE_S).astype(np.float64)
        if mean_e < 30:
            assert mu.max() < 30, "this case must exercise the exact Poisson branch (< 30 e⁻)"
        measured = frames.var(axis=0, ddof=1)
        expected = model.expected_variance_dn(mu, gain_db)
        ratio = float((measured / expected).mean())
        assert ratio == pytest.approx(1.0, abs=0.05), (
            f"measured/expected variance = {ratio:.4f} (tolerance 5 %)"
        )
        # the mean follows too: gain · μ + black, to 5 standard errors of the frame mean
        g = model.gain_factor(gain_db)
        offset = float((frames.mean(axis=0) - (g * mu + model.black_level_dn)).mean())
        tolerance = 5.0 * float(np.sqrt(expected.mean() / frames.size))
        assert abs(offset) < tolerance, (
            f"mean counts off by {offset:.3f} DN (tolerance {tolerance:.3f} DN = 5 SE)"
        )

    def test_low_signal_is_exactly_poisson(self) -> None:
        """With unit gain and no read noise or black level, counts are Poisson(μ) integers."""
        shape = (64, 64)
        sensor = _sensor(
            shape,
            gain_dn_per_e=1.0,
            read_noise_e=0.0,
            black_level_dn=0.0,
            prnu=0.0,
            dark_current_e_per_s=0.0,
        )
        mu = 3.0
        irradiance = np.full(shape, mu / 0.01, np.float32)
        rng = np.random.default_rng(5)
        counts = np.concatenate(
            [sensor.expose(irradiance, 0.01, rng=rng)[0].ravel() for _ in range(100)]
        )
        histogram = np.bincount(counts, minlength=12)[:9] / counts.size
        k = np.arange(9)
        pmf = np.exp(-mu) * mu**k / np.array([np.prod(np.arange(1, n + 1)) for n in k])
        np.testing.assert_allclose(histogram, pmf, rtol=0, atol=0.003)  # ≥ 4.5σ for 409600 draws
        assert counts.mean() == pytest.approx(mu, abs=0.02)


class TestDark:
    """Dark frames: black level + gain · dark current · t."""

    SHAPE = (128, 128)
    EXPOSURES_S = (0.5, 1.0, 2.0, 4.0)
    FRAMES = 8

    def test_dark_map_has_the_nominal_mean(self) -> None:
        sensor = _sensor(self.SHAPE)
        rate = sensor.model.dark_current_e_per_s
        assert float(sensor.dark_map.mean()) == pytest.approx(rate, rel=0.01)
        assert float(np.log(sensor.dark_map).std()) == pytest.approx(0.2, rel=0.02)

    def test_dark_level_and_slope(self) -> None:
        sensor = _sensor(self.SHAPE)
        model = sensor.model
        rng = np.random.default_rng(21)
        means = []
        for t in self.EXPOSURES_S:
            frames = [sensor.expose(None, t, rng=rng)[0] for _ in range(self.FRAMES)]
            mean = float(np.mean(frames, dtype=np.float64))
            nominal = model.black_level_dn + model.gain_dn_per_e * model.dark_current_e_per_s * t
            assert mean == pytest.approx(nominal, abs=0.05), (
                f"dark mean at {t} s = {mean:.3f} DN, expected {nominal:.3f} ± 0.05 DN"
            )
            means.append(mean)
        slope, intercept = np.polyfit(self.EXPOSURES_S, means, 1)
        expected = model.gain_dn_per_e * float(sensor.dark_map.mean())
        assert slope == pytest.approx(expected, rel=0.02), (
            f"dark slope {slope:.4f} DN/s, expected {expected:.4f} DN/s ± 2 %"
        )
        assert intercept == pytest.approx(model.black_level_dn, abs=0.05)


class TestSaturation:
    """A bright spot clips at the full well (or the ADC) and blooms along its column."""

    SHAPE = (64, 64)
    SPOT = (32, 33)

    def _frames(self, sensor: Sensor) -> tuple[np.ndarray, np.ndarray]:
        # background ≥ 30 e⁻ everywhere: every pixel takes the Gaussian branch, so both
        # frames consume the same random numbers and differ only through the spot
        background = np.full(self.SHAPE, 1.0e5, np.float32)  # 1000 e⁻ in 10 ms
        spot = background.copy()
        spot[self.SPOT] = 1.0e8  # 100 full wells
        plain, _ = sensor.expose(background, 0.01, rng=np.random.default_rng(7))
        bright, _ = sensor.expose(spot, 0.01, rng=np.random.default_rng(7))
        return plain, bright

    @pytest.mark.parametrize("gain", [0.4, 0.5], ids=["full-well", "adc"])
    def test_saturation_level(self, gain: float) -> None:
        sensor = _sensor(self.SHAPE, gain_dn_per_e=gain)
        model = sensor.model
        plain, bright = self._frames(sensor)
        level = min(round(model.full_well_e * gain + model.black_level_dn), model.adc_max)
        assert level == (4032 if gain == 0.4 else 4095)
        assert bright[self.SPOT] == level
        assert bright.max() == level, "nothing exceeds the saturation level"
        assert plain.max() < 0.5 * level, "the background is far from saturation"

    def test_blooming_runs_along_the_column(self) -> None:
        sensor = _sensor(self.SHAPE)
        plain, bright = self._frames(sensor)
        r, c = self.SPOT
        for dr in (-3, -2, -1, 1, 2, 3):
            assert int(bright[r + dr, c]) > int(plain[r + dr, c]) + 100, (
                f"pixel {dr:+d} rows from the spot received no spilled charge"
            )
        changed = np.argwhere(bright != plain)
        rows_span = np.ptp(changed[:, 0])
        cols_span = np.ptp(changed[:, 1])
        assert rows_span > cols_span, "charge spills mostly vertically (interline CCD)"
        far = np.ones(self.SHAPE, bool)
        far[r - 10 : r + 11, c - 10 : c + 11] = False
        np.testing.assert_array_equal(bright[far], plain[far])


def test_sensor_model_validation() -> None:
    with pytest.raises(ConfigError, match="even sizes"):
        SensorModel(width=33, height=32)
    with pytest.raises(ConfigError, match="full_well_e"):
        SensorModel(width=32, height=32, full_well_e=0)
    with pytest.raises(ConfigError, match="exposure must be > 0"):
        _sensor((4, 4)).expose(None, 0.0, rng=np.random.default_rng(0))


# == optics and renderer =======================================================================

DISK_SHAPE = (256, 320)
DISK_PITCH = 40.0
WINDOW = 19  # half-width of the centroid window: the disk ± the largest shift, no neighbours


def _disk_scene(radius: float) -> Scene:
    return disk_pattern(
        DISK_SHAPE, radius_px=radius, pitch_px=DISK_PITCH, margin_px=20.0, offset_px=(0.31, 0.17)
    )


def _paper(scene: Scene) -> Scene:
    return Scene("paper", scene.materials, scene.grid)


def _centroids(image: np.ndarray, background: float, centres: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroids (x, y) of (background − image) around each centre."""
    out = []
    for cx, cy in centres:
        x0, y0 = round(cx), round(cy)
        ys, xs = slice(y0 - WINDOW, y0 + WINDOW + 1), slice(x0 - WINDOW, x0 + WINDOW + 1)
        weight = background - image[ys, xs]
        yy, xx = np.mgrid[ys, xs]
        out.append(((weight * xx).sum() / weight.sum(), (weight * yy).sum() / weight.sum()))
    return np.array(out)


def _green(scene: Scene, lens: Lens, response, light: np.ndarray, **kwargs) -> np.ndarray:
    rgb = render_irradiance(scene, lens, response, {"l": light}, WAVELENGTHS, **kwargs)["l"]
    return rgb[..., 1].astype(np.float64)


def _measured_shift(scene: Scene, lens: Lens, response, light: np.ndarray, **kwargs) -> np.ndarray:
    """Centroid with the lens' dispersion minus centroid without, per disk (n, 2), px."""
    still = Lens(lens.shape, max_shift_px=0.0)
    background = _green(_paper(scene), still, response, light)
    assert np.ptp(background) <= 1e-6 * background.mean(), "paper renders flat"
    centres = scene.disks.centres()
    with_d = _centroids(_green(scene, lens, response, light, **kwargs), background[0, 0], centres)
    without = _centroids(_green(scene, still, response, light), background[0, 0], centres)
    assert np.abs(without - centres).max() < 0.01, "undispersed centroids sit on the disks"
    return with_d - without


# (radial profile, spectral profile, disk radius): the non-monotonic field is curved, which
# moves a disk's centroid away from the displacement at its centre by ~ A r²/R² (≈ 0.02 px
# for r = 8 at the corners), so that case uses r = 6 (see the exact-geometry test below).
LENS_CASES = [
    ("linear", "singlet", 8.0),
    ("nonmonotonic", "singlet", 6.0),
    ("linear", "achromat", 8.0),
]
LENS_IDS = ["linear-singlet", "nonmonotonic-singlet", "linear-achromat"]


@pytest.mark.parametrize(("radial", "spectral", "radius"), LENS_CASES, ids=LENS_IDS)
@pytest.mark.parametrize("wavelength", [450.0, 680.0])
def test_monochromatic_disk_shift_equals_displacement(
    response, radial: str, spectral: str, radius: float, wavelength: float
) -> None:
    lens = Lens(DISK_SHAPE, max_shift_px=3.0, radial_profile=radial, spectral_profile=spectral)
    scene = _disk_scene(radius)
    centres = scene.disks.centres()
    assert len(centres) >= 30
    shift = _measured_shift(scene, lens, response, _monochromatic(wavelength))
    dx, dy = lens.displacement(centres[:, 0], centres[:, 1], wavelength)
    assert np.hypot(dx, dy).max() > 0.25, "the test needs visible shifts"
    error = np.hypot(shift[:, 0] - dx, shift[:, 1] - dy)
    assert error.max() < 0.02, (
        f"disk shift differs from lens.displacement by up to {error.max():.4f} px (> 0.02 px)"
    )


@pytest.mark.parametrize(("radial", "spectral", "radius"), LENS_CASES, ids=LENS_IDS)
@pytest.mark.parametrize("level_step_px", [0.25, 1.0])
def test_broadband_disk_shift_is_weighted_mean_displacement(
    response, lamp, radial: str, spectral: str, radius: float, level_step_px: float
) -> None:
    lens = Lens(DISK_SHAPE, max_shift_px=3.0, radial_profile=radial, spectral_profile=spectral)
    scene = _disk_scene(radius)
    centres = scene.disks.centres()
    shift = _measured_shift(scene, lens, response, lamp, level_step_px=level_step_px)
    # spectral weights of the disk's contrast in G: w = Q_G E (R_paper − R_ink) · trapezoid
    q_green = response.resample(WAVELENGTHS, extrapolate="zero")["G"]
    reflect = scene.materials.resample(WAVELENGTHS, extrapolate="constant").values
    w = q_green * lamp * (reflect[:, 0] - reflect[:, 1]) * trapezoid_weights(WAVELENGTHS)
    dx, dy = lens.displacement(centres[:, :1], centres[:, 1:], WAVELENGTHS[None, :])
    expected = np.column_stack([dx @ w, dy @ w]) / w.sum()
    error = np.hypot(*(shift - expected).T)
    assert error.max() < 0.02, (
        f"broadband disk shift differs from the weighted displacement by {error.max():.4f} px"
    )


def test_nonmonotonic_shift_matches_exact_geometry(response) -> None:
    """For r = 8 the curved field's centroid is the Jacobian-weighted mean of p + d(p)."""
    lens = Lens(DISK_SHAPE, max_shift_px=3.0, radial_profile="nonmonotonic")
    scene = _disk_scene(8.0)
    wavelength = 450.0
    shift = _measured_shift(scene, lens, response, _monochromatic(wavelength))
    step, eps = 0.05, 1e-3
    offsets = np.arange(-9.5, 9.5 + step / 2, step)
    expected = []
    for cx, cy in scene.disks.centres():
        qx, qy = (a.ravel() for a in np.meshgrid(cx + offsets, cy + offsets))
        cover = scene.disks.coverage(qx, qy).astype(np.float64)  # pixel-box blurred disk
        ux, uy = lens.displacement(qx, qy, wavelength)
        ax, ay = lens.displacement(qx + eps, qy, wavelength)
        bx, by = lens.displacement(qx, qy + eps, wavelength)
        det = (1 + (ax - ux) / eps) * (1 + (by - uy) / eps) - (bx - ux) * (ay - uy) / eps**2
        f = cover * det
        expected.append(
            (
                (f * (qx + ux)).sum() / f.sum() - (cover * qx).sum() / cover.sum(),
                (f * (qy + uy)).sum() / f.sum() - (cover * qy).sum() / cover.sum(),
            )
        )
    error = np.hypot(*(shift - np.array(expected)).T)
    assert error.max() < 0.01, f"shift differs from the exact geometry by {error.max():.4f} px"


@pytest.mark.parametrize("max_shift_px", [0.0, 3.0])
@pytest.mark.parametrize("light_kind", ["broadband", "monochromatic"])
def test_flat_field_renders_flat(response, lamp, max_shift_px: float, light_kind: str) -> None:
    shape = (64, 80)
    lens = Lens(shape, max_shift_px=max_shift_px, vignetting=0.0, blur_sigma_px=0.0)
    light = lamp * 1e5 if light_kind == "broadband" else _monochromatic(550.0)
    rgb = render_irradiance(
        flat_field(shape, reflectance=0.7), lens, response, {"l": light}, WAVELENGTHS
    )["l"]
    expected = 0.7 * (
        response.resample(WAVELENGTHS).values * (light * trapezoid_weights(WAVELENGTHS))[:, None]
    ).sum(axis=0)
    for channel in range(3):
        image = rgb[..., channel].astype(np.float64)
        relative_std = image.std() / image.mean()
        assert relative_std < 1e-5, f"channel {channel}: relative std {relative_std:.2e} ≥ 1e-5"
        assert image.mean() == pytest.approx(expected[channel], rel=1e-5)


def test_vignetting_map_follows_cos4(response) -> None:
    lens = Lens((64, 80), vignetting=0.15)
    v = lens.vignetting_map()
    assert v.max() == pytest.approx(1.0, abs=1e-3)
    assert v[0, 0] == pytest.approx(0.85, rel=1e-5) and v[-1, -1] == pytest.approx(0.85, rel=1e-5)


@pytest.mark.parametrize("radius", [8.0, 7.3])
def test_disk_area_is_exact(response, lamp, radius: float) -> None:
    shape = (96, 96)
    scene = disk_pattern(
        shape, radius_px=radius, pitch_px=40.0, margin_px=20.0, offset_px=(0.37, 0.21)
    )
    cx, cy = scene.disks.centres()[0]
    x0, y0 = round(cx), round(cy)
    ys, xs = slice(y0 - WINDOW, y0 + WINDOW + 1), slice(x0 - WINDOW, x0 + WINDOW + 1)
    area = np.pi * radius**2
    coverage = scene.coverage_image(shape)
    np.testing.assert_allclose(coverage.sum(axis=2), 1.0, atol=1e-6)
    ink = float(coverage[ys, xs, 1].sum())
    assert ink == pytest.approx(area, rel=1e-3), (
        f"coverage area {ink:.3f} vs πr² {area:.3f} (0.1 %)"
    )
    # the same through the renderer: normalise between all-paper and all-ink irradiance
    lens = Lens(shape, max_shift_px=0.0)
    image = _green(scene, lens, response, lamp)[ys, xs]
    paper = _green(_paper(scene), lens, response, lamp)[0, 0]
    all_ink = Scene("ink", scene.materials, CellGrid(np.ones((1, 1), int), 98.0, outside=1))
    ink_level = _green(all_ink, lens, response, lamp)[0, 0]
    rendered = float(((paper - image) / (paper - ink_level)).sum())
    assert rendered == pytest.approx(area, rel=1e-3), (
        f"rendered area {rendered:.3f} vs πr² {area:.3f}"
    )


# == camera ======================================================================================


def test_same_seed_same_frames(small_sim_rig: SimulatedRig) -> None:
    frames_a = SimCamera(small_sim_rig, seed=5).grab(0.004, 3)
    frames_b = SimCamera(small_sim_rig, seed=5).grab(0.004, 3)
    frames_c = SimCamera(small_sim_rig, seed=6).grab(0.004, 3)
    for a, b, c in zip(frames_a, frames_b, frames_c, strict=True):
        assert a.frame_id == b.frame_id == c.frame_id
        np.testing.assert_array_equal(a.image, b.image)
        assert a.extra["light_level"] == b.extra["light_level"]
        assert not np.array_equal(a.image, c.image), "different seeds must give different noise"
    assert not np.array_equal(frames_a[0].image, frames_a[1].image), "frames differ by id"


def test_dark_frame_through_camera(small_sim_rig: SimulatedRig) -> None:
    camera = SimCamera(small_sim_rig, seed=8)
    camera.set_illumination("dark")
    frame = camera.grab(1.0, 1)[0]
    model = small_sim_rig.sensor.model
    assert frame.extra["dark"] is True
    t = frame.extra["true_exposure_s"]
    assert t == pytest.approx(1.0, abs=1e-4)
    expected = (
        model.black_level_dn + model.gain_dn_per_e * float(small_sim_rig.sensor.dark_map.mean()) * t
    )
    assert float(frame.image.mean()) == pytest.approx(expected, abs=0.1)


def test_exposure_time_feature(small_sim_rig: SimulatedRig) -> None:
    camera = SimCamera(small_sim_rig)
    camera.set("ExposureTime", 12345.0)
    assert camera.get("ExposureTime") == 12345.0
    camera.set("ExposureTime", 12345.4)
    assert camera.get("ExposureTime") == 12345.0, "1 µs increment"
    for bad in (5.0, 4.0e7, float("nan")):
        with pytest.raises(DeviceError, match="ExposureTime"):
            camera.set("ExposureTime", bad)
    assert camera.get("ExposureTime") == 12345.0, "a rejected value leaves the feature as it was"
    frame = camera.grab(0.0125, 1)[0]
    assert camera.get("ExposureTime") == 12500.0
    assert frame.exposure_s == pytest.approx(0.0125, rel=1e-12)
    with pytest.raises(DeviceError, match="not writable"):
        camera.set("Width", 64)


def test_pixel_formats_scale_counts(small_sim_rig: SimulatedRig) -> None:
    cameras = {}
    for bits in (8, 12, 16):
        camera = SimCamera(small_sim_rig, seed=11)
        camera.set_scene("colorchecker")
        camera.set("PixelFormat", f"BayerGB{bits}")
        cameras[bits] = camera.grab(0.004, 1)[0]
    raw = cameras[12].image
    assert raw.dtype == np.uint16 and raw.max() <= 4095 and raw.max() > 255
    assert cameras[8].image.dtype == np.uint8
    np.testing.assert_array_equal(cameras[8].image, (raw >> 4).astype(np.uint8))
    assert cameras[16].image.dtype == np.uint16
    np.testing.assert_array_equal(cameras[16].image, raw << 4)
    assert [cameras[b].pixel_format for b in (8, 12, 16)] == ["BayerGB8", "BayerGB12", "BayerGB16"]
    # the black level (32 DN at 12 bits) is reported in each format's own counts
    assert [cameras[b].extra["black_level"] for b in (8, 12, 16)] == [2.0, 32.0, 512.0]
    camera = SimCamera(small_sim_rig)
    with pytest.raises(DeviceError, match="not one of"):
        camera.set("PixelFormat", "BayerRG12")
    camera.start_acquisition()
    with pytest.raises(DeviceError, match="during acquisition"):
        camera.set("PixelFormat", "BayerGB8")


@pytest.mark.parametrize("exposure_s", [0.01, 0.0123])
def test_frame_ids_and_device_timestamps(small_sim_rig: SimulatedRig, exposure_s: float) -> None:
    camera = SimCamera(small_sim_rig)
    readout = small_sim_rig.rig.sim.readout_s
    frames = camera.grab(exposure_s, 3) + camera.grab(exposure_s, 2)
    assert [f.frame_id for f in frames] == [1, 2, 3, 4, 5]
    stamps = np.array([f.device_timestamp_ns for f in frames])
    assert stamps[0] == 0
    np.testing.assert_array_equal(np.diff(stamps), round((exposure_s + readout) * 1e9))
    hosts = [f.host_timestamp_s for f in frames]
    assert hosts == sorted(hosts)


def test_device_clock_is_exact_for_thesis_exposure(small_sim_rig: SimulatedRig) -> None:
    camera = SimCamera(small_sim_rig)
    camera.set_illumination("dark")
    frames = camera.grab(3.916, 2)
    assert frames[1].device_timestamp_ns - frames[0].device_timestamp_ns == 3_966_000_000


def test_software_trigger_needs_trigger_mode_on(small_sim_rig: SimulatedRig) -> None:
    camera = SimCamera(small_sim_rig)
    camera.set("TriggerMode", "On")
    with pytest.raises(DeviceError, match="before AcquisitionStart"):
        camera.execute("TriggerSoftware")
    camera.set("TriggerMode", "Off")
    camera.execute("AcquisitionStart")
    assert camera.acquiring
    with pytest.raises(DeviceError, match="TriggerMode=On"):
        camera.execute("TriggerSoftware")
    camera.set("TriggerMode", "On")
    with pytest.raises(DeviceError, match="no trigger was sent"):
        camera.fetch()
    camera.execute("TriggerSoftware")
    assert camera.fetch().frame_id == 1
    camera.close()
    with pytest.raises(DeviceError, match="closed"):
        camera.get("ExposureTime")


def test_twelve_bit_format_from_fourteen_bit_adc(sim_rig_path) -> None:
    data = yaml.safe_load(sim_rig_path.read_text(encoding="utf-8"))
    data["sim"]["sensor"]["adc_bits"] = 14
    rig = SimulatedRig(rig_from_dict(data, source="adc14"), shape=(128, 160))
    images = {}
    for bits in (12, 16):
        camera = SimCamera(rig, seed=4)
        camera.set("PixelFormat", f"BayerGB{bits}")
        images[bits] = camera.grab(0.004, 1)[0].image
    np.testing.assert_array_equal(images[12], images[16] >> 4)
