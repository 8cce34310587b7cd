"""Relative channel sensitivity (thesis Algorithm 12): known answers from planted and
simulated images, the rig's prediction, and the CSV/YAML files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration import (
    ChannelSensitivity,
    channel_sensitivity,
    nominal_channel_sensitivity,
    plot_channel_sensitivity,
)
from calibration.bands import filter_bands
from calibration.sensitivity import (
    is_sensitivity_file,
    load_response,
    neighbour_pairs,
    smooth_unsaturated_mask,
)
from labkit.cfa import CFA_LAYOUTS, channel_index, mosaic
from labkit.errors import ConfigError, DataError
from labkit.io.exr import RawImage
from labkit.rig import load_rig
from labkit.sim import SimulatedRig
from labkit.spectra import Spectra, camera_response, write_response_csv


def smooth_green(shape: tuple[int, int], *, level: float = 0.3) -> np.ndarray:
    """A smooth, non-negative test image (rows, cols) around `level`."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return level * (1 + 0.3 * np.sin(xx / 17.0) * np.cos(yy / 13.0) + 0.2 * xx / shape[1])


def planted(
    green: np.ndarray,
    r: float,
    b: float,
    layout: str,
    rng: np.random.Generator,
    *,
    noise: float = 2e-3,
    wavelength: float = 550.0,
) -> RawImage:
    """A mosaic with R = r·G and B = b·G exactly, plus Gaussian noise."""
    rgb = np.stack([r * green, green, b * green], axis=-1)
    raw = mosaic(rgb, layout) + noise * rng.standard_normal(green.shape)
    return RawImage(raw.astype(np.float32), layout, 0.5, f"{wavelength:g}", wavelength)


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_planted_ratios_are_recovered_for_every_layout(
    layout: str, rng: np.random.Generator
) -> None:
    image = planted(smooth_green((128, 160)), 0.37, 1.9, layout, rng)
    result = channel_sensitivity([image])
    assert result.wavelengths_nm.tolist() == [550.0]
    assert result.r_over_g[0] == pytest.approx(0.37, rel=0.005)
    assert result.b_over_g[0] == pytest.approx(1.9, rel=0.005)
    assert result.reliable_r[0] and result.reliable_b[0]
    assert result.reason_r == ("",) and result.reason_b == ("",)
    green = image.raw[channel_index(layout, image.raw.shape) == 1]
    assert result.green_level[0] == pytest.approx(green.mean() / 0.5, rel=1e-6)
    # about half the pixels of every plane pass the gradient test, so roughly a quarter of
    # the 2 × 128 × 160 / 2 green–red neighbour pairs keep both members
    assert 0.15 * 128 * 160 < result.pairs_r[0] < 0.4 * 128 * 160


def test_images_of_a_band_are_pooled_and_bands_sorted(rng: np.random.Generator) -> None:
    green = smooth_green((64, 64))
    a = planted(green, 0.5, 0.2, "GBRG", rng, wavelength=600)
    b = planted(0.5 * green, 0.5, 0.2, "RGGB", rng, wavelength=600)
    c = planted(green, 2.0, 0.1, "GBRG", rng, wavelength=450)
    together = channel_sensitivity([a, c, b])
    alone = [channel_sensitivity([image]) for image in (a, b)]
    assert together.wavelengths_nm.tolist() == [450.0, 600.0]
    assert together.illuminations == ("450", "600")
    assert together.pairs_r[1] == alone[0].pairs_r[0] + alone[1].pairs_r[0]
    assert together.r_over_g.tolist() == pytest.approx([2.0, 0.5], rel=0.01)
    assert together.b_over_g.tolist() == pytest.approx([0.1, 0.2], rel=0.01)


