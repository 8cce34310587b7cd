"""``labkit calibrate sensitivity`` and ``labkit synthesize`` on an HDR folder written here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration import (
    ChannelSensitivity,
    channel_sensitivity,
    load_filtered_hdr,
    nominal_channel_sensitivity,
    synthesize_multispectral,
)
from labkit.cfa import mosaic
from labkit.cli import main
from labkit.io import RawImage, read_raw_exr, read_spectral_exr, write_raw_exr
from labkit.rig import load_rig

SHAPE = (48, 64)


@pytest.fixture
def hdr_folder(tmp_path: Path, sim_rig_path: Path, rng: np.random.Generator) -> Path:
    """``hdr/<scene>/<illumination>.exr`` for 2 scenes × 7 filters + 1 unfiltered image.

    Each band plants the default rig's nominal R/G and B/G on a smooth image with noise.
    """
    rig = load_rig(sim_rig_path)
    nominal = nominal_channel_sensitivity(rig)
    folder = tmp_path / "hdr"
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    smooth = 1 + 0.3 * np.sin(xx / 9.0) * np.cos(yy / 7.0)
    for scene, level in (("chart", 0.6), ("flat", 0.3)):
        for i, name in enumerate(nominal.illuminations):
            r, b = nominal.r_over_g[i], nominal.b_over_g[i]
            green = level * smooth / max(1.0, r, b)  # brightest channel ≤ 0.78
            rgb = np.stack([r * green, green, b * green], axis=-1)
            raw = mosaic(rgb, rig.cfa) + 2e-4 * rng.standard_normal(SHAPE)
            image = RawImage(raw.astype(np.float32), rig.cfa, 0.1 * (i + 1), name,
                             nominal.wavelengths_nm[i],
                             labkit={"scene": scene, "illumination": name})  # fmt: skip
            write_raw_exr(folder / scene / f"{name}.exr", image)
        unfiltered = RawImage(np.full(SHAPE, 0.5, np.float32), rig.cfa, 0.003, "unfiltered",
                              labkit={"scene": scene, "illumination": "unfiltered"})  # fmt: skip
        write_raw_exr(folder / scene / "unfiltered.exr", unfiltered)
    return folder


def test_calibrate_sensitivity_writes_the_api_result(
    hdr_folder: Path, tmp_path: Path, sim_rig_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "calib"
    assert main(["calibrate", "sensitivity", str(hdr_folder), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "14 image(s) of 2 scene(s) ['chart', 'flat']" in printed
    for name in ("sensitivity.csv", "sensitivity.yaml", "sensitivity.png"):
        assert (out / name).stat().st_size > 0, name

    images = [image for group in load_filtered_hdr(hdr_folder).values() for image in group]
    expected = channel_sensitivity(images)
    for path in (out / "sensitivity.csv", out / "sensitivity.yaml"):
        written = ChannelSensitivity.from_file(path)
        np.testing.assert_array_equal(written.wavelengths_nm, expected.wavelengths_nm)
        np.testing.assert_array_equal(written.r_over_g, expected.r_over_g)
        np.testing.assert_array_equal(written.b_over_g, expected.b_over_g)
        np.testing.assert_array_equal(written.pairs_r, expected.pairs_r)
        np.testing.assert_array_equal(written.reliable_b, expected.reliable_b)
    # the planted ratios are the default rig's nominal ones: the table shows small differences
    nominal = nominal_channel_sensitivity(load_rig(sim_rig_path))
    np.testing.assert_allclose(expected.r_over_g, nominal.r_over_g, rtol=0.01)
    np.testing.assert_allclose(expected.b_over_g, nominal.b_over_g, rtol=0.01)
    rows = [line for line in printed.splitlines() if " nm " in line]
    assert [row.split()[0] for row in rows] == ["400.0", "450.0", "500.0", "550.0", "600.0",
                                                "650.0", "700.0"]  # fmt: skip
    for row in rows:
        cells = row.split()
        assert cells[-1] == "yes"
        assert abs(float(cells[4].rstrip("%"))) <= 1.0 and abs(float(cells[7].rstrip("%"))) <= 1.0


def test_calibrate_one_scene_and_synthesize(
    hdr_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "calib"
    args = ["calibrate", "sensitivity", str(hdr_folder), "--out", str(out), "--scene", "flat"]
    assert main(args) == 0
    flat_only = channel_sensitivity(load_filtered_hdr(hdr_folder, scenes=["flat"])["flat"])
    table = ChannelSensitivity.from_file(out / "sensitivity.csv")
    np.testing.assert_array_equal(table.pairs_r, flat_only.pairs_r)

    synth = tmp_path / "synth"
    args = ["synthesize", str(hdr_folder), "--sensitivity", str(out / "sensitivity.yaml"),
            "--out", str(synth)]  # fmt: skip
    assert main(args) == 0
    assert "wrote 2 scene(s)" in capsys.readouterr().out
    for scene in ("chart", "flat"):
        expected = synthesize_multispectral(load_filtered_hdr(hdr_folder)[scene], table)
        raw = read_raw_exr(synth / f"{scene}-synthetic-raw.exr")
        np.testing.assert_array_equal(raw.raw, expected.raw.raw)
        assert raw.labkit["scene"] == scene
        cube = read_spectral_exr(synth / f"{scene}-multispectral.exr")
        np.testing.assert_array_equal(cube.cube, expected.multispectral.cube)
        assert (synth / f"{scene}-synthetic-rgb.png").stat().st_size > 0

    only = tmp_path / "only"
    args = ["synthesize", str(hdr_folder), "--sensitivity", str(out / "sensitivity.csv"),
            "--scene", "chart", "--out", str(only)]  # fmt: skip
    assert main(args) == 0
    assert sorted(p.name for p in only.iterdir()) == [
        "chart-multispectral.exr", "chart-synthetic-raw.exr", "chart-synthetic-rgb.png",
        "labkit-run.json",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("command", "message"),
    [
        (["calibrate", "sensitivity", "{empty}", "--out", "{tmp}/o"],
         "holds no filtered-light images"),
        (["calibrate", "sensitivity", "{hdr}", "--out", "{tmp}/o", "--scene", "disks"],
         "no filtered images of scene(s) ['disks']"),
        (["synthesize", "{hdr}", "--sensitivity", "{tmp}/bad.csv", "--out", "{tmp}/o"],
         "bad.csv: line 2, column 'b_over_g' is 'x'"),
        (["synthesize", "{hdr}", "--sensitivity", "{tmp}/short.csv", "--out", "{tmp}/o"],
         "has no 400 nm band"),
    ],
)  # fmt: skip
def test_bad_inputs_exit_2_with_one_line(
    hdr_folder: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    command: list[str],
    message: str,
) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad.csv").write_text("wavelength_nm,r_over_g,b_over_g\n550,0.1,x\n")
    (tmp_path / "short.csv").write_text("wavelength_nm,r_over_g,b_over_g\n550,0.1,0.1\n")
    places = {"empty": tmp_path / "empty", "hdr": hdr_folder, "tmp": tmp_path}
    capsys.readouterr()
    assert main([part.format(**places) for part in command]) == 2
    error = capsys.readouterr().err
    assert error.startswith("labkit: error: ") and error.count("\n") == 1, error
    assert message in error
    assert not (tmp_path / "o").exists()


def test_calibrate_is_a_command_group(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--help"]) == 0
    assert "sensitivity" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        ("nan", "1 NaN/Inf value"),
        ("zeros", "holds no light"),
        ("saturated", "are saturated"),
        ("negated", "holds no light"),
    ],
)
def test_degenerate_hdr_images_are_refused_and_nothing_is_written(
    hdr_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str, match: str
) -> None:
    path = hdr_folder / "chart" / "550.exr"
    image = read_raw_exr(path)
    raw = image.raw.copy()
    if damage == "nan":
        raw[3, 4] = np.nan
    elif damage == "zeros":
        raw[:] = 0
    elif damage == "saturated":
        raw[:] = 1.0
    else:
        raw = -raw
    if damage == "nan":  # labkit's writer refuses NaN: write it as other software might
        from labkit.io.exr import read_exr, write_exr

        header, channels = read_exr(path)
        channels["raw"] = raw.astype(np.float32)
        keep = ("compression", "type", "labkit", "cfa", "exposure_s", "wavelength_nm")
        write_exr(path, {k: v for k, v in header.items() if k in keep}, channels)
    else:
        image.raw = raw
        write_raw_exr(path, image)
    image.raw = raw
    out = tmp_path / "calib"
    assert main(["calibrate", "sensitivity", str(hdr_folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and match in err and err.count("\n") == 1
    assert not out.exists()
    with pytest.raises(Exception, match=match):
        channel_sensitivity([image])  # the Python API refuses it too


def test_a_sensor_map_with_some_green_levels_missing_is_not_a_response(
    hdr_folder: Path,
) -> None:
    from labkit.errors import DataError

    table = channel_sensitivity(
        [image for group in load_filtered_hdr(hdr_folder).values() for image in group]
    )
    assert table.has_levels
    table.green_level[2] = np.nan
    with pytest.raises(DataError, match=r"Green level at .* nm is missing"):
        table.as_response()
    table.green_level[:] = np.nan  # the thesis' convention: no levels at all, G = 1
    np.testing.assert_allclose(table.as_response().values[:, 1], 1.0)
