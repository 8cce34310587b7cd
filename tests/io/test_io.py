"""Files: atomic writes never leave partial files; raw TIFF round-trips; previews."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.io import (
    atomic_write,
    raw_preview,
    read_raw_tiff,
    to_display,
    write_png,
    write_raw_tiff,
)


def test_atomic_write_replaces_only_on_success(tmp_path: Path) -> None:
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_write(target) as handle:
        handle.write(b"new but half")
        raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"old", "a failed write must leave the old file untouched"
    assert list(tmp_path.iterdir()) == [target], "no temporary file may be left behind"
    with atomic_write(target) as handle:
        handle.write(b"new")
    assert target.read_bytes() == b"new"


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_raw_tiff_round_trip_with_metadata(tmp_path: Path, dtype: type) -> None:
    rng = np.random.default_rng(3)
    image = rng.integers(0, np.iinfo(dtype).max, size=(48, 64), dtype=dtype)
    meta = {"exposure_s": np.float64(0.025), "scene": "disks", "frame_id": np.int64(7)}
    write_raw_tiff(tmp_path / "f.tiff", image, meta)
    back, read_meta = read_raw_tiff(tmp_path / "f.tiff")
    assert back.dtype == dtype and np.array_equal(back, image), "TIFF must be lossless"
    assert read_meta == {"exposure_s": 0.025, "scene": "disks", "frame_id": 7}


def test_raw_tiff_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="2-D uint8/uint16"):
        write_raw_tiff(tmp_path / "f.tiff", np.zeros((4, 4), np.float32))
    (tmp_path / "corrupt.tiff").write_bytes(b"II*\x00garbage")
    with pytest.raises(DataError, match=r"corrupt\.tiff is not a readable TIFF"):
        read_raw_tiff(tmp_path / "corrupt.tiff")
    with pytest.raises(DataError, match="does not exist"):
        read_raw_tiff(tmp_path / "missing.tiff")


def test_preview_of_a_grey_mosaic_is_neutral_and_normalised() -> None:
    raw = np.full((64, 80), 1032, dtype=np.uint16)  # flat grey 1000 DN over black level 32
    image = raw_preview(raw, "GBRG", black_level=32)
    assert image.shape == (64, 80, 3) and image.dtype == np.uint8
    assert np.all(image == 255), "a flat field normalises to white"


def test_display_downsampling_and_png(tmp_path: Path) -> None:
    linear = np.zeros((200, 300, 3), np.float32)
    linear[:, 150:] = 1.0
    shown = to_display(linear, max_side=100)
    assert shown.shape == (66, 100, 3), "3× block-averaged to fit 100 px"
    assert shown[0, 0, 0] == 0 and shown[0, -1, 0] == 255
    write_png(tmp_path / "p.png", shown)
    from PIL import Image

    assert np.array_equal(np.asarray(Image.open(tmp_path / "p.png")), shown)


def test_atomic_files_get_the_usual_mode_not_mkstemps_0600(tmp_path) -> None:
    import stat

    from labkit.io.atomic import _UMASK, write_text_atomic

    write_text_atomic(tmp_path / "note.txt", "hello")
    assert stat.S_IMODE((tmp_path / "note.txt").stat().st_mode) == 0o666 & ~_UMASK
    assert (tmp_path / "note.txt").read_text() == "hello"


def test_rgb_exr_is_labelled_rgb_whatever_provenance_it_carries(tmp_path: Path) -> None:
    """`labkit correct warp` passes a raw image's provenance (kind: raw) along; the RGB
    file must still say kind: rgb, and its pixels come back exactly."""
    from labkit.io import read_rgb_exr, write_rgb_exr
    from labkit.io.exr import read_exr, read_provenance

    rgb = np.random.default_rng(0).random((6, 8, 3)).astype(np.float32)
    path = tmp_path / "rgb.exr"
    write_rgb_exr(path, rgb, {"kind": "raw", "format": "old", "cfa": "GBRG"})
    header, _ = read_exr(path)
    provenance = read_provenance(path, header)
    assert provenance["kind"] == "rgb" and provenance["cfa"] == "GBRG"
    assert provenance["format"] != "old"
    np.testing.assert_array_equal(read_rgb_exr(path), rgb)


def _exr(path: Path) -> Path:
    from labkit.io.exr import RawImage, write_raw_exr

    raw = np.random.default_rng(1).random((40, 48)).astype(np.float32)
    write_raw_exr(path, RawImage(raw, "GBRG", 0.01, "unfiltered", None))
    return path


def test_a_truncated_exr_is_called_truncated_without_library_noise(tmp_path, capfd):
    from labkit.io.exr import read_exr, read_exr_header

    data = _exr(tmp_path / "whole.exr").read_bytes()
    read_exr(tmp_path / "whole.exr")
    for cut in (len(data) - 10, len(data) // 2, 400):
        (tmp_path / "cut.exr").write_bytes(data[:cut])
        with pytest.raises(DataError, match=r"cut\.exr is truncated"):
            read_exr(tmp_path / "cut.exr")
        with pytest.raises(DataError, match=r"cut\.exr is truncated"):
            read_exr_header(tmp_path / "cut.exr")
    assert capfd.readouterr().err == ""  # OpenEXR printed nothing: it was never reached


@pytest.mark.parametrize(
    ("content", "match"),
    [(b"II*\x00" + bytes(64), r"it is a TIFF file \(\.tif\)"),
     (b"\x89PNG\r\n" + bytes(64), "it is a PNG file"),
     (b"", "it does not start like one")],
)  # fmt: skip
def test_a_file_that_is_not_exr_says_what_it_is(tmp_path, content, match):
    from labkit.io.exr import read_exr

    (tmp_path / "x.exr").write_bytes(content)
    with pytest.raises(DataError, match=rf"x\.exr is not an OpenEXR file \({match}"):
        read_exr(tmp_path / "x.exr")


def test_a_folder_where_a_file_goes_is_called_a_folder(tmp_path):
    from calibration import load_dispersion_model
    from labkit.errors import ConfigError
    from labkit.io import read_mosaic
    from labkit.io.envi import read_envi
    from labkit.io.exr import read_exr

    (tmp_path / "d.exr").mkdir()
    (tmp_path / "d.hdr").mkdir()
    with pytest.raises(DataError, match=r"d\.exr is a folder; give a raw image file"):
        read_mosaic(tmp_path / "d.exr")
    with pytest.raises(DataError, match=r"d\.exr is a folder; give an EXR file"):
        read_exr(tmp_path / "d.exr")
    with pytest.raises(DataError, match=r"d\.hdr is a folder"):
        read_envi(tmp_path / "d.hdr")
    with pytest.raises(ConfigError, match=r"dispersion model .*d\.exr is a folder"):
        load_dispersion_model(tmp_path / "d.exr")


def test_spectral_preview_shows_grey_under_a_coloured_light_as_grey() -> None:
    """Grey patches (reflectances 0.2, 0.5, 0.9) under a green-heavy light: grey-world
    adaptation shows them neutral; without it the light's green tints them."""
    from labkit.io import spectral_preview

    wavelengths = np.arange(400.0, 701.0, 10.0)
    light = 1.0 + 2.0 * np.exp(-0.5 * ((wavelengths - 545.0) / 25.0) ** 2)  # a lamp's green line
    reflectance = np.repeat([0.2, 0.5, 0.9], 8)[None, :, None]
    cube = np.broadcast_to(reflectance * light, (6, 24, wavelengths.size))
    balanced = spectral_preview(cube, wavelengths)
    rgb = balanced.image.reshape(-1, 3).astype(int)
    assert np.abs(rgb - rgb.mean(axis=1, keepdims=True)).max() <= 2
    assert balanced.white_balance == "grey-world"
    _, y = balanced.scene_white_xy
    assert y > 0.36  # the light's chromaticity, greener than D65 (0.3127, 0.3290)
    tinted = spectral_preview(cube, wavelengths, white_balance=False).image.reshape(-1, 3)
    assert np.all(tinted[:, 1].astype(int) - tinted[:, 0] > 10)
    assert np.all(tinted[:, 1].astype(int) - tinted[:, 2] > 10)