def test_channel_without_signal_is_flagged_not_nan(rng: np.random.Generator) -> None:
    green = smooth_green((96, 128))
    dark_red = planted(green, 0.0, 1.2, "GRBG", rng, noise=1e-3)  # red is pure noise
    result = channel_sensitivity([dark_red])
    assert not result.reliable_r[0]
    assert "red has no signal" in result.reason_r[0]
    assert np.isfinite(result.r_over_g[0])  # reported (a noise fit), but flagged
    assert result.reliable_b[0] and result.b_over_g[0] == pytest.approx(1.2, rel=0.005)


def test_channel_with_no_pairs_is_nan_and_unreliable(rng: np.random.Generator) -> None:
    green = smooth_green((32, 32))
    image = planted(green, 0.0, 0.8, "BGGR", rng, noise=0.0)  # red exactly 0: never kept
    small = planted(green[:8, :8], 0.5, 0.5, "BGGR", rng, wavelength=650)
    result = channel_sensitivity([image, small])
    assert np.isnan(result.r_over_g[0]) and not result.reliable_r[0]
    assert "only 0 green–red pairs" in result.reason_r[0]
    assert not result.reliable_r[1] and not result.reliable_b[1]  # 8 × 8 px: too few pairs
    assert "need 200" in result.reason_r[1]


def test_gradients_are_taken_per_colour_plane_and_saturation_excluded() -> None:
    # flat within every colour plane but strongly different between channels: a gradient
    # across the mosaic would reject everything, a per-plane gradient keeps everything
    raw = mosaic(np.broadcast_to([0.1, 0.5, 0.9], (16, 20, 3)), "GBRG")
    raw[3, 4], raw[5, 5] = 0.97, -0.01
    keep = smooth_unsaturated_mask(raw)
    expected = np.ones_like(keep)
    expected[3, 4] = expected[5, 5] = False
    # each outlier raises the gradient of its 4 neighbours *in its own plane* (2 px away;
    # central differences leave its own gradient at 0), above the plane's median of 0
    red_plane = [(3, 2), (3, 6), (1, 4), (5, 4)]  # around (3, 4), a Red pixel of GBRG
    green_plane = [(5, 3), (5, 7), (3, 5), (7, 5)]  # around (5, 5), a Green pixel
    for row, col in red_plane + green_plane:
        expected[row, col] = False
    np.testing.assert_array_equal(keep, expected)


@pytest.mark.parametrize("layout", CFA_LAYOUTS)
def test_neighbour_pairs_match_a_brute_force_enumeration(layout: str) -> None:
    shape = (6, 8)
    raw = np.arange(np.prod(shape), dtype=np.float64).reshape(shape)
    index = channel_index(layout, shape)
    keep = np.ones(shape, dtype=bool)
    keep[2, 3] = keep[4, 4] = False
    for channel in (0, 2):
        green, other = neighbour_pairs(raw, keep, index, channel)
        expected = set()
        for row in range(shape[0]):
            for col in range(shape[1]):
                if index[row, col] != 1 or not keep[row, col]:
                    continue
                for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                    r, c = row + dr, col + dc
                    inside = 0 <= r < shape[0] and 0 <= c < shape[1]
                    if inside and index[r, c] == channel and keep[r, c]:
                        expected.add((raw[row, col], raw[r, c]))
        assert sorted(zip(green, other, strict=True)) == sorted(expected)


