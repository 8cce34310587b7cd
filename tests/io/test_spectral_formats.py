"""Spectral images in the field's formats: the Fichet et al. (2021) OpenEXR layout (checked
with colour-science's reader, not only labkit's), labkit's older EXR layout, ENVI (checked
with Spectral Python's reader) and xarray. Round trips must be exact in float32."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from colour.io import (
    Specification_Fichet2021,
    read_spectral_image_Fichet2021,
    write_spectral_image_Fichet2021,
)
from spectral.io import envi

from labkit.cli import main
from labkit.errors import DataError
from labkit.io import (
    SpectralImage,
    read_envi,
    read_spectral_exr,
    write_envi,
    write_spectral_exr,
)

# uneven centres, one that is not a whole nm, one with a long decimal expansion
WAVELENGTHS = np.array([400.0, 433.3333333333333, 552.5, 610.0, 700.0])


def _image(dtype: type = np.float32, shape: tuple[int, int] = (12, 17)) -> SpectralImage:
    rng = np.random.default_rng(7)
    cube = (rng.random((*shape, WAVELENGTHS.size)) * 3 - 0.5).astype(dtype)
    cube[0, 0] = [0.0, 1e-30, 3.0e38, -2.0, 1.5]  # extremes float32 holds exactly
    return SpectralImage(cube, WAVELENGTHS.copy(), {"units": "raw units per nm", "note": "t"})


def test_the_published_layout_reads_back_through_colour_science(tmp_path: Path) -> None:
    image = _image()
    path = tmp_path / "spectral.exr"
    write_spectral_exr(path, image)

    components, specification = read_spectral_image_Fichet2021(path, additional_data=True)
    assert set(components) == {"S0"} and specification.is_emissive
    wavelengths, values = components["S0"]
    np.testing.assert_allclose(wavelengths, WAVELENGTHS, rtol=1e-11)  # 12 digits in names
    np.testing.assert_array_equal(values, image.cube)
    attributes = {a.name: a.value for a in specification.attributes}
    assert attributes["spectralLayoutVersion"] == "1.0"
    assert attributes["emissiveUnits"] == "raw units per nm"
    provenance = json.loads(attributes["labkit"])
    assert provenance["note"] == "t" and provenance["wavelengths_nm"] == WAVELENGTHS.tolist()

    channels = set(OpenEXR.File(str(path), separate_channels=True).channels())
    assert {"S0.552,5nm", "S0.400,0nm", "R", "G", "B"} <= channels


def test_labkit_reads_back_exactly_and_keeps_its_provenance(tmp_path: Path) -> None:
    image = _image(np.float64)  # float64 in, float32 stored
    path = tmp_path / "spectral.exr"
    write_spectral_exr(path, image)
    back = read_spectral_exr(path)
    assert back.cube.dtype == np.float32
    np.testing.assert_array_equal(back.cube, image.cube.astype(np.float32))
    np.testing.assert_array_equal(back.wavelengths_nm, WAVELENGTHS)
    assert back.labkit["note"] == "t" and back.labkit["units"] == "raw units per nm"


def test_the_rgb_channels_show_an_equal_energy_spectrum_of_one_as_luminance_one(
    tmp_path: Path,
) -> None:
    wavelengths = np.arange(400.0, 701.0, 10.0)
    path = tmp_path / "flat.exr"
    write_spectral_exr(path, SpectralImage(np.ones((4, 5, wavelengths.size)), wavelengths))
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    r, g, b = (np.asarray(channels[c].pixels, dtype=np.float64) for c in "RGB")
    luminance = 0.2126 * r + 0.7152 * g + 0.0722 * b
    np.testing.assert_allclose(luminance, 1.0, atol=1e-3)


def test_images_from_other_software_in_the_layout_are_read(tmp_path: Path) -> None:
    """A reflectance image (component T) written by colour-science itself, no labkit header."""
    rng = np.random.default_rng(1)
    wavelengths = np.array([450.0, 500.0, 550.0])
    values = rng.random((6, 8, 3)).astype(np.float32)
    path = tmp_path / "reflectance.exr"
    specification = Specification_Fichet2021(is_emissive=False)
    specification.attributes = []
    write_spectral_image_Fichet2021(
        {"T": (wavelengths, values)},
        str(path),
        "float32",
        specification,
        components_to_RGB_callable=lambda *_: (None, []),
    )
    back = read_spectral_exr(path)
    np.testing.assert_array_equal(back.cube, values)
    np.testing.assert_array_equal(back.wavelengths_nm, wavelengths)


def test_files_in_the_older_labkit_layout_still_read(tmp_path: Path) -> None:
    cube = np.random.default_rng(2).random((5, 6, 2)).astype(np.float32)
    wavelengths = np.array([500.0, 600.0])
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "wavelengths_nm": wavelengths.astype(np.float32),
        "labkit": json.dumps({"format": 1, "kind": "spectral", "wavelengths_nm": [500.0, 600.0]}),
    }
    channels = {"S500.0": cube[:, :, 0].copy(), "S600.0": cube[:, :, 1].copy()}
    path = tmp_path / "old.exr"
    OpenEXR.File(header, channels).write(str(path))
    back = read_spectral_exr(path)
    np.testing.assert_array_equal(back.cube, cube)
    np.testing.assert_array_equal(back.wavelengths_nm, wavelengths)


def test_bad_images_are_refused_and_leave_nothing_behind(tmp_path: Path) -> None:
    path = tmp_path / "spectral.exr"
    write_spectral_exr(path, _image())
    before = path.read_bytes()
    bad = _image()
    bad.cube[3, 4, 2] = np.nan
    with pytest.raises(DataError, match=r"spectral\.exr: channel 'band 552\.5 nm' has 1 NaN"):
        write_spectral_exr(path, bad)
    with pytest.raises(DataError, match="band centres must increase"):
        write_spectral_exr(path, SpectralImage(_image().cube, WAVELENGTHS[::-1]))
    with pytest.raises(DataError, match="one wavelength per band"):
        write_spectral_exr(path, SpectralImage(_image().cube, WAVELENGTHS[:3]))
    assert path.read_bytes() == before, "a refused write must leave the old file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spectral.exr"]

    raw = tmp_path / "raw.exr"
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"raw": np.zeros((4, 4), np.float32)}).write(
        str(raw)
    )
    with pytest.raises(DataError, match=r"raw\.exr: not a spectral EXR"):
        read_spectral_exr(raw)


def test_envi_round_trip_is_exact_and_standard(tmp_path: Path) -> None:
    image = _image()
    header = tmp_path / "cube.hdr"
    data = write_envi(header, image, description="test cube")
    assert data == tmp_path / "cube.img" and data.stat().st_size == image.cube.nbytes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.hdr", "cube.img"]

    opened = envi.open(str(header))  # Spectral Python's own reader
    assert opened.metadata["wavelength units"] == "Nanometers"
    np.testing.assert_array_equal(np.asarray(opened.metadata["wavelength"], float), WAVELENGTHS)
    np.testing.assert_array_equal(np.asarray(opened.load()), image.cube)
    assert opened.metadata["interleave"] == "bsq"

    back = read_envi(header)
    np.testing.assert_array_equal(back.cube, image.cube)
    np.testing.assert_array_equal(back.wavelengths_nm, WAVELENGTHS)
    assert back.labkit["units"] == "raw units per nm"


def test_envi_headers_in_micrometres_convert_and_bad_ones_are_refused(tmp_path: Path) -> None:
    values = np.random.default_rng(3).random((4, 5, 3)).astype(np.float32)
    header = tmp_path / "um.hdr"
    envi.save_image(
        str(header),
        values,
        dtype=np.float32,
        interleave="bil",
        metadata={"wavelength": ["0.45", "0.55", "0.65"], "wavelength units": "Micrometers"},
    )
    back = read_envi(header)
    np.testing.assert_allclose(back.wavelengths_nm, [450.0, 550.0, 650.0], rtol=1e-12)
    np.testing.assert_array_equal(back.cube, values)

    envi.save_image(str(tmp_path / "none.hdr"), values, dtype=np.float32)
    with pytest.raises(DataError, match=r"none\.hdr: the header has no 'wavelength'"):
        read_envi(tmp_path / "none.hdr")
    with pytest.raises(DataError, match="does not exist"):
        read_envi(tmp_path / "missing.hdr")
    with pytest.raises(DataError, match=r"must end in \.hdr"):
        write_envi(tmp_path / "cube.img", _image())


def test_xarray_round_trip_is_exact_and_labelled() -> None:
    image = _image()
    array = image.to_xarray()
    assert array.dims == ("y", "x", "wavelength")
    np.testing.assert_array_equal(array["wavelength"].values, WAVELENGTHS)
    np.testing.assert_array_equal(array["x"].values, np.arange(17))
    assert array.attrs["units"] == "raw units per nm" and array.attrs["wavelength_units"] == "nm"
    assert float(array.sel(wavelength=610.0, y=0, x=0)) == pytest.approx(-2.0)

    back = SpectralImage.from_xarray(array.transpose("wavelength", "x", "y"))
    np.testing.assert_array_equal(back.cube, image.cube)
    np.testing.assert_array_equal(back.wavelengths_nm, WAVELENGTHS)
    assert back.labkit == image.labkit
    with pytest.raises(DataError, match="no 'wavelength' dimension"):
        SpectralImage.from_xarray(array.rename(wavelength="band"))


def test_export_command_converts_both_ways(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    image = _image()
    source = tmp_path / "spectral.exr"
    write_spectral_exr(source, image)
    assert main(["export", str(source), "--to", "envi"]) == 0
    assert "spectral.hdr and spectral.img" in capsys.readouterr().out
    np.testing.assert_array_equal(read_envi(tmp_path / "spectral.hdr").cube, image.cube)

    out = tmp_path / "again.exr"
    assert main(["export", str(tmp_path / "spectral.hdr"), "--to", "exr", "--out", str(out)]) == 0
    again = read_spectral_exr(out)
    np.testing.assert_array_equal(again.cube, image.cube)
    np.testing.assert_array_equal(again.wavelengths_nm, WAVELENGTHS)

    assert main(["export", str(source), "--to", "envi", "--out", str(tmp_path / "x.img")]) == 2
    assert "ENVI files end in .hdr" in capsys.readouterr().err
    assert main(["export", str(source), "--to", "exr"]) == 2
    assert "reads an ENVI header" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda text: text.replace("data type = 4", "data type = 5"), r"is 240 bytes, .*float64"),
        (lambda text: text.replace("bands = 3", "bands = 2"), r"is 240 bytes, .*4×5×2"),
        (lambda text: text.replace("0.45 , ", "").replace("0.45,", ""), "2 wavelengths for 3"),
    ],
)
def test_envi_headers_that_contradict_their_data_are_refused(tmp_path: Path, edit, match):
    values = np.random.default_rng(3).random((4, 5, 3)).astype(np.float32)
    header = tmp_path / "cube.hdr"
    envi.save_image(str(header), values, dtype=np.float32,
                    metadata={"wavelength": ["0.45", "0.55", "0.65"],
                              "wavelength units": "Micrometers"})  # fmt: skip
    header.write_text(edit(header.read_text()))
    with pytest.raises(DataError, match=match):
        read_envi(header)


@pytest.mark.parametrize(
    ("spoil", "match"),
    [
        (
            lambda h: h.with_suffix(".img").unlink(),
            r"cube\.img, the data file of .*cube\.hdr, is missing",
        ),
        (
            lambda h: h.write_text(h.read_text().replace("Micrometers", "Nanometers")),
            r"0\.45–0\.65 nm, read with 'wavelength units' = nanometers\) miss the visible",
        ),
        (
            lambda h: h.write_text(
                h.read_text().replace("0.45", "4.5").replace("0.55", "5.5").replace("0.65", "6.5")
            ),
            r"4500–6500 nm.*'wavelength units'",
        ),
    ],
    ids=["data file missing", "units wrong", "wavelengths ×10"],
)
def test_envi_missing_data_or_unseen_wavelengths_are_named(tmp_path, spoil, match):
    values = np.random.default_rng(3).random((4, 5, 3)).astype(np.float32)
    header = tmp_path / "cube.hdr"
    envi.save_image(str(header), values, dtype=np.float32,
                    metadata={"wavelength": ["0.45", "0.55", "0.65"],
                              "wavelength units": "Micrometers"})  # fmt: skip
    spoil(header)
    with pytest.raises(DataError, match=match):
        read_envi(header)
