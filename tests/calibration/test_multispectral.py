"""Multispectral and synthetic RGB/raw synthesis (thesis Algorithm 13): exact values from
planted band images, bilinear Green interpolation, consistency checks and files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration import (
    ChannelSensitivity,
    green_bilinear,
    load_filtered_hdr,
    synthesize_multispectral,
    write_synthesis,
)
from labkit.cfa import CFA_LAYOUTS, channel_masks
from labkit.errors import DataError
from labkit.io import RawImage, read_raw_exr, read_spectral_exr, write_raw_exr
from labkit.io.preview import demosaic_bilinear

#: Planted bands: wavelength (nm), constant HDR value, reference exposure (s), R/G, B/G.
BANDS = [
    (650.0, 0.8, 0.25, 11.7, 0.17),
    (450.0, 0.6, 2.0, 0.38, 5.2),
    (550.0, 0.3, 0.1, 0.06, 0.09),
]


def sensitivity_table(
    *, reliable_b: bool = True, nan_at: float | None = None
) -> ChannelSensitivity:
    """The ratios of BANDS (sorted); optionally 450 nm B/G unreliable, or R/G missing."""
    rows = sorted(BANDS)
    return ChannelSensitivity(
        wavelengths_nm=[w for w, *_ in rows],
        illuminations=tuple(f"{w:g}" for w, *_ in rows),
        r_over_g=[np.nan if w == nan_at else r for w, _, _, r, _ in rows],
        b_over_g=[b for *_, b in rows],
        pairs_r=[500] * 3,
        pairs_b=[500] * 3,
        residual_r=[0.01] * 3,
        residual_b=[0.01] * 3,
        reliable_r=[w != nan_at for w, *_ in rows],
        reliable_b=[reliable_b, True, True],
        reason_r=tuple("no fit" if w == nan_at else "" for w, *_ in rows),
        reason_b=("" if reliable_b else "blue has no signal", "", ""),
    )


def band_images(
    layout: str, shape: tuple[int, int] = (12, 16), *, scene: str = "chart"
) -> list[RawImage]:
    return [
        RawImage(np.full(shape, value, np.float32), layout, exposure, f"{w:g}", w,
                 labkit={"scene": scene, "illumination": f"{w:g}"})
        for w, value, exposure, *_ in BANDS
    ]  # fmt: skip


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_constant_bands_give_exact_multispectral_rgb_and_raw(layout: str) -> None:
    synthesis = synthesize_multispectral(band_images(layout), sensitivity_table())
    order = sorted(BANDS)
    rates = np.array([value / exposure for _, value, exposure, *_ in order])  # 0.3/0.1 …
    cube = synthesis.multispectral.cube
    assert synthesis.multispectral.wavelengths_nm.tolist() == [450.0, 550.0, 650.0]
    assert cube.shape == (12, 16, 3) and cube.dtype == np.float32
    np.testing.assert_allclose(cube, np.broadcast_to(rates, cube.shape), rtol=1e-6)
    expected_rgb = np.array(
        [sum(rate * row[3] for rate, row in zip(rates, order, strict=True)),
         rates.sum(),
         sum(rate * row[4] for rate, row in zip(rates, order, strict=True))]
    )  # fmt: skip
    # 0.3 + 3 + 3.2 = 6.5 per second in Green
    assert expected_rgb[1] == pytest.approx(0.6 / 2.0 + 0.3 / 0.1 + 0.8 / 0.25)
    np.testing.assert_allclose(synthesis.rgb, np.broadcast_to(expected_rgb, (12, 16, 3)), rtol=1e-5)
    masks = channel_masks(layout, (12, 16))
    raw = synthesis.raw
    assert raw.cfa == layout and raw.exposure_s == 1.0 and raw.illumination == "synthetic"
    assert raw.wavelength_nm is None
    for channel in range(3):
        np.testing.assert_allclose(raw.raw[masks[..., channel]], expected_rgb[channel], rtol=1e-5)
    assert raw.labkit["units"] == "fraction of saturation per second"
    assert raw.labkit["scene"] == "chart"
    assert raw.labkit["sensitivity"]["450"] == {"r_over_g": 0.38, "b_over_g": 5.2,
                                                "reliable": True}  # fmt: skip


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_green_interpolation_is_bilinear_demosaicing(layout: str, rng: np.random.Generator) -> None:
    raw = rng.uniform(0, 1, (10, 14))
    green = green_bilinear(raw, layout)
    np.testing.assert_allclose(green, demosaic_bilinear(raw, layout)[..., 1], rtol=1e-6)
    sites = channel_masks(layout, raw.shape)[..., 1]
    np.testing.assert_array_equal(green[sites], raw[sites])
    # a Red/Blue site inside the image averages its four Green neighbours
    row, col = next((r, c) for r, c in zip(*np.nonzero(~sites), strict=True) if r and c)
    neighbours = raw[row - 1, col] + raw[row + 1, col] + raw[row, col - 1] + raw[row, col + 1]
    assert green[row, col] == pytest.approx(neighbours / 4)


def test_rgb_green_is_the_sum_of_the_bands_and_red_blue_are_weighted(
    rng: np.random.Generator,
) -> None:
    images = band_images("GBRG", (20, 24))
    for image in images:
        image.raw = rng.uniform(0, 0.9, image.raw.shape).astype(np.float32)
    synthesis = synthesize_multispectral(images, sensitivity_table())
    cube = synthesis.multispectral.cube.astype(np.float64)
    np.testing.assert_allclose(synthesis.rgb[..., 1], cube.sum(axis=-1), rtol=1e-5)
    np.testing.assert_allclose(synthesis.rgb[..., 0], cube @ [0.38, 0.06, 11.7], rtol=1e-5)
    np.testing.assert_allclose(synthesis.rgb[..., 2], cube @ [5.2, 0.09, 0.17], rtol=1e-5)
    by_wavelength = {image.wavelength_nm: image for image in images}
    expected = green_bilinear(by_wavelength[550.0].raw, "GBRG") / 0.1
    np.testing.assert_allclose(cube[..., 1], expected, rtol=1e-6)


def test_unreliable_ratios_are_used_and_recorded() -> None:
    synthesis = synthesize_multispectral(band_images("RGGB"), sensitivity_table(reliable_b=False))
    assert synthesis.raw.labkit["unreliable_bands"] == [450.0]
    assert synthesis.raw.labkit["sensitivity"]["450"]["reliable"] is False


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("shape", "is 15×12 GBRG but"),
        ("cfa", "is 16×12 RGGB but"),
        ("band", "has no 500 nm band"),
        ("duplicate", "are both the 550 nm band"),
        ("nan", "no R/G or B/G for the 650 nm band (no fit)"),
        ("unfiltered", "is unfiltered"),
    ],
)
def test_inconsistent_inputs_are_rejected(change: str, message: str) -> None:
    images = band_images("GBRG")
    table = sensitivity_table(nan_at=650.0 if change == "nan" else None)
    if change == "shape":
        images[1].raw = images[1].raw[:, :15]
    elif change == "cfa":
        images[1].cfa = "RGGB"
    elif change == "band":
        images[1].wavelength_nm = 500.0
    elif change == "duplicate":
        images[0].wavelength_nm = 550.0
    elif change == "unfiltered":
        images[2].wavelength_nm = None
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)")):
        synthesize_multispectral(images, table)


def test_write_synthesis_round_trip_and_folder_loader(tmp_path: Path) -> None:
    hdr = tmp_path / "hdr"
    for scene in ("chart", "disks"):
        for image in band_images("GBRG", scene=scene):
            write_raw_exr(hdr / scene / f"{image.illumination}.exr", image)
    unfiltered = RawImage(np.ones((12, 16), np.float32), "GBRG", 0.01, "unfiltered",
                          labkit={"scene": "chart"})  # fmt: skip
    write_raw_exr(hdr / "chart" / "unfiltered.exr", unfiltered)

    scenes = load_filtered_hdr(hdr)
    assert sorted(scenes) == ["chart", "disks"]
    assert [image.wavelength_nm for image in scenes["chart"]] == [450.0, 550.0, 650.0]
    assert scenes["chart"][0].labkit["source_file"] == str(hdr / "chart" / "450.exr")
    synthesis = synthesize_multispectral(scenes["chart"], sensitivity_table())
    paths = write_synthesis(synthesis, tmp_path / "out", "chart")
    assert sorted(p.name for p in paths.values()) == [
        "chart-multispectral.exr", "chart-synthetic-raw.exr", "chart-synthetic-rgb.png"
    ]  # fmt: skip
    spectral = read_spectral_exr(paths["multispectral"])
    np.testing.assert_array_equal(spectral.cube, synthesis.multispectral.cube)
    assert spectral.wavelengths_nm.tolist() == [450.0, 550.0, 650.0]
    raw = read_raw_exr(paths["raw"])
    np.testing.assert_array_equal(raw.raw, synthesis.raw.raw)
    assert raw.cfa == "GBRG" and raw.illumination == "synthetic" and raw.wavelength_nm is None
    assert raw.labkit["sources"] == [str(hdr / "chart" / f"{w}.exr") for w in (450, 550, 650)]
    assert raw.labkit["source_exposures_s"] == [2.0, 0.1, 0.25]
    assert paths["rgb"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_folder_loader_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="does not exist"):
        load_filtered_hdr(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="holds no filtered-light images"):
        load_filtered_hdr(tmp_path / "empty")
    images = band_images("GBRG")
    images[2].raw = images[2].raw[:10]
    for image in images:
        write_raw_exr(tmp_path / "hdr" / "chart" / f"{image.illumination}.exr", image)
    with pytest.raises(DataError, match=r"scene\(s\) \['disks'\].*scenes with filtered images"):
        load_filtered_hdr(tmp_path / "hdr", scenes=["disks"])
    with pytest.raises(DataError, match=r"550\.exr is 16×10 GBRG but .*450\.exr is 16×12 GBRG"):
        load_filtered_hdr(tmp_path / "hdr")