def test_simulated_rig_ratios_match_the_camera_response(
    tmp_path: Path, make_rig, rng: np.random.Generator
) -> None:
    """Flat grey scenes through the simulated rig: measured ratios vs ∫ q T L dλ.

    The camera response's Red channel is cut below 430 nm and the 400 nm filter blocks
    OD 8, so Red has no signal at 400 nm (as on the thesis' camera).
    """
    nikon = camera_response("Nikon 5100 (NPL)")
    values = nikon.values.copy()
    values[nikon.wavelengths < 430, 0] = 0.0
    response = tmp_path / "response.csv"
    write_response_csv(Spectra(nikon.wavelengths, values, nikon.labels), response)
    rig = load_rig(
        make_rig(
            **{
                "camera.response": str(response),
                "slider.positions.2.filter.optical_density": 8,
                "sim.scenes.flat": {"type": "flat", "reflectance": 0.6},
                "sim.scenes.grey": {"type": "flat", "reflectance": 0.25},
            }
        )
    )
    world = SimulatedRig(rig, shape=(96, 128))
    bands = [name for name in rig.slider.illumination_names() if rig.filter_for(name)]
    full_well = world.sensor.model.full_well_e
    images = []
    for scene in ("flat", "grey"):
        world.prerender(scene, bands)
        for name in bands:
            electrons_per_s = world.irradiance(scene, name).astype(np.float64)
            exposure = 0.8 * full_well / world.irradiance("flat", name).max()
            fraction = electrons_per_s * exposure / full_well  # brightest channel ≤ 0.8
            # HDR noise: shot + 8 e⁻ read noise, averaged over 5 frames
            sigma = np.sqrt(8.0**2 + fraction * full_well) / full_well / np.sqrt(5)
            raw = fraction + sigma * rng.standard_normal(fraction.shape)
            wavelength = rig.filter_for(name).centre_nm
            images.append(RawImage(raw.astype(np.float32), rig.cfa, exposure, name, wavelength,
                                   labkit={"scene": scene}))  # fmt: skip

    measured = channel_sensitivity(images)
    nominal = nominal_channel_sensitivity(rig)
    np.testing.assert_array_equal(measured.wavelengths_nm, nominal.wavelengths_nm)
    assert measured.illuminations == tuple(bands)
    # 400 nm: Red has no signal → flagged with a reason, still a number, not NaN
    assert not measured.reliable_r[0] and "red has no signal" in measured.reason_r[0]
    assert np.isfinite(measured.r_over_g[0])
    assert nominal.r_over_g[0] < 0.002
    assert measured.reliable_b[0]
    # every other ratio has signal and matches the prediction within 2 %
    assert measured.reliable_r[1:].all() and measured.reliable_b.all()
    for key in ("r", "b"):
        ok = getattr(measured, f"reliable_{key}")
        ratio = getattr(measured, f"{key}_over_g")[ok] / getattr(nominal, f"{key}_over_g")[ok]
        np.testing.assert_allclose(ratio, 1.0, rtol=0.02, err_msg=f"{key}/g per band")
    assert measured.labkit["scenes"] == ["flat", "grey"]

    plot = tmp_path / "sensitivity.png"
    plot_channel_sensitivity(measured, nominal, plot)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_nominal_ratios_equal_a_rendered_grey_scene(tmp_path: Path, make_rig) -> None:
    rig = load_rig(
        make_rig(
            **{
                "sim.lens.vignetting": 0.0,
                "sim.scenes.flat": {"type": "flat", "reflectance": 0.5},
            }
        )
    )
    nominal = nominal_channel_sensitivity(rig)
    assert nominal.illuminations == ("400", "450", "500", "550", "600", "650", "700")
    assert nominal.source == "nominal" and nominal.reliable.all()
    world = SimulatedRig(rig, shape=(8, 8))
    rendered = world.render_rgb("flat", list(nominal.illuminations))
    for i, name in enumerate(nominal.illuminations):
        r, g, b = rendered[name].reshape(-1, 3).astype(np.float64).mean(axis=0)
        assert nominal.r_over_g[i] == pytest.approx(r / g, rel=1e-5)
        assert nominal.b_over_g[i] == pytest.approx(b / g, rel=1e-5)
    greens = np.array(
        [rendered[name][..., 1].astype(np.float64).mean() for name in nominal.illuminations]
    )  # the predicted Green levels are relative: their ratios are the rendered ones
    np.testing.assert_allclose(
        nominal.green_level / nominal.green_level[3], greens / greens[3], rtol=1e-5
    )
    only = nominal_channel_sensitivity(rig, ["650", "450"])
    assert only.illuminations == ("450", "650")
    assert only.r_over_g.tolist() == [nominal.r_over_g[1], nominal.r_over_g[5]]
    with pytest.raises(ConfigError, match="'unfiltered' has no filter"):
        nominal_channel_sensitivity(rig, ["unfiltered"])


