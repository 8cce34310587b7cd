"""Disk keypoints (thesis §3.2.1): detection, Levenberg–Marquardt refinement, pairing and
outlier rejection, against disk patterns rendered by the simulator with known centres."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from calibration.disks import (
    DiskCandidates,
    DiskFit,
    background_mask,
    channel_disk_keypoints,
    detect_disks,
    disk_keypoints,
    fit_disks,
    pair_mutual_nearest,
)
from calibration.disks._outliers import displacement_outliers
from labkit.cfa import mosaic
from labkit.errors import DataError
from labkit.io.exr import RawImage
from labkit.sim import SimulatedRig
from labkit.sim.lens import Lens
from labkit.sim.render import render_irradiance
from labkit.sim.scenes import (
    Scene,
    colorchecker_chart,
    disk_pattern,
    flat_field,
    textured_scene,
)
from labkit.sim.sensor import Sensor, SensorModel

SHAPE = (192, 256)
RADIUS_PX = 10.0
PITCH_PX = 40.0
OFFSET_PX = (0.3, -0.27)
CFA = "GBRG"
#: 5 × 4 disks fit a 256 × 192 view at pitch 40 with the default half-pitch margin
N_DISKS = 20


def render(
    rig: SimulatedRig,
    *,
    offset: tuple[float, float] = OFFSET_PX,
    light: str = "600",
    vignetting: float = 0.0,
    blur: float = 0.0,
    shape: tuple[int, int] = SHAPE,
    radius: float = RADIUS_PX,
    pitch: float = PITCH_PX,
) -> tuple[np.ndarray, Scene]:
    """Noise-free irradiance (rows, cols, 3) of the disk pattern, peak 1, and its scene."""
    scene = disk_pattern(shape, radius_px=radius, pitch_px=pitch, offset_px=offset)
    lens = Lens(shape, max_shift_px=0.0, vignetting=vignetting, blur_sigma_px=blur)
    rgb = render_irradiance(
        scene, lens, rig.response, {light: rig.light(light)}, rig.wavelengths, workers=1
    )[light]
    return rgb / rgb.max(), scene


def true_centres(scene: Scene) -> np.ndarray:
    return scene.disks.centres()


def centre_errors(found: np.ndarray, scene: Scene) -> np.ndarray:
    """(n, 2) found − true centre of the nearest true disk, px."""
    truth = true_centres(scene)
    _, nearest = cKDTree(truth).query(found)
    return found - truth[nearest]


def rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.atleast_2d(errors) ** 2, axis=1))))


def sensor_image(
    irradiance: np.ndarray, rng: np.random.Generator, *, paper: float = 0.7, replicates: int = 5
) -> np.ndarray:
    """Mean of `replicates` simulated 12-bit frames as a fraction of saturation.

    `irradiance` (rows, cols) peaks at 1; the brightest paper pixel collects `paper` of
    the full well (Poisson shot noise, 8 e⁻ read noise, PRNU, dark current, quantisation).
    """
    rows, cols = irradiance.shape
    sensor = Sensor(SensorModel(width=cols, height=rows, cfa=CFA), seed=7)
    model = sensor.model
    exposure = 1.0
    rate = irradiance * np.float32(paper * model.full_well_e / exposure)
    frames = [sensor.expose(rate, exposure, rng=rng)[0] for _ in range(replicates)]
    counts = np.mean(frames, axis=0)
    gain = model.gain_factor(0.0)
    dark = sensor.mean_electrons(None, exposure) * gain
    return ((counts - model.black_level_dn - dark) / (model.full_well_e * gain)).astype(np.float32)


def raw_image(raw: np.ndarray, wavelength: float | None, name: str) -> RawImage:
    return RawImage(
        np.asarray(raw, dtype=np.float32),
        CFA,
        1.0,
        name,
        wavelength,
        labkit={"source_file": f"/data/hdr/disks/{name}.exr"},
    )


@pytest.fixture(scope="module")
def rig(small_sim_rig: SimulatedRig) -> SimulatedRig:
    return small_sim_rig


@pytest.fixture(scope="module")
def sharp(rig: SimulatedRig) -> tuple[np.ndarray, Scene]:
    """Noise-free 600 nm mosaic at a sub-pixel lattice offset."""
    rgb, scene = render(rig)
    return mosaic(rgb, CFA), scene


# -- detection and refinement -----------------------------------------------------------


def test_noise_free_centres_are_exact(sharp: tuple[np.ndarray, Scene]) -> None:
    raw, scene = sharp
    candidates = detect_disks(raw, cfa=CFA, name="sharp")
    assert isinstance(candidates, DiskCandidates)
    assert len(candidates) == N_DISKS
    # centroids of the thresholded regions: good to a tenth of a pixel
    assert rms(centre_errors(candidates.centres, scene)) < 0.1
    assert np.allclose(candidates.axes, RADIUS_PX, atol=0.5)
    assert candidates.labels.max() == N_DISKS and candidates.labels.shape == raw.shape

    joint = fit_disks(raw, cfa=CFA, candidates=candidates, workers=1)
    assert isinstance(joint, DiskFit) and joint.channel_centres is None
    assert len(joint) == N_DISKS and joint.rejected == {}
    # measured: 0.002 px
    assert rms(centre_errors(joint.centres, scene)) <= 0.02
    assert np.allclose(joint.axes, RADIUS_PX, atol=0.02)
    assert np.all(joint.residual < 0.01)
    assert np.all(joint.edge_width_px < 0.2)  # sharp edge: only the pixel footprint

    per_channel = fit_disks(raw, cfa=CFA, candidates=candidates, per_channel=True, workers=1)
    assert per_channel.channel_centres.shape == (N_DISKS, 3, 2)
    np.testing.assert_array_equal(per_channel.centres, per_channel.channel_centres[:, 1])
    for channel in range(3):
        # measured: R 0.0097, G 0.0011, B 0.0002 px (R and B use a quarter of the pixels)
        errors = centre_errors(per_channel.channel_centres[:, channel], scene)
        assert rms(errors) <= 0.02, channel


def test_noisy_centres_at_thesis_exposure(rig: SimulatedRig, rng: np.random.Generator) -> None:
    rgb, scene = render(rig)
    raw = sensor_image(mosaic(rgb, CFA), rng)
    fit = fit_disks(raw, cfa=CFA, workers=1)
    assert len(fit) == N_DISKS
    # measured: 0.004 px with the brightest paper at 70 % of the full well, mean of 5 frames
    assert rms(centre_errors(fit.centres, scene)) <= 0.05


def test_vignetting_and_blur(rig: SimulatedRig, rng: np.random.Generator) -> None:
    rgb, scene = render(rig, vignetting=0.3, blur=0.7)
    noise_free = mosaic(rgb, CFA)
    fit = fit_disks(noise_free, cfa=CFA, workers=1)
    assert len(fit) == N_DISKS
    # measured: 0.0055 px noise-free; the local illumination gradient absorbs vignetting
    assert rms(centre_errors(fit.centres, scene)) <= 0.05
    assert np.all((fit.edge_width_px > 1.0) & (fit.edge_width_px < 4.0))  # blurred edge
    noisy = fit_disks(sensor_image(noise_free, rng), cfa=CFA, workers=1)
    assert len(noisy) == N_DISKS
    # measured: 0.008 px with noise
    assert rms(centre_errors(noisy.centres, scene)) <= 0.05


def test_channel_without_signal_is_ignored_by_detection(
    rig: SimulatedRig, rng: np.random.Generator
) -> None:
    rgb, scene = render(rig, light="500")
    rgb[..., 0] *= 1e-3  # a filtered image whose Red channel holds almost nothing
    raw = mosaic(rgb, CFA) + rng.normal(0.0, 3e-3, SHAPE).astype(np.float32)
    candidates = detect_disks(raw, cfa=CFA, name="500 nm")
    assert len(candidates) == N_DISKS
    errors = centre_errors(candidates.centres, scene)
    assert np.all(np.abs(errors) < 0.5)
    fit = fit_disks(raw, cfa=CFA, candidates=candidates, workers=1)
    assert len(fit) == N_DISKS
    # measured: 0.0012 px (Red adds noise, not bias)
    assert rms(centre_errors(fit.centres, scene)) <= 0.05


def supersampled_ellipses(
    shape: tuple[int, int],
    centres: list[tuple[float, float]],
    axes: tuple[float, float],
    angle: float,
    *,
    samples: int = 8,
) -> np.ndarray:
    """Area fraction (rows, cols) of each pixel covered by equal ellipses (8×8 samples)."""
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    c, s = np.cos(angle), np.sin(angle)
    cover = np.zeros(shape)
    for oy in offsets:
        for ox in offsets:
            inside = np.zeros(shape, dtype=bool)
            for cx, cy in centres:
                dx, dy = xx + ox - cx, yy + oy - cy
                u, v = c * dx + s * dy, -s * dx + c * dy
                inside |= (u / axes[0]) ** 2 + (v / axes[1]) ** 2 <= 1.0
            cover += inside
    return cover / samples**2


@pytest.mark.parametrize("angle", [0.5, -1.2])
def test_ellipse_axes_and_orientation(angle: float) -> None:
    """A tilted pattern images disks as ellipses; the angle is from +x towards +y (rows)."""
    centres = [(40.3 + 60 * i, 40.7 + 60 * j) for j in range(2) for i in range(3)]
    cover = supersampled_ellipses((160, 200), centres, (13.0, 9.0), angle)
    paper, ink = np.array([0.9, 0.6, 0.3]), np.array([0.05, 0.04, 0.02])
    raw = mosaic(paper + (ink - paper) * cover[..., None], "RGGB")
    candidates = detect_disks(raw, cfa="RGGB")
    assert len(candidates) == 6
    np.testing.assert_allclose(candidates.axes, [[13.0, 9.0]] * 6, atol=0.15)
    np.testing.assert_allclose(candidates.angle_rad, angle, atol=0.02)
    fit = fit_disks(raw, cfa="RGGB", candidates=candidates, workers=1)
    # measured: centres 0.006 px, axes 0.01 px, angle 0.001 rad
    order = np.lexsort((fit.centres[:, 0], fit.centres[:, 1]))
    np.testing.assert_allclose(fit.centres[order], centres, atol=0.02)
    np.testing.assert_allclose(fit.axes, [[13.0, 9.0]] * 6, atol=0.03)
    np.testing.assert_allclose(fit.angle_rad, angle, atol=0.005)


def test_process_pool_gives_the_same_fits(sharp: tuple[np.ndarray, Scene]) -> None:
    raw, _ = sharp
    candidates = detect_disks(raw, cfa=CFA)
    serial = fit_disks(raw, cfa=CFA, candidates=candidates, workers=1)
    pooled = fit_disks(raw, cfa=CFA, candidates=candidates, workers=2)
    np.testing.assert_array_equal(pooled.candidate, serial.candidate)
    np.testing.assert_allclose(pooled.centres, serial.centres, atol=1e-9)


def test_disks_at_the_border(rig: SimulatedRig) -> None:
    # a negative margin puts the lattice's outer disks across the image border; the
    # offset moves the left column to 2.5 px from the border: whole, but too close to fit
    scene = disk_pattern(
        SHAPE, radius_px=RADIUS_PX, pitch_px=PITCH_PX, margin_px=-4.0, offset_px=(5.0, 0.3)
    )
    lens = Lens(SHAPE, max_shift_px=0.0)
    rgb = render_irradiance(scene, lens, rig.response, {"600": rig.light("600")}, rig.wavelengths)
    raw = mosaic(rgb["600"] / rgb["600"].max(), CFA)
    truth = true_centres(scene)
    rows, cols = SHAPE
    whole = (
        (truth[:, 0] - RADIUS_PX > 0.5)
        & (truth[:, 1] - RADIUS_PX > 0.5)
        & (truth[:, 0] + RADIUS_PX < cols - 1.5)
        & (truth[:, 1] + RADIUS_PX < rows - 1.5)
    )
    near_left = whole & (truth[:, 0] - RADIUS_PX < 5.0)
    assert whole.sum() == 30 and near_left.sum() == 5  # 5 × 7 disks, the right column cut
    candidates = detect_disks(raw, cfa=CFA)
    assert len(candidates) == whole.sum()  # disks cut by the border are not candidates
    fit = fit_disks(raw, cfa=CFA, candidates=candidates, workers=1)
    assert fit.rejected == {"touches border": 5}  # their neighbourhood leaves the image
    assert len(fit) == 25
    found = centre_errors(fit.centres, scene)
    assert rms(found) <= 0.02
    assert cKDTree(fit.centres).query(truth[near_left])[0].min() > PITCH_PX / 2


# -- keypoints ----------------------------------------------------------------------------

SHIFT = (0.37, -0.21)


@pytest.fixture(scope="module")
def two_bands(rig: SimulatedRig) -> tuple[RawImage, RawImage, Scene]:
    """The pattern at 600 nm and, shifted by SHIFT, at 500 nm."""
    rgb600, scene = render(rig, light="600")
    shifted = (OFFSET_PX[0] + SHIFT[0], OFFSET_PX[1] + SHIFT[1])
    rgb500, _ = render(rig, light="500", offset=shifted)
    return (
        raw_image(mosaic(rgb600, CFA), 600.0, "600"),
        raw_image(mosaic(rgb500, CFA), 500.0, "500"),
        scene,
    )


def test_planted_shift_between_bands_is_recovered(
    two_bands: tuple[RawImage, RawImage, Scene],
) -> None:
    ref, band, scene = two_bands
    keypoints = disk_keypoints([band, ref], reference_nm=600.0, workers=1)
    assert keypoints.source == "disks" and keypoints.reference == 600.0
    assert keypoints.bands == [500.0, 600.0]
    assert keypoints.image_shape == SHAPE
    own = keypoints.for_band(600.0)
    assert len(own) == N_DISKS
    assert np.all(own.dx == 0) and np.all(own.dy == 0)
    shifted = keypoints.for_band(500.0)
    assert len(shifted) == N_DISKS  # every disk pairs
    errors = shifted.displacements() - np.array(SHIFT)
    # measured: 0.0003 px
    assert rms(errors) <= 0.02
    # positions are the reference centres
    assert rms(centre_errors(shifted.positions(), scene)) <= 0.02
    info = keypoints.meta["bands"]["500.0"]
    assert info["file"] == "/data/hdr/disks/500.exr"
    assert (info["disks"], info["paired"], info["outliers"]) == (N_DISKS, N_DISKS, 0)
    assert keypoints.meta["bands"]["600.0"]["reference"] is True
    assert keypoints.quality is not None and np.all(keypoints.quality < 0.02)


def test_wavelengths_can_come_from_a_mapping(
    two_bands: tuple[RawImage, RawImage, Scene],
) -> None:
    ref, band, _ = two_bands
    unnamed = [
        RawImage(image.raw, image.cfa, 1.0, name, None)
        for image, name in ((ref, "slot6"), (band, "slot4"))
    ]
    keypoints = disk_keypoints(  # also runs the fits in a pool of 2 processes
        unnamed, reference_nm=600.0, wavelengths={"slot6": 600.0, "slot4": 500.0}, workers=2
    )
    assert keypoints.bands == [500.0, 600.0]
    assert rms(keypoints.for_band(500.0).displacements() - np.array(SHIFT)) <= 0.02


def test_lens_dispersion_is_measured_without_false_outliers(rig: SimulatedRig) -> None:
    """A steep radial dispersion field at one wavelength: keypoints match the lens' truth.

    Monochromatic light makes the truth exact: the disk imaged at c at 600 nm is imaged at
    c + d(c, 450 nm), and d is linear in position, so the centroid moves by d(c). Keypoints
    at the pattern's edge, whose neighbours all lie on one side, must not be outliers.
    """
    lens = Lens(SHAPE, max_shift_px=5.0, reference_nm=600.0)
    scene = disk_pattern(SHAPE, radius_px=RADIUS_PX, pitch_px=PITCH_PX, offset_px=OFFSET_PX)
    lights = {}
    for wavelength in (450.0, 600.0):
        light = np.zeros(rig.wavelengths.size)
        light[np.argmin(np.abs(rig.wavelengths - wavelength))] = 1.0
        lights[f"{wavelength:g}"] = light
    rgb = render_irradiance(scene, lens, rig.response, lights, rig.wavelengths)
    images = [
        raw_image(mosaic(rgb[name] / rgb[name].max(), CFA), float(name), name)
        for name in ("450", "600")
    ]
    keypoints = disk_keypoints(images, reference_nm=600.0, workers=1)
    band = keypoints.for_band(450.0)
    assert len(band) == N_DISKS and keypoints.meta["bands"]["450.0"]["outliers"] == 0
    truth = np.column_stack(lens.displacement(band.x, band.y, 450.0))
    assert np.abs(truth).max() > 1.5  # about 0.8 px of change from one disk to the next
    # measured: 0.0014 px
    assert rms(band.displacements() - truth) <= 0.02


def test_outliers_of_a_steep_field_are_found_at_the_edges_too() -> None:
    # a 12 × 9 lattice in a radial field changing 0.38 px from one keypoint to the next:
    # plain neighbour medians would flag 12 good keypoints at the edges; the field's robust
    # quadratic trend is removed before comparing neighbours
    yy, xx = np.mgrid[0:9, 0:12] * 32.0
    xy = np.column_stack([xx.ravel(), yy.ravel()]) + 20.0
    d = 0.012 * (xy - xy.mean(axis=0))
    d += np.random.default_rng(0).normal(0.0, 0.01, d.shape)
    planted = [0, 40, 77]  # a corner, an inner and an edge keypoint
    d[planted] += [0.8, -0.5]
    assert np.flatnonzero(displacement_outliers(xy, d)).tolist() == planted


def test_displaced_disks_are_rejected_as_outliers(
    rig: SimulatedRig, two_bands: tuple[RawImage, RawImage, Scene]
) -> None:
    ref, band, scene = two_bands
    # three disks of the 500 nm image are moved by a further 1.2 px: copy their
    # neighbourhoods from a render of the whole lattice moved that way
    moved_offset = (OFFSET_PX[0] + SHIFT[0] + 1.2, OFFSET_PX[1] + SHIFT[1])
    moved, _ = render(rig, light="500", offset=moved_offset)
    raw = band.raw.copy()
    moved_raw = mosaic(moved, CFA)
    picked = true_centres(scene)[[0, 7, 13]]
    for x, y in picked:
        r0, c0 = int(y - RADIUS_PX - 4), int(x - RADIUS_PX - 4)
        r1, c1 = int(y + RADIUS_PX + 6), int(x + RADIUS_PX + 6)
        raw[r0:r1, c0:c1] = moved_raw[r0:r1, c0:c1]
    corrupted = raw_image(raw, 500.0, "500")
    keypoints = disk_keypoints([ref, corrupted], reference_nm=600.0, workers=1)
    info = keypoints.meta["bands"]["500.0"]
    assert (info["disks"], info["paired"], info["outliers"]) == (N_DISKS, N_DISKS, 3)
    kept = keypoints.for_band(500.0)
    assert len(kept) == N_DISKS - 3
    assert cKDTree(kept.positions()).query(picked)[0].min() > PITCH_PX / 2
    assert rms(kept.displacements() - np.array(SHIFT)) <= 0.02


def test_colour_channel_shifts_are_recovered(rig: SimulatedRig) -> None:
    planted = {"R": (0.25, -0.15), "B": (-0.2, 0.3)}
    rgb, scene = render(rig, light="unfiltered")
    for channel, (sx, sy) in ((0, planted["R"]), (2, planted["B"])):
        shifted, _ = render(rig, light="unfiltered", offset=(OFFSET_PX[0] + sx, OFFSET_PX[1] + sy))
        rgb[..., channel] = shifted[..., channel]
    image = raw_image(mosaic(rgb, CFA), None, "unfiltered")
    keypoints = channel_disk_keypoints(image, workers=1)
    assert not keypoints.spectral and keypoints.reference == "G"
    assert keypoints.bands == ["B", "R"]
    for label, shift in planted.items():
        part = keypoints.for_band(label)
        assert len(part) == N_DISKS
        # measured: R 0.009, B 0.001 px
        assert rms(part.displacements() - np.array(shift)) <= 0.02, label
        assert rms(centre_errors(part.positions(), scene)) <= 0.02
    assert keypoints.meta["channels"]["R"]["outliers"] == 0


def test_mutual_nearest_pairs() -> None:
    ref = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    band = np.array([[10.4, 0.2], [0.3, 0.1], [19.0, 0.0], [21.5, 0.0], [36.0, 0.0]])
    ri, bi = pair_mutual_nearest(ref, band, max_distance_px=2.0)
    # 20 ↔ 19 is mutual; 21.5's nearest is 20 but 20 prefers 19; 36 is too far from 30
    assert ri.tolist() == [0, 1, 2]
    assert bi.tolist() == [1, 0, 2]
    empty = pair_mutual_nearest(ref, np.zeros((0, 2)), max_distance_px=2.0)
    assert empty[0].size == 0 and empty[1].size == 0
    with pytest.raises(DataError, match="band_xy"):
        pair_mutual_nearest(ref, np.zeros((3, 3)), max_distance_px=1.0)


# -- bad input --------------------------------------------------------------------------


def flat_raw(rig: SimulatedRig, rng: np.random.Generator) -> np.ndarray:
    scene = flat_field(SHAPE, reflectance=0.8)
    lens = Lens(SHAPE, max_shift_px=0.0, vignetting=0.2)
    rgb = render_irradiance(scene, lens, rig.response, {"500": rig.light("500")}, rig.wavelengths)
    raw = mosaic(rgb["500"] / rgb["500"].max(), CFA)
    return raw + rng.normal(0.0, 2e-3, SHAPE).astype(np.float32)


def test_flat_field_has_no_disks(rig: SimulatedRig, rng: np.random.Generator) -> None:
    raw = flat_raw(rig, rng)
    with pytest.raises(DataError, match=r"no calibration disks found in flat\.exr"):
        detect_disks(raw, cfa=CFA, name="flat.exr")
    with pytest.raises(DataError, match=r"flat\.exr"):
        fit_disks(raw, cfa=CFA, name="flat.exr", workers=1)
    # callers fall back to the whole image when background_mask says it is no disk scene
    with pytest.raises(DataError, match="no calibration disks found"):
        background_mask(raw, cfa=CFA)


@pytest.mark.parametrize("make_scene", [colorchecker_chart, textured_scene])
def test_other_scenes_are_not_disk_patterns(rig: SimulatedRig, make_scene) -> None:
    scene = make_scene(SHAPE)
    lens = Lens(SHAPE, max_shift_px=0.0, vignetting=0.15)
    rgb = render_irradiance(scene, lens, rig.response, {"600": rig.light("600")}, rig.wavelengths)
    raw = mosaic(rgb["600"] / rgb["600"].max(), CFA)
    # the chart is one dark rectangle; the texture's dark area is mostly not round
    with pytest.raises(DataError, match=r"no calibration disks found in chart\.exr"):
        detect_disks(raw, cfa=CFA, name="chart.exr")
    with pytest.raises(DataError, match="is this an image of the disk pattern"):
        background_mask(raw, cfa=CFA)


def test_band_without_disks_is_named(
    rig: SimulatedRig, rng: np.random.Generator, two_bands: tuple[RawImage, RawImage, Scene]
) -> None:
    ref, _, _ = two_bands
    flat = raw_image(flat_raw(rig, rng), 500.0, "500")
    with pytest.raises(DataError, match=r"band 500 nm \(/data/hdr/disks/500\.exr\)"):
        disk_keypoints([ref, flat], reference_nm=600.0, workers=1)


def test_band_that_does_not_pair_is_named(two_bands: tuple[RawImage, RawImage, Scene]) -> None:
    ref, band, _ = two_bands
    with pytest.raises(DataError, match=r"band 500 nm \(/data/hdr/disks/500\.exr\).*pair"):
        disk_keypoints([ref, band], reference_nm=600.0, max_shift_px=0.1, workers=1)


def test_reference_band_must_be_present(two_bands: tuple[RawImage, RawImage, Scene]) -> None:
    ref, band, _ = two_bands
    with pytest.raises(DataError, match=r"reference band 550 nm.*500, 600 nm"):
        disk_keypoints([ref, band], reference_nm=550.0, workers=1)


def test_images_must_agree(two_bands: tuple[RawImage, RawImage, Scene]) -> None:
    ref, band, _ = two_bands
    cropped = raw_image(band.raw[:, :-2], 500.0, "500")
    with pytest.raises(DataError, match=r"500\.exr is 254×192"):
        disk_keypoints([ref, cropped], reference_nm=600.0, workers=1)
    other_cfa = RawImage(band.raw, "RGGB", 1.0, "500", 500.0)
    with pytest.raises(DataError, match="same camera mode"):
        disk_keypoints([ref, other_cfa], reference_nm=600.0, workers=1)
    twice = raw_image(band.raw, 500.2, "500b")
    with pytest.raises(DataError, match="two images are of band"):
        disk_keypoints([ref, band, twice], reference_nm=600.0, workers=1)


def test_unfiltered_image_needs_a_wavelength(
    two_bands: tuple[RawImage, RawImage, Scene],
) -> None:
    ref, band, _ = two_bands
    unfiltered = RawImage(band.raw, CFA, 1.0, "unfiltered", None)
    with pytest.raises(DataError, match="'unfiltered' has no wavelength_nm"):
        disk_keypoints([ref, unfiltered], reference_nm=600.0, workers=1)


def test_nan_pixels_are_refused(sharp: tuple[np.ndarray, Scene]) -> None:
    raw = sharp[0].copy()
    raw[5, 7] = np.nan
    with pytest.raises(DataError, match=r"nan\.exr: 1 raw pixels are NaN"):
        detect_disks(raw, cfa=CFA, name="nan.exr")


# -- background ---------------------------------------------------------------------------


def test_background_mask_avoids_every_disk(rig: SimulatedRig) -> None:
    rgb, scene = render(rig, vignetting=0.3)
    raw = mosaic(rgb, CFA)
    ink = scene.coverage_image(SHAPE)[..., 1] > 0  # any pixel a disk touches
    mask = background_mask(raw, cfa=CFA)
    assert mask.shape == SHAPE and mask.dtype == bool
    assert not np.any(mask & ink)
    # measured: 86 % of the paper is kept at the default 3 px margin
    assert mask.sum() > 0.8 * (~ink).sum()
    with_candidates = background_mask(raw, cfa=CFA, candidates=detect_disks(raw, cfa=CFA))
    np.testing.assert_array_equal(with_candidates, mask)
    wider = background_mask(raw, cfa=CFA, margin_px=6.0)
    assert wider.sum() < mask.sum() and not np.any(wider & ~mask)


# -- full size ------------------------------------------------------------------------------


@pytest.mark.slow
def test_full_size_image_within_time_budget(rig: SimulatedRig) -> None:
    """One 2448 × 2048 image, ~1150 disks of radius 14 px: detect + fit ≤ 5 s on 2 workers."""
    shape = (2048, 2448)
    rgb, scene = render(rig, shape=shape, radius=14.0, pitch=64.0, vignetting=0.15)
    raw = mosaic(rgb, CFA)
    start = time.perf_counter()
    fit = fit_disks(raw, cfa=CFA, workers=2)
    elapsed = time.perf_counter() - start
    assert len(fit) >= 0.99 * len(true_centres(scene))
    assert rms(centre_errors(fit.centres, scene)) <= 0.01
    assert elapsed <= 5.0, f"detect + fit took {elapsed:.1f} s"
