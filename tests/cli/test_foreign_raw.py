"""labkit reconstruct / evaluate / correct warp on raw images other software wrote."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
from _helpers import lens_model_file
from _raw_files import BLACK, SCALE, WHITE, X_TRANS, frame_dng, real_frame, write_dng

from calibration.keypoints import DispersionKeypoints
from calibration.polynomial import fit_polynomial_model
from labkit.cfa import mosaic
from labkit.cli import main
from labkit.data import real_colorchecker
from labkit.io import read_rgb_exr, read_spectral_exr

RESPONSE = "Nikon 5100 (NPL)"
CROP = (slice(100, 164), slice(200, 264))  # even offsets keep the frame's GBRG phase


def _foreign_exr(path: Path, plane: np.ndarray) -> Path:
    """One channel ``Y``, none of labkit's attributes (as other software writes it)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": np.ascontiguousarray(plane, np.float32)}).write(str(path))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 64×64 DNG and TIFF of a real frame, and files that are not Bayer mosaics."""
    folder = tmp_path_factory.mktemp("foreign-raw")
    frame = real_frame()
    small = frame[CROP]
    tiff = folder / "frame.tif"
    tifffile.imwrite(tiff, frame, photometric="minisblack")
    small_tiff = folder / "small.tif"
    tifffile.imwrite(small_tiff, small, photometric="minisblack")
    colour = folder / "colour.tif"
    tifffile.imwrite(colour, np.zeros((64, 64, 3), np.uint8), photometric="rgb")
    odd = folder / "odd.tif"
    tifffile.imwrite(odd, small[:63], photometric="minisblack")
    text = folder / "x.nef"
    text.write_text("not a raw file\n")
    counts = small.astype(np.uint16) * SCALE + BLACK
    return {
        "dng": frame_dng(folder / "frame.dng", small),
        "tiff": tiff,
        "small_tiff": small_tiff,
        "exr": _foreign_exr(folder / "other.exr", small / 255.0),
        "colour": colour,
        "odd": odd,
        "text": text,
        "xtrans": write_dng(folder / "xtrans.dng", counts[:60, :60], pattern=X_TRANS),
    }