def test_unfiltered_images_are_rejected(rng: np.random.Generator) -> None:
    image = planted(smooth_green((16, 16)), 0.5, 0.5, "GBRG", rng)
    image.wavelength_nm = None
    with pytest.raises(DataError, match="unfiltered"):
        channel_sensitivity([image])


# -- files ------------------------------------------------------------------------------------


def example_table() -> ChannelSensitivity:
    return ChannelSensitivity(
        wavelengths_nm=[400.0, 550.0, 650.0],
        illuminations=("400", "550", "650"),
        r_over_g=[np.nan, 0.0575, 11.694],
        b_over_g=[6.37, 0.0884, 0.1735],
        pairs_r=[0, 3061, 3088],
        pairs_b=[1903, 3061, 3088],
        residual_r=[np.nan, 0.012, 0.004],
        residual_b=[0.01, 0.02, 0.03],
        reliable_r=[False, True, True],
        reliable_b=[True, True, True],
        reason_r=("only 0 green–red pairs (need 200), no fit", "", ""),
        reason_b=("", "", ""),
        green_level=[0.002, 1.5, 0.03],
        labkit={"method": "test", "scenes": ["flat"]},
    )


@pytest.mark.parametrize("suffix", ["csv", "yaml"])
def test_sensitivity_file_round_trip(tmp_path: Path, suffix: str) -> None:
    table = example_table()
    path = tmp_path / f"sensitivity.{suffix}"
    getattr(table, f"to_{suffix}")(path)
    back = ChannelSensitivity.from_file(path)
    for name in ("wavelengths_nm", "r_over_g", "b_over_g", "residual_r", "residual_b",
                 "pairs_r", "pairs_b", "reliable_r", "reliable_b", "green_level"):  # fmt: skip
        np.testing.assert_array_equal(getattr(back, name), getattr(table, name), err_msg=name)
    assert back.illuminations == table.illuminations
    assert back.reason_r == table.reason_r and back.reason_b == table.reason_b
    assert back.labkit["file"] == str(path)
    if suffix == "yaml":
        assert back.source == "measured" and back.labkit["scenes"] == ["flat"]


def test_hand_written_csv_needs_only_the_ratios(tmp_path: Path) -> None:
    path = tmp_path / "hand.csv"
    path.write_text("wavelength_nm,r_over_g,b_over_g\n650,11.7,0.17\n450,0.38,5.2\n")
    table = ChannelSensitivity.from_file(path)
    assert table.wavelengths_nm.tolist() == [450.0, 650.0]
    assert table.r_over_g.tolist() == [0.38, 11.7]
    assert table.illuminations == ("450", "650") and table.reliable.all()
    assert np.isnan(table.green_level).all() and not table.has_levels
    np.testing.assert_array_equal(table.as_response().values[:, 1], 1.0)  # the thesis' map
    assert table.index_of(450.03) == 0 and table.index_of(451) is None


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g\n550,abc,0.1\n", "line 2, column 'r_over_g'"),
        ("bad.csv", "wavelength_nm,r_over_g\n550,0.1\n", "column 'b_over_g' is missing"),
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g,gain\n550,1,1,2\n", "column 'gain'"),
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g\n550,1,1\n550,2,2\n",
         "line 3, column 'wavelength_nm' repeats"),
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g,reliable_r\n550,,1,true\n",
         "line 2, column 'r_over_g' is missing"),
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g\n550,-0.5,1\n",
         "line 2, column 'r_over_g' is -0.5"),
        ("bad.csv", "wavelength_nm,r_over_g,b_over_g,green_level\n550,0.5,1,0\n",
         "line 2, column 'green_level' is 0; a Green level must be positive"),
        ("bad.yaml", "format: 1\nbands:\n- {wavelength_nm: 450, r_over_g: 1, b_over_g: 1}\n"
         "- {wavelength_nm: 550, r_over_g: 1, b_over_g: x}\n", "bands[1].b_over_g is 'x'"),
        ("bad.yaml", "format: 1\nbands:\n- {wavelength_nm: 450, r_over_g: 1, b_over_G: 1}\n",
         "bands[0].b_over_G is not a known key"),
        ("bad.yaml", "format: 1\nbands:\n- {wavelength_nm: 450, r_over_g: 1, b_over_g: 1,"
         " reliable_b: maybe}\n", "bands[0].reliable_b is 'maybe'"),
        ("bad.yaml", "format: 2\nbands: []\n", "format is 2"),
        ("bad.yaml", "bands: {a: 1}\n", "bands is missing or not a list"),
        ("bad.txt", "wavelength_nm,r_over_g,b_over_g\n", "unknown sensitivity file type"),
    ],
)  # fmt: skip
def test_malformed_sensitivity_file_names_file_and_field(
    tmp_path: Path, name: str, text: str, where: str
) -> None:
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(DataError) as error:
        ChannelSensitivity.from_file(path)
    message = str(error.value)
    assert message.startswith(str(path)), message
    assert where in message, message
    assert "\n" not in message


