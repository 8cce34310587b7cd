"""read_mosaic: raw mosaics from labkit, other software's EXR/TIFF/PNG and camera raw files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile
from _raw_files import BLACK, SCALE, WHITE, X_TRANS, frame_dng, real_frame, write_dng
from PIL import Image

from labkit.errors import ConfigError, DataError
from labkit.io import (
    MOSAIC_SUFFIXES,
    RawImage,
    SpectralImage,
    read_mosaic,
    read_raw_exr,
    write_raw_exr,
    write_raw_tiff,
    write_spectral_exr,
)


def _foreign_exr(path: Path, channels: dict[str, np.ndarray], header: dict | None = None) -> Path:
    """An EXR written with the OpenEXR package directly: no labkit attributes."""
    import OpenEXR

    planes = {name: np.ascontiguousarray(plane, np.float32) for name, plane in channels.items()}
    exr_header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File({**exr_header, **(header or {})}, planes).write(str(path))
    return path


@pytest.fixture
def mosaic() -> np.ndarray:
    """A 6×8 float mosaic with distinct values."""
    return (np.arange(48, dtype=np.float32).reshape(6, 8) + 1) / 64


# -- OpenEXR ----------------------------------------------------------------------------
def test_foreign_single_channel_exr_needs_cfa(tmp_path: Path, mosaic: np.ndarray) -> None:
    path = _foreign_exr(tmp_path / "other.exr", {"Y": mosaic})
    image = read_mosaic(path, cfa="GBRG")
    np.testing.assert_array_equal(image.raw, mosaic)
    assert image.raw.dtype == np.float32 and image.cfa == "GBRG"
    assert image.exposure_s is None and image.illumination == "" and image.variance is None
    assert image.labkit["source"] == {
        "file": str(path),
        "reader": "OpenEXR",
        "channel": "Y",
        "cfa_from": "--cfa",
        "scale": "as stored",
    }
    with pytest.raises(DataError, match="does not say its CFA layout; pass --cfa") as error:
        read_mosaic(path)
    assert str(path) in str(error.value) and "\n" not in str(error.value)


def test_foreign_exr_prefers_the_raw_channel_and_its_cfa(tmp_path: Path, mosaic) -> None:
    path = _foreign_exr(
        tmp_path / "two.exr", {"raw": mosaic, "mask": np.zeros_like(mosaic)}, {"cfa": "RGGB"}
    )
    image = read_mosaic(path)
    np.testing.assert_array_equal(image.raw, mosaic)
    assert image.cfa == "RGGB" and image.exposure_s is None
    assert image.labkit["source"]["cfa_from"] == "file"
    assert read_mosaic(path, cfa="RGGB").cfa == "RGGB"
    with pytest.raises(DataError, match=r"CFA layouts disagree: .*two.exr says RGGB, --cfa says"):
        read_mosaic(path, cfa="BGGR")


def test_several_channels_without_raw_are_named(tmp_path: Path, mosaic) -> None:
    path = _foreign_exr(tmp_path / "rgb.exr", {c: mosaic for c in "RGB"})
    with pytest.raises(DataError, match=r"no 'raw' channel and 3 channels \(B, G, R\)"):
        read_mosaic(path, cfa="GBRG")


def test_labkit_raw_exr_reads_as_before(tmp_path: Path, mosaic) -> None:
    path = tmp_path / "hdr.exr"
    variance = mosaic**2
    write_raw_exr(path, RawImage(mosaic, "BGGR", 0.025, "550", 550.0, variance, {"scene": "disks"}))
    image = read_mosaic(path)
    assert _same(image, read_raw_exr(path))
    assert image.cfa == "BGGR" and image.exposure_s == 0.025 and image.wavelength_nm == 550.0
    np.testing.assert_array_equal(image.variance, variance)
    assert "source" not in image.labkit and image.labkit["scene"] == "disks"
    with pytest.raises(DataError, match=r"hdr\.exr says BGGR, --cfa says GBRG"):
        read_mosaic(path, cfa="GBRG")


def _same(a: RawImage, b: RawImage) -> bool:
    np.testing.assert_array_equal(a.raw, b.raw)
    np.testing.assert_array_equal(a.variance, b.variance)
    return (a.cfa, a.exposure_s, a.illumination, a.wavelength_nm, a.labkit) == (
        b.cfa,
        b.exposure_s,
        b.illumination,
        b.wavelength_nm,
        b.labkit,
    )


def test_spectral_exr_is_not_a_mosaic(tmp_path: Path) -> None:
    path = tmp_path / "spectral.exr"
    cube = np.ones((4, 6, 1), np.float32)  # one band: a single channel, still spectral
    write_spectral_exr(path, SpectralImage(cube, np.array([550.0]), {}))
    with pytest.raises(DataError, match=r"no 'raw' channel .* spectral image"):
        read_mosaic(path, cfa="GBRG")


def test_exposure_unknown_is_not_written(tmp_path: Path, mosaic) -> None:
    with pytest.raises(DataError, match="exposure_s must be a positive number of seconds"):
        write_raw_exr(tmp_path / "x.exr", RawImage(mosaic, "GBRG", None, ""))
    assert not (tmp_path / "x.exr").exists()


# -- TIFF and PNG -----------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".png"])
@pytest.mark.parametrize(("dtype", "peak"), [(np.uint8, 255), (np.uint16, 65535)])
def test_integer_mosaics_are_scaled_by_the_container(tmp_path: Path, suffix, dtype, peak) -> None:
    values = np.array([[0, 1, 2, 3], [peak - 3, peak - 2, peak - 1, peak]], dtype=dtype)
    values = np.tile(values, (2, 2))
    path = tmp_path / f"mosaic{suffix}"
    if suffix == ".png":
        Image.fromarray(values).save(path)
    else:
        tifffile.imwrite(path, values, photometric="minisblack")
    image = read_mosaic(path, cfa="GRBG")
    expected = (values.astype(np.float64) / peak).astype(np.float32)
    np.testing.assert_array_equal(image.raw, expected)
    assert image.raw.dtype == np.float32 and image.cfa == "GRBG" and image.exposure_s is None
    assert image.labkit["source"]["scale"].startswith(f"value / {peak}")
    with pytest.raises(DataError, match="pass --cfa"):
        read_mosaic(path)


def test_float_tiff_is_taken_as_stored(tmp_path: Path, mosaic) -> None:
    path = tmp_path / "float.tif"
    tifffile.imwrite(path, mosaic.astype(np.float64) * 1000)
    np.testing.assert_allclose(read_mosaic(path, cfa="RGGB").raw, mosaic * 1000, rtol=1e-7)
    for bad, message in ((np.nan, "1 NaN/Inf pixel"), (-1.0, "1 negative pixel value")):
        broken = mosaic.copy()
        broken[2, 3] = bad
        tifffile.imwrite(path, broken)
        with pytest.raises(DataError, match=message):
            read_mosaic(path, cfa="RGGB")


def test_labkit_raw_tiff_names_its_cfa_and_exposure(tmp_path: Path) -> None:
    path = tmp_path / "frame.tiff"
    counts = np.arange(32, dtype=np.uint16).reshape(4, 8) * 1000
    metadata = {"pixel_format": "BayerRG12", "exposure_s": 0.05, "illumination": "600"}
    write_raw_tiff(path, counts, metadata)
    image = read_mosaic(path)
    assert image.cfa == "RGGB" and image.exposure_s == 0.05 and image.illumination == "600"
    np.testing.assert_array_equal(image.raw, (counts / 65535).astype(np.float32))
    with pytest.raises(DataError, match="CFA layouts disagree"):
        read_mosaic(path, cfa="GBRG")


@pytest.mark.parametrize(
    ("name", "data"),
    [
        ("rgb.tif", np.zeros((4, 6, 3), np.uint8)),
        ("rgba.tiff", np.zeros((4, 6, 4), np.uint16)),
        ("rgb.png", np.zeros((4, 6, 3), np.uint8)),
        ("rgba.png", np.zeros((4, 6, 4), np.uint8)),
    ],
)
def test_colour_images_are_refused(tmp_path: Path, name: str, data: np.ndarray) -> None:
    path = tmp_path / name
    if name.endswith(".png"):
        Image.fromarray(data).save(path)
    else:
        tifffile.imwrite(path, data, photometric="rgb")
    with pytest.raises(DataError, match="demosaiced/colour image, labkit needs the raw Bayer"):
        read_mosaic(path, cfa="GBRG")


@pytest.mark.parametrize("suffix", [".tif", ".png", ".exr"])
@pytest.mark.parametrize("shape", [(5, 8), (6, 7), (1, 1)])
def test_odd_sized_mosaics_are_refused(tmp_path: Path, suffix: str, shape) -> None:
    path = tmp_path / f"odd{suffix}"
    data = np.full(shape, 7, np.uint8)
    if suffix == ".png":
        Image.fromarray(data).save(path)
    elif suffix == ".tif":
        tifffile.imwrite(path, data)
    else:
        _foreign_exr(path, {"raw": data})
    message = f"is not a Bayer mosaic: size {shape[0]}×{shape[1]} px; .*: crop to even dimensions"
    with pytest.raises(DataError, match=message):
        read_mosaic(path, cfa="GBRG")


def test_unsupported_kinds_and_options(tmp_path: Path) -> None:
    jpeg = tmp_path / "photo.jpg"
    jpeg.write_bytes(b"not read")
    with pytest.raises(DataError, match=r"unsupported kind of file '\.jpg'.*\.tiff.*\.dng.*\.nef"):
        read_mosaic(jpeg)
    assert {".exr", ".tif", ".png", ".dng", ".nef", ".cr3", ".arw", ".raf"} <= set(MOSAIC_SUFFIXES)
    with pytest.raises(DataError, match=r"raw image .*missing\.tif does not exist"):
        read_mosaic(tmp_path / "missing.tif", cfa="GBRG")
    with pytest.raises(ConfigError, match="--cfa is 'RGBG'; use one of RGGB, BGGR, GRBG, GBRG"):
        read_mosaic(jpeg, cfa="RGBG")


# -- camera raw files (LibRaw) ----------------------------------------------------------
def test_dng_known_answer_in_the_active_area(tmp_path: Path) -> None:
    """A real frame as 12-bit DN with black 64 and white 4159 inside a 4-px/6-px margin of
    masked pixels (ActiveArea): the visible area, (DN − black) / (white − black)."""
    frame = real_frame()
    rows, cols = frame.shape
    sensor = np.full((rows + 8, cols + 12), WHITE, np.uint16)  # margins LibRaw must drop
    sensor[4 : 4 + rows, 6 : 6 + cols] = frame.astype(np.uint16) * SCALE + BLACK
    extra = (
        (50829, "I", 4, (4, 6, 4 + rows, 6 + cols), True),  # ActiveArea: top, left, bottom, right
        (33434, "2I", 1, (1, 50), True),  # ExposureTime 1/50 s
        (271, "s", 0, "Labkit", True),  # Make
        (272, "s", 0, "Test Rig", True),  # Model
    )
    path = write_dng(tmp_path / "frame.dng", sensor, extra=extra)
    image = read_mosaic(path)
    assert image.cfa == "GBRG" and image.raw.shape == (rows, cols)
    assert image.raw.dtype == np.float32
    expected = frame.astype(np.float64) * SCALE / (WHITE - BLACK)  # frame · 16 / 4095
    np.testing.assert_allclose(image.raw, expected, rtol=6e-8, atol=0)
    assert image.raw.max() == pytest.approx(255 * 16 / 4095) and image.raw.min() >= 0
    assert image.exposure_s == 0.02
    source = image.labkit["source"]
    assert source["file"] == str(path) and source["reader"].startswith("LibRaw ")
    assert source["black_levels"] == [[BLACK, BLACK], [BLACK, BLACK]]
    assert source["white_level"] == WHITE
    assert source["camera_make"] == "Labkit" and source["camera_model"] == "Test Rig"
    area = source["visible_area"]
    assert (area["top"], area["left"], area["rows"], area["cols"]) == (4, 6, rows, cols)
    assert (area["sensor_rows"], area["sensor_cols"]) == (rows + 8, cols + 12)


def test_dng_black_level_per_cfa_channel(tmp_path: Path) -> None:
    """BlackLevel 60, 62, 64, 66 repeating per 2×2 position: each is subtracted where it
    applies and the white level's distance from it divides."""
    frame = real_frame()[:64, :96]
    levels = np.array([[60, 62], [64, 66]])
    counts = frame.astype(np.uint16) * SCALE + np.tile(levels, (32, 48)).astype(np.uint16)
    path = write_dng(tmp_path / "black.dng", counts, black=(60, 62, 64, 66))
    image = read_mosaic(path, cfa="GBRG")
    expected = frame.astype(np.float64) * SCALE / (WHITE - np.tile(levels, (32, 48)))
    np.testing.assert_allclose(image.raw, expected, rtol=6e-8, atol=0)
    assert image.labkit["source"]["black_levels"] == levels.tolist()
    assert image.exposure_s is None


