"""Registration keypoints (thesis §3.2.3, App. B.2): planted sub-pixel shifts on simulated
Bayer images, a planted radial dispersion field, rejection of flat patches, colour-channel
registration and input checks.

Images are rendered with the simulator's exact pixel-area coverage under single-wavelength
light (one dispersion level per render, so the planted geometry is exact), mosaicked GBRG
and given 0.1 % Gaussian noise. The lens has no blur unless stated (the hardest case for
Bayer aliasing).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from skimage.registration import phase_cross_correlation

from calibration.multispectral import green_bilinear
from calibration.registration import (
    MAX_ERROR,
    MIN_TEXTURE,
    PatchShifts,
    channel_registration_keypoints,
    patch_shifts,
    registration_keypoints,
)
from calibration.registration._grid import patch_grid
from labkit.cfa import mosaic
from labkit.errors import DataError
from labkit.io.exr import RawImage
from labkit.sim import Lens, SimulatedRig, disk_pattern, render_irradiance, textured_scene
from labkit.sim.scenes import Scene

SHAPE = (256, 320)
LAYOUT = "GBRG"
#: Planted displacement reference → band, (dx, dy) px.
PLANTED = (0.37, -0.21)
#: 7 × 9 patches of 64 px every 32 px in a 256 × 320 image.
N_PATCHES = 63


def shifted(scene: Scene, offset: tuple[float, float]) -> Scene:
    """The scene moved by `offset` (x, y) px: a feature at p appears at p + offset."""
    grid = scene.grid
    moved = dataclasses.replace(
        grid, origin=(grid.origin[0] + offset[0], grid.origin[1] + offset[1])
    )
    disks = scene.disks
    if disks is not None:
        first = disks.first_centre
        disks = dataclasses.replace(
            disks, first_centre=(first[0] + offset[0], first[1] + offset[1])
        )
    return dataclasses.replace(scene, grid=moved, disks=disks)


def render(rig: SimulatedRig, scene: Scene, lens: Lens, light_nm: float | None) -> np.ndarray:
    """Irradiance (rows, cols, 3) under one wavelength (or flat white light), max G = 1."""
    light = np.zeros(rig.wavelengths.size)
    if light_nm is None:
        light[:] = 1.0
    else:
        light[np.argmin(np.abs(rig.wavelengths - light_nm))] = 1.0
    rgb = render_irradiance(scene, lens, rig.response, {"b": light}, rig.wavelengths, workers=2)
    return rgb["b"] / rgb["b"][..., 1].max()


def raw_image(
    rgb: np.ndarray, wavelength: float | None, name: str, rng: np.random.Generator
) -> RawImage:
    raw = mosaic(rgb, LAYOUT) + rng.normal(0.0, 1e-3, rgb.shape[:2])
    illumination = "unfiltered" if wavelength is None else f"{wavelength:g}"
    return RawImage(
        raw.astype(np.float32),
        LAYOUT,
        1.0,
        illumination,
        wavelength,
        labkit={"source_file": name},
    )


def make_scene(kind: str) -> Scene:
    return textured_scene(SHAPE, seed=7) if kind == "texture" else disk_pattern(SHAPE)


@pytest.fixture(scope="module")
def planted_pairs(small_sim_rig: SimulatedRig) -> dict[str, tuple[RawImage, RawImage]]:
    """600 nm reference and 550 nm band of each scene, the band moved by PLANTED."""
    rng = np.random.default_rng(11)
    lens = Lens(SHAPE, max_shift_px=0.0)
    pairs = {}
    for kind in ("texture", "disks"):
        scene = make_scene(kind)
        reference = render(small_sim_rig, scene, lens, 600.0)
        band = render(small_sim_rig, shifted(scene, PLANTED), lens, 550.0)
        pairs[kind] = (
            raw_image(reference, 600.0, f"{kind}/600.exr", rng),
            raw_image(band, 550.0, f"{kind}/550.exr", rng),
        )
    return pairs


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


# -- 1. planted uniform shift ---------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "min_accepted"),
    # measured RMS error: texture 0.016 px (47 patches), disks 0.010 px (12 patches centred
    # on disks; patches seeing only disk edges in their window's tails are rejected)
    [("texture", 40), ("disks", 12)],
)
def test_planted_uniform_shift_is_recovered_with_its_sign(
    planted_pairs: dict, kind: str, min_accepted: int
) -> None:
    reference, band = planted_pairs[kind]
    keypoints = registration_keypoints([band, reference], reference_nm=600.0)
    assert keypoints.source == "registration"
    assert keypoints.reference == 600.0
    assert keypoints.image_shape == SHAPE
    assert keypoints.bands == [550.0, 600.0]
    moved = keypoints.for_band(550.0)
    assert len(moved) >= min_accepted
    error = np.hypot(moved.dx - PLANTED[0], moved.dy - PLANTED[1])
    assert rms(error) < 0.03, f"{kind}: RMS error {rms(error):.4f} px"
    # sign: the feature moves right (+x) and up (−y) from the reference to the band
    assert np.all(moved.dx > 0.3) and np.all(moved.dy < -0.15)
    assert np.all(moved.quality <= MAX_ERROR)
    # the reference band's own keypoints: every patch centre, zero displacement
    own = keypoints.for_band(600.0)
    assert len(own) == N_PATCHES
    assert np.all(own.dx == 0) and np.all(own.dy == 0)
    _, c0 = patch_grid(SHAPE, 64, 32)
    np.testing.assert_array_equal(np.sort(own.x), np.sort(c0 + 31.5))
    meta = keypoints.meta["bands"]
    assert meta["550.0"]["file"] == f"{kind}/550.exr"
    assert meta["550.0"]["patches"] == N_PATCHES
    assert meta["550.0"]["accepted"] == len(moved)
    assert meta["600.0"]["file"] == f"{kind}/600.exr"
    assert keypoints.meta["rejected"] == N_PATCHES - len(moved)


def test_plain_settings_reproduce_scikit_image(planted_pairs: dict) -> None:
    """Without window, weight or refinement the batched estimator is scikit-image's
    phase_cross_correlation with the opposite sign (what registers moving onto reference)."""
    reference, band = planted_pairs["texture"]
    ref = green_bilinear(reference.raw, LAYOUT)
    mov = green_bilinear(band.raw, LAYOUT)
    plain = patch_shifts(ref, mov, window=False, lowpass=None, normalization="phase", iterations=0)
    r0, c0 = patch_grid(SHAPE, 64, 32)
    for i in range(0, N_PATCHES, 7):
        a = ref[r0[i] : r0[i] + 64, c0[i] : c0[i] + 64]
        b = mov[r0[i] : r0[i] + 64, c0[i] : c0[i] + 64]
        shift, _, _ = phase_cross_correlation(a - a.mean(), b - b.mean(), upsample_factor=100)
        assert (plain.dy[i], plain.dx[i]) == pytest.approx((-shift[0], -shift[1]), abs=1e-6)
    # … and, on Bayer Green, it loses most of the planted shift (measured: x ≈ −0.02 px)
    assert abs(np.mean(plain.dx) - PLANTED[0]) > 0.2


# -- 2. planted smooth non-uniform field ----------------------------------------------


@pytest.mark.parametrize("kind", ["texture", "disks"])
def test_radial_dispersion_field_matches_the_lens(small_sim_rig: SimulatedRig, kind: str) -> None:
    """A lens with 2 px of dispersion at the corner (principal point off-centre): per-patch
    displacements against the truth at the patch centres (measured RMS: texture
    0.026 px, disks 0.014 px)."""
    rng = np.random.default_rng(5)
    lens = Lens(SHAPE, max_shift_px=2.0, reference_nm=600.0, centre_px=(150.0, 120.0))
    scene = make_scene(kind)
    images = [
        raw_image(render(small_sim_rig, scene, lens, nm), nm, f"{kind}/{nm:g}.exr", rng)
        for nm in (450.0, 600.0)
    ]
    keypoints = registration_keypoints(images, reference_nm=600.0)
    band = keypoints.for_band(450.0)
    assert len(band) >= 12
    true_dx, true_dy = lens.displacement(band.x, band.y, 450.0)
    assert np.ptp(true_dx) > 0.7 and np.ptp(true_dy) > 0.7  # really non-uniform
    error = np.hypot(band.dx - true_dx, band.dy - true_dy)
    assert rms(error) < 0.05, f"{kind}: RMS error {rms(error):.4f} px"


# -- 3. rejection -----------------------------------------------------------------------


def test_flat_patches_are_rejected_and_a_flat_band_is_an_error(
    small_sim_rig: SimulatedRig, planted_pairs: dict
) -> None:
    """The textured scene with its left 128 px painted plain white paper."""
    scene = make_scene("texture")
    labels = scene.grid.labels.copy()
    labels[:, :66] = 0  # 2 px cells from x = −2.5: paper up to x = 129.5
    scene = dataclasses.replace(scene, grid=dataclasses.replace(scene.grid, labels=labels))
    lens = Lens(SHAPE, max_shift_px=0.0)
    rng = np.random.default_rng(3)
    ref, mov = (
        green_bilinear(raw_image(render(small_sim_rig, s, lens, nm), nm, "", rng).raw, LAYOUT)
        for s, nm in ((scene, 600.0), (shifted(scene, PLANTED), 550.0))
    )
    shifts = patch_shifts(ref, mov)
    assert isinstance(shifts, PatchShifts) and len(shifts) == N_PATCHES
    inside = shifts.x + 32 <= 128
    assert inside.sum() == 21
    assert not shifts.accepted[inside].any()
    assert np.all(shifts.texture[inside] < MIN_TEXTURE)
    assert shifts.n_rejected >= 21
    good = shifts.accepted
    assert good.sum() >= 20  # measured 26: colour blocks (right) fail the error test
    assert rms(np.hypot(shifts.dx[good] - PLANTED[0], shifts.dy[good] - PLANTED[1])) < 0.03
    for name in ("x", "y", "dx", "dy", "error", "texture"):
        assert np.all(np.isfinite(getattr(shifts, name)))

    reference, _ = planted_pairs["texture"]
    flat = RawImage(
        np.full(SHAPE, 0.5, np.float32) + rng.normal(0, 1e-3, SHAPE).astype(np.float32),
        LAYOUT,
        1.0,
        "550",
        550.0,
        labkit={"source_file": "flat/550.exr"},
    )
    with pytest.raises(DataError, match=r"flat/550\.exr \(550 nm\).*too little texture"):
        registration_keypoints([reference, flat], reference_nm=600.0)


def test_shifts_beyond_the_search_range_are_rejected(planted_pairs: dict) -> None:
    reference, band = planted_pairs["texture"]
    ref = green_bilinear(reference.raw, LAYOUT)
    mov = green_bilinear(band.raw, LAYOUT)
    assert patch_shifts(ref, mov, max_shift_px=0.3).n_accepted == 0
    assert patch_shifts(ref, mov, max_shift_px=1.0).n_accepted > 40


# -- 4. colour channels -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "blur_px"),
    # measured RMS (R, B): disks without blur 0.032 / 0.040 px; texture with 1 px blur
    # 0.030 / 0.026 px. Without blur the simulated texture, drawn on 2 px cells aligned
    # with the pixels, aliases on the 2 px R/B lattice and locks the shift (0.3 px off).
    [("disks", 0.0), ("texture", 1.0)],
)
def test_channel_registration_recovers_planted_red_and_blue_shifts(
    small_sim_rig: SimulatedRig, kind: str, blur_px: float
) -> None:
    rng = np.random.default_rng(8)
    lens = Lens(SHAPE, max_shift_px=0.0, blur_sigma_px=blur_px)
    scene = make_scene(kind)
    planted = {"R": (0.6, -0.3), "B": (-0.45, 0.25)}
    rgb = render(small_sim_rig, scene, lens, None)
    rgb[..., 0] = render(small_sim_rig, shifted(scene, planted["R"]), lens, None)[..., 0]
    rgb[..., 2] = render(small_sim_rig, shifted(scene, planted["B"]), lens, None)[..., 2]
    image = raw_image(rgb, None, f"{kind}/unfiltered.exr", rng)
    keypoints = channel_registration_keypoints(image)
    assert keypoints.reference == "G"
    assert not keypoints.spectral
    assert keypoints.bands == ["B", "R"]
    for channel, (tx, ty) in planted.items():
        part = keypoints.for_band(channel)
        assert len(part) >= 12
        error = np.hypot(part.dx - tx, part.dy - ty)
        assert rms(error) < 0.05, f"{kind} {channel}: RMS error {rms(error):.4f} px"
        assert keypoints.meta["channels"][channel]["accepted"] == len(part)

    filtered = dataclasses.replace(image, wavelength_nm=550.0, illumination="550")
    with pytest.raises(DataError, match="unfiltered image"):
        channel_registration_keypoints(filtered)


# -- input checks -----------------------------------------------------------------------


def test_inputs_are_checked(planted_pairs: dict) -> None:
    reference, band = planted_pairs["texture"]
    with pytest.raises(DataError, match=r"no image of the reference band 650 nm.*550, 600"):
        registration_keypoints([reference, band], reference_nm=650.0)
    cropped = dataclasses.replace(band, raw=band.raw[:, :-2])
    with pytest.raises(DataError, match="same camera mode"):
        registration_keypoints([reference, cropped], reference_nm=600.0)
    other_cfa = dataclasses.replace(band, cfa="RGGB")
    with pytest.raises(DataError, match="RGGB"):
        registration_keypoints([reference, other_cfa], reference_nm=600.0)
    with pytest.raises(DataError, match="both the 600 nm band"):
        registration_keypoints([reference, reference], reference_nm=600.0)
    unfiltered = dataclasses.replace(band, wavelength_nm=None, illumination="unfiltered")
    with pytest.raises(DataError, match="unfiltered"):
        registration_keypoints([reference, unfiltered], reference_nm=600.0)
    with pytest.raises(DataError, match="two 2-D images of one shape"):
        patch_shifts(np.zeros((80, 80)), np.zeros((80, 90)))
    nan = np.ones((80, 80))
    nan[3, 4] = np.nan
    with pytest.raises(DataError, match="NaN"):
        patch_shifts(np.ones((80, 80)), nan)


def test_wavelengths_mapping_labels_the_bands(planted_pairs: dict) -> None:
    """Bands may be labelled by illumination name (e.g. effective wavelengths)."""
    reference, band = planted_pairs["disks"]
    keypoints = registration_keypoints(
        [reference, band], reference_nm=601.5, wavelengths={"600": 601.5, "550": 548.25}
    )
    assert keypoints.bands == [548.25, 601.5]
    assert set(keypoints.meta["bands"]) == {"548.25", "601.5"}
    with pytest.raises(DataError, match=r"'550' has no entry in wavelengths="):
        registration_keypoints([reference, band], reference_nm=600.0, wavelengths={"600": 600})