def test_a_measured_sensitivity_is_a_camera_response_sampled_at_its_bands(tmp_path: Path):
    table = example_table()
    table.r_over_g[0] = 0.02  # the example's unreliable band: a finite ratio, used as is
    table.to_yaml(tmp_path / "sensitivity.yaml")
    table.to_csv(tmp_path / "sensitivity.csv")
    for path in (tmp_path / "sensitivity.yaml", tmp_path / "sensitivity.csv"):
        assert is_sensitivity_file(path)
        response = load_response(path)
        assert response.labels == ("R", "G", "B")
        np.testing.assert_array_equal(response.wavelengths, table.wavelengths_nm)
        level = np.array([0.002, 1.5, 0.03]) / 1.5  # relative to the brightest band
        np.testing.assert_allclose(response.values[:, 0], table.r_over_g * level, rtol=1e-15)
        np.testing.assert_allclose(response.values[:, 1], level, rtol=1e-15)
        np.testing.assert_allclose(response.values[:, 2], table.b_over_g * level, rtol=1e-15)
    write_response_csv(camera_response("Nikon 5100 (NPL)"), tmp_path / "curve.csv")
    assert not is_sensitivity_file(tmp_path / "curve.csv")
    np.testing.assert_array_equal(
        load_response(tmp_path / "curve.csv").values, camera_response(tmp_path / "curve.csv").values
    )
    assert load_response("Nikon 5100 (NPL)").labels == ("R", "G", "B")
    table.r_over_g[1] = np.nan
    table.reliable_r[1] = False
    with pytest.raises(DataError, match=r"r_over_g at 550 nm is unknown"):
        table.as_response()


def test_a_rig_can_name_its_measured_sensitivity(make_rig, tmp_path: Path) -> None:
    """``camera.response: sensitivity.yaml`` (relative to the rig file) reaches every user."""
    rig_file = make_rig(**{"camera.response": "sensitivity.yaml"})
    table = nominal_channel_sensitivity(load_rig(make_rig()))
    table.to_yaml(rig_file.parent / "sensitivity.yaml")
    rig = load_rig(rig_file)
    assert rig.response_source() == str(rig_file.parent / "sensitivity.yaml")
    bands = filter_bands(rig)  # purity and effective wavelengths from the sampled map
    assert set(bands) == {"400", "450", "500", "550", "600", "650", "700"}
    curve = filter_bands(load_rig(make_rig()))  # the continuous response it was made from
    for name in ("450", "500", "550", "600", "650"):
        assert bands[name].effective_nm == pytest.approx(curve[name].effective_nm, abs=3.0), name
        assert bands[name].purity > 0.9, name