def test_values_below_black_are_clipped_and_cfa_checked(tmp_path: Path) -> None:
    counts = np.full((24, 24), BLACK + 100, np.uint16)  # LibRaw opens ≥ 22×22 px only
    counts[0, 0] = BLACK - 10
    path = write_dng(tmp_path / "rggb.dng", counts, cfa="RGGB")
    image = read_mosaic(path)
    assert image.cfa == "RGGB" and image.raw[0, 0] == 0
    assert image.raw[1, 1] == pytest.approx(100 / (WHITE - BLACK), rel=1e-7)
    with pytest.raises(DataError, match=r"rggb.dng says RGGB, --cfa says GBRG"):
        read_mosaic(path, cfa="GBRG")


def test_files_libraw_cannot_read_are_one_line(tmp_path: Path) -> None:
    path = tmp_path / "x.nef"
    path.write_text("this is not a photograph\n")
    with pytest.raises(DataError) as error:
        read_mosaic(path)
    message = str(error.value)
    assert message.startswith(f"{path} is not a camera raw image LibRaw can read")
    assert "\n" not in message


def test_x_trans_and_non_bayer_sensors_are_refused(tmp_path: Path) -> None:
    frame = real_frame()[:36, :48].astype(np.uint16) * SCALE + BLACK
    path = write_dng(tmp_path / "xtrans.dng", frame, pattern=X_TRANS)
    with pytest.raises(DataError, match=r"repeats every 6×6 px .*labkit needs a 2×2 Bayer"):
        read_mosaic(path)

    linear = tmp_path / "linear.dng"  # LinearRaw: three samples per pixel, no CFA
    tifffile.imwrite(
        linear,
        np.stack([frame] * 3, axis=-1),
        photometric=34892,
        extratags=[
            (50706, "B", 4, (1, 4, 0, 0), True),
            (50708, "s", 0, "labkit linear", True),
            (50717, "H", 1, (WHITE,), True),
        ],
    )
    with pytest.raises(DataError, match="non-Bayer or already demosaiced"):
        read_mosaic(linear)


def test_dng_of_the_whole_frame_round_trips(tmp_path: Path) -> None:
    """frame_dng (the CLI tests' builder) gives back frame · 16 / 4095 exactly as float32."""
    frame = real_frame()
    image = read_mosaic(frame_dng(tmp_path / "f.dng", frame))
    expected = (frame.astype(np.float64) * SCALE / (WHITE - BLACK)).astype(np.float32)
    np.testing.assert_array_equal(image.raw, expected)