def test_reconstruct_a_dng(files, tmp_path: Path, capsys) -> None:
    """CFA, levels and area from the DNG; a finite spectral image; exposure unknown → null."""
    out = tmp_path / "recon"
    args = ["reconstruct", str(files["dng"]), "--response", RESPONSE, "--bands",
            "450,550,650", "--weights", "fixed:0.01", "--patch-px", "32", "--quiet",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0, capsys.readouterr().err
    assert "reconstructed 64×64 px → 3 bands 450–650 nm" in capsys.readouterr().out
    spectral = read_spectral_exr(out / "spectral.exr")
    assert spectral.cube.shape == (64, 64, 3) and np.all(np.isfinite(spectral.cube))
    assert spectral.cube.max() > 0
    raw = spectral.labkit["raw"]
    assert raw["cfa"] == "GBRG" and raw["exposure_s"] is None and raw["shape"] == [64, 64]
    assert raw["labkit"]["source"]["white_level"] == WHITE
    assert raw["labkit"]["source"]["black_levels"] == [[BLACK, BLACK], [BLACK, BLACK]]
    log = json.loads((out / "log.json").read_text())
    assert log["arguments"]["cfa"] is None and log["input"] == str(files["dng"])


def test_reconstruct_a_tiff_takes_the_rigs_cfa(files, sim_rig_path: Path, tmp_path: Path):
    """A TIFF names no layout: --rig supplies it (GBRG), and --cfa must agree with the rig."""
    out = tmp_path / "recon"
    args = ["reconstruct", str(files["small_tiff"]), "--rig", str(sim_rig_path), "--latent",
            "colour", "--weights", "fixed:0.01", "--patch-px", "32", "--quiet"]  # fmt: skip
    assert main([*args, "--out", str(out)]) == 0
    colour = read_rgb_exr(out / "raw_colour.exr")
    assert colour.shape == (64, 64, 3) and np.all(np.isfinite(colour))
    raw = _provenance(out / "raw_colour.exr")["raw"]
    assert raw["cfa"] == "GBRG" and raw["labkit"]["source"]["cfa_from"] == str(sim_rig_path)
    assert raw["labkit"]["source"]["scale"].startswith("value / 255")
    refused = tmp_path / "refused"
    assert main([*args, "--cfa", "RGGB", "--out", str(refused)]) == 2
    assert not refused.exists()


def _provenance(path: Path) -> dict:
    """The ``labkit`` header attribute of an EXR written by labkit."""
    import OpenEXR

    with OpenEXR.File(str(path), header_only=True) as exr:
        return json.loads(exr.header()["labkit"])


def _run(argv: list[str], capsys) -> str:
    """Exit status 2 and exactly one line on stderr; returns that line."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("labkit: error: ") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize(
    ("name", "options", "message"),
    [
        ("text", [], "{text} is not a camera raw image LibRaw can read"),
        ("xtrans", [], "{xtrans}: its colour filter pattern repeats every 6×6 px"),
        ("colour", ["--cfa", "GBRG"], "demosaiced/colour image, labkit needs the raw Bayer"),
        ("odd", ["--cfa", "GBRG"], "{odd} is not a Bayer mosaic: size 63×64 px"),
        ("exr", [], "{exr} does not say its CFA layout; pass --cfa"),
        ("small_tiff", [], "{small_tiff} does not say its CFA layout; pass --cfa"),
        ("dng", ["--cfa", "RGGB"], "CFA layouts disagree: {dng} says GBRG, --cfa says RGGB"),
    ],
)
def test_bad_raw_input_is_one_line_and_writes_nothing(
    files, tmp_path: Path, capsys, name: str, options: list[str], message: str
) -> None:
    out = tmp_path / "out"
    names = {key: str(path) for key, path in files.items()}
    expected = message.format(**names)
    argv = ["reconstruct", names[name], "--response", RESPONSE, *options, "--out", str(out)]
    assert expected in _run(argv, capsys)
    assert not out.exists()
    if name in ("text", "colour", "exr"):
        assert expected in _run(["evaluate", names[name], *options, "--out", str(out)], capsys)
        assert not out.exists()


def test_reconstruct_module_entry_point_on_a_bad_file(files, tmp_path: Path) -> None:
    """``python -m labkit reconstruct BAD …``: exit status 2, one stderr line, no DIR."""
    import subprocess
    import sys

    out = tmp_path / "out"
    argv = [sys.executable, "-m", "labkit", "reconstruct", str(files["text"]), "--response",
            RESPONSE, "--out", str(out)]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "LibRaw can read" in done.stderr, done.stderr
    assert not out.exists()


def test_evaluate_a_tiff_mosaic(files, tmp_path: Path, capsys) -> None:
    """The real frame as a plain TIFF with --cfa GBRG and the chart's label image."""
    out = tmp_path / "eval"
    labels = real_colorchecker() / "labels.png"
    argv = ["evaluate", str(files["tiff"]), "--cfa", "GBRG", "--baselines", "bilinear",
            "--labels", str(labels), "--out", str(out)]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    result = json.loads((out / "evaluation.json").read_text())
    assert result["raw"] == str(files["tiff"]) and list(result["methods"]) == ["bilinear"]
    edge = result["methods"]["bilinear"]["residual_aberration"]["edge"]["rmse"]
    assert set(edge) == {"R", "G", "B"} and all(np.isfinite(v) for v in edge.values())
    assert (out / "bilinear.png").is_file()


def _colour_model(path: Path, shape: tuple[int, int], shift_px: float) -> Path:
    """A colour-channel model (from_reference): Red is `shift_px` to the right of Green."""
    gy, gx = np.mgrid[4 : shape[0] - 4 : 8, 4 : shape[1] - 4 : 8].astype(float)
    x, y = gx.ravel(), gy.ravel()
    keypoints = DispersionKeypoints(
        x, y, np.full(x.size, shift_px), np.zeros(x.size), reference="G", image_shape=shape,
        channel=np.full(x.size, "R"),
    )  # fmt: skip
    return fit_polynomial_model(keypoints, max_degree_xy=1, folds=2).save(path)


def test_correct_warp_a_foreign_exr(tmp_path: Path, capsys) -> None:
    """A linear Red ramp, moved 1 px by the model: Red at x becomes the ramp at x + 1
    (bilinear demosaicing and warping are exact on linear ramps), Green and Blue stay."""
    shape = (64, 64)
    xx = np.broadcast_to(np.arange(shape[1], dtype=float), shape)
    colour = np.stack([0.2 + 0.005 * xx, np.full(shape, 0.5), np.full(shape, 0.3)], axis=-1)
    image = _foreign_exr(tmp_path / "other.exr", mosaic(colour, "GBRG"))
    model = _colour_model(tmp_path / "colour.yaml", shape, 1.0)
    out = tmp_path / "warped.exr"
    argv = ["correct", "warp", str(image), "--model", str(model), "--out", str(out)]
    assert "does not say its CFA layout; pass --cfa" in _run(argv, capsys)
    assert not out.exists()
    assert main([*argv, "--cfa", "GBRG"]) == 0
    rgb = read_rgb_exr(out)
    inner = (slice(2, -2), slice(2, -3))
    np.testing.assert_allclose(rgb[..., 0][inner], 0.2 + 0.005 * (xx[inner] + 1), atol=1e-4)
    np.testing.assert_allclose(rgb[..., 1][inner], 0.5, atol=1e-6)
    np.testing.assert_allclose(rgb[..., 2][inner], 0.3, atol=1e-6)
    assert out.with_suffix(".png").is_file()


def test_correct_warp_still_takes_spectral_exrs(tmp_path: Path, capsys) -> None:
    """A spectral EXR is no mosaic: its bands are warped (a flat cube stays flat); --cfa is
    refused for it."""
    from labkit.io import SpectralImage, write_spectral_exr

    shape = (48, 64)
    model_path = lens_model_file(tmp_path / "spectral.yaml", shape)
    image = tmp_path / "cube.exr"
    cube = np.full((*shape, 2), 0.25, np.float32)
    write_spectral_exr(image, SpectralImage(cube, np.array([500.0, 600.0]), {}))
    out = tmp_path / "warped.exr"
    argv = ["correct", "warp", str(image), "--model", str(model_path), "--out", str(out)]
    assert main(argv) == 0
    assert "warped 2 bands" in capsys.readouterr().out
    warped = read_spectral_exr(out)
    np.testing.assert_array_equal(warped.wavelengths_nm, [500.0, 600.0])
    np.testing.assert_allclose(warped.cube, 0.25, rtol=1e-6)
    refused = tmp_path / "refused.exr"
    argv = ["correct", "warp", str(image), "--cfa", "GBRG", "--model", str(model_path),
            "--out", str(refused)]  # fmt: skip
    assert "--cfa applies to raw mosaics only" in _run(argv, capsys)
    assert not refused.exists()
