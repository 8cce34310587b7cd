"""labkit calibrate vignetting|dispersion, labkit dispersion eval, labkit correct warp."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _helpers import write_rig

from calibration.dispersion_model import load_dispersion_model
from calibration.multispectral import green_bilinear
from labkit.cli import main
from labkit.hdr.truth import simulated_hdr_images
from labkit.io import SpectralImage, read_spectral_exr, write_raw_exr, write_spectral_exr
from labkit.rig import load_rig
from labkit.sim import SimulatedRig

SHAPE = (192, 256)


@pytest.fixture(scope="module")
def hdr_folder(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path):
    """(rig file, HDR folder) of the disk scene from simulated merged images (no session)."""
    folder = tmp_path_factory.mktemp("cli-dispersion")
    rig_file = write_rig(
        folder,
        sim_rig_path,
        **{
            "sim.sensor.width": SHAPE[1],
            "sim.sensor.height": SHAPE[0],
            "sim.scenes.disks": {"type": "disks", "radius_px": 8, "pitch_px": 32},
            "plan.exposures_s": {"unfiltered": [0.003], "filtered": [0.025, 0.1, 0.4, 1.6]},
        },
    )
    sim = SimulatedRig(load_rig(rig_file))
    names = [n for n in sim.rig.slider.illumination_names()]
    images = simulated_hdr_images(sim, "disks", names, rng=np.random.default_rng(3))
    for image in images:
        write_raw_exr(folder / "hdr" / "disks" / f"{image.illumination}.exr", image)
    return rig_file, folder / "hdr"


def test_calibrate_dispersion_checks_the_shot_against_the_chart(hdr_folder, tmp_path, capsys):
    """The simulated chart has 8 px disks 32 px apart: a chart made for that passes, one made
    for 14 px disks 64 px apart is named as shot from 2× farther (a warning; the model is
    still written)."""
    rig_file, hdr = hdr_folder
    for radius, pitch, warned in ((8, 32, False), (14, 64, True)):
        chart = tmp_path / f"chart{radius}"
        assert main(["target", "--out", str(chart), "--pixel-um", "3.45", "--focal-mm", "8",
                     "--distance-m", "0.3", "--radius-px", str(radius), "--pitch-px",
                     str(pitch)]) == 0  # fmt: skip
        capsys.readouterr()
        out = tmp_path / f"model{radius}.yaml"
        assert main(["calibrate", "dispersion", str(hdr), "--rig", str(rig_file), "--out",
                     str(out), "--workers", "1", "--no-plots",
                     "--target", str(chart / "chart.yaml")]) == 0  # fmt: skip
        printed = capsys.readouterr().out
        assert "disks in the shot: radius " in printed and out.is_file()
        assert ("2.00× farther from the chart" in printed) is warned, printed


def test_calibrate_dispersion_eval_and_warp(hdr_folder, tmp_path: Path, capsys):
    rig_file, hdr = hdr_folder
    out = tmp_path / "model.yaml"
    assert main(["calibrate", "dispersion", str(hdr), "--rig", str(rig_file), "--out",
                 str(out), "--workers", "1"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "left out" in printed and "593.0" in printed and "by the images" in printed
    for suffix in (".yaml", ".keypoints.csv", ".png", ".residuals.png"):
        assert out.with_suffix(suffix).stat().st_size > 0
    model = load_dispersion_model(out)
    assert model.variables == "xylambda" and model.direction == "from_reference"

    # `labkit dispersion eval` prints what the Python API returns
    assert main(["dispersion", "eval", str(out), "--x", "20", "230", "--y", "30",
                 "--wavelength", "450"]) == 0  # fmt: skip
    printed = capsys.readouterr().out.splitlines()
    assert printed[1].startswith("# calibrated domain: 4")  # the bands' range, nm
    rows = [line.split() for line in printed[3:]]
    dx, dy = model.within_domain().displacement(np.array([20.0, 230.0]), 30.0, 450.0)
    assert [float(r[4]) for r in rows] == pytest.approx(dx, abs=1e-4)
    assert [float(r[5]) for r in rows] == pytest.approx(dy, abs=1e-4)

    # beyond the calibrated bands: clamped to the range's end, and said so
    lo, hi = model.region.wavelength_nm
    assert main(["dispersion", "eval", str(out), "--x", "128", "--y", "96",
                 "--wavelength", "380"]) == 0  # fmt: skip
    row = capsys.readouterr().out.splitlines()[3]
    assert f"clamped to (128.0, 96.0, {lo:.1f} nm)" in row
    edge = [float(v) for v in model.displacement(128.0, 96.0, lo)]
    assert [float(v) for v in row.split()[4:6]] == pytest.approx(edge, abs=1e-4)
    assert main(["dispersion", "eval", str(out), "--x", "128", "--y", "96",
                 "--wavelength", "380", "--extrapolation", "allow"]) == 0  # fmt: skip
    row = capsys.readouterr().out.splitlines()[3]
    assert row.endswith("extrapolated")
    fitted = [float(v) for v in model.displacement(128.0, 96.0, 380.0)]
    assert [float(v) for v in row.split()[4:6]] == pytest.approx(fitted, abs=1e-4)
    assert main(["dispersion", "eval", str(out), "--x", "128", "--y", "96",
                 "--wavelength", "380", "--extrapolation", "refuse"]) == 2  # fmt: skip
    assert "lies outside the domain" in capsys.readouterr().err

    # `labkit dispersion show` prints the domain and how each filter entered it
    assert main(["dispersion", "show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert f"domain       {lo:.1f}–{hi:.1f} nm; keypoints over x" in shown
    assert "one keypoint spacing" in shown and "% of the image lies beyond it" in shown
    assert "   400 " in shown and "no: " in shown and "degree_lambda" in shown

    # `labkit dispersion crop`: the sensor's model on a crop; eval there = eval on the sensor
    cropped = tmp_path / "crop.yaml"
    assert main(["dispersion", "crop", str(out), "--origin", "40,64", "--shape", "96,128",
                 "--out", str(cropped)]) == 0  # fmt: skip
    assert "on the 128×96 px crop at (row, col) = (40, 64)" in capsys.readouterr().out
    crop_model = load_dispersion_model(cropped)
    assert crop_model.image_shape == (96, 128)
    np.testing.assert_array_equal(
        np.stack(crop_model.displacement(np.array([10.0, 100.0]), np.array([5.0, 90.0]), 520.0)),
        np.stack(model.displacement(np.array([74.0, 164.0]), np.array([45.0, 130.0]), 520.0)),
    )
    assert main(["dispersion", "show", str(cropped)]) == 0
    assert "crop         of the sensor's [192, 256] px" in capsys.readouterr().out
    assert main(["dispersion", "crop", str(out), "--origin", "160,0", "--shape", "96,128",
                 "--out", str(tmp_path / "outside.yaml")]) == 2  # fmt: skip
    assert "does not lie inside the model's 192×256 px image" in capsys.readouterr().err
    assert not (tmp_path / "outside.yaml").exists()
    assert main(["dispersion", "crop", str(out), "--origin", "4", "--shape", "96,128",
                 "--out", str(tmp_path / "bad.yaml")]) == 2  # fmt: skip
    assert "--origin is '4'; expected two whole numbers" in capsys.readouterr().err

    # warping a multispectral image of the disks aligns its bands with the reference
    bands = {b: read_band(hdr, b) for b in ("450", "600")}
    wavelengths = [model.provenance["bands_table"][i]["wavelength_nm"] for i in (1, 4)]
    cube = np.stack([bands["450"], bands["600"]], axis=-1).astype(np.float32)
    spectral = tmp_path / "multi.exr"
    write_spectral_exr(spectral, SpectralImage(cube, np.array(wavelengths), {}))
    corrected = tmp_path / "corrected.exr"
    assert main(["correct", "warp", str(spectral), "--model", str(out), "--out",
                 str(corrected)]) == 0  # fmt: skip
    assert "nm (calibrated" not in capsys.readouterr().out  # every band inside the range
    warped = read_spectral_exr(corrected).cube
    before = _misalignment(cube[..., 0], cube[..., 1])
    after = _misalignment(warped[..., 0], warped[..., 1])
    # 0.05 px of the remainder is Bayer aliasing of the 32-px disk lattice
    assert before > 0.5 and after < 0.08, (before, after)

    # a band beyond the calibrated range is clamped, and the output says so
    wide = tmp_path / "wide.exr"
    write_spectral_exr(wide, SpectralImage(cube, np.array([380.0, wavelengths[1]]), {}))
    assert main(["correct", "warp", str(wide), "--model", str(out), "--out",
                 str(tmp_path / "wide-corrected.exr")]) == 0  # fmt: skip
    assert "380.0 → " in capsys.readouterr().out
    header = read_spectral_exr(tmp_path / "wide-corrected.exr").labkit
    assert header["dispersion_domain"]["outside_nm"] == [380.0]
    assert "outside the domain" in header["warnings"][0]


def read_band(hdr: Path, name: str) -> np.ndarray:
    from labkit.io import read_raw_exr

    image = read_raw_exr(hdr / "disks" / f"{name}.exr")
    green = green_bilinear(image.raw, image.cfa)
    return green / np.median(green)


def _misalignment(band: np.ndarray, reference: np.ndarray) -> float:
    """RMS patch-wise shift between two images (sub-pixel registration), px."""
    from calibration.registration import patch_shifts

    shifts = patch_shifts(reference, band, max_error=1.0, min_texture=0.0)
    pick = shifts.accepted
    return float(np.sqrt(np.mean(shifts.dx[pick] ** 2 + shifts.dy[pick] ** 2)))


def test_effective_wavelengths_need_a_rig(hdr_folder, tmp_path: Path, capsys):
    _, hdr = hdr_folder
    assert main(["calibrate", "dispersion", str(hdr), "--out", str(tmp_path / "m.yaml")]) == 2
    error = capsys.readouterr().err
    assert "--rig" in error and "--wavelengths nominal" in error
    assert not (tmp_path / "m.yaml").exists()


def test_unknown_reference_band_is_named(hdr_folder, tmp_path: Path, capsys):
    rig_file, hdr = hdr_folder
    code = main(["calibrate", "dispersion", str(hdr), "--rig", str(rig_file), "--reference",
                 "610", "--out", str(tmp_path / "m.yaml")])  # fmt: skip
    assert code == 2
    error = capsys.readouterr().err
    assert "610" in error and "600 (600 nm)" in error


def test_scene_without_disks_is_named(hdr_folder, tmp_path: Path, capsys):
    rig_file, hdr = hdr_folder
    flat = tmp_path / "hdr"
    from labkit.io import read_raw_exr

    for name in ("500", "550", "600"):
        image = read_raw_exr(hdr / "disks" / f"{name}.exr")
        blank = replace(image, raw=np.full_like(image.raw, 0.5))
        write_raw_exr(flat / "flat" / f"{name}.exr", blank)
    code = main(["calibrate", "dispersion", str(flat), "--scene", "flat", "--rig",
                 str(rig_file), "--out", str(tmp_path / "m.yaml")])  # fmt: skip
    assert code == 2
    error = capsys.readouterr().err
    assert "no calibration disks" in error and "flat" in error


def test_calibrate_vignetting_cli(hdr_folder, tmp_path: Path, capsys):
    _, hdr = hdr_folder
    out = tmp_path / "vignetting.yaml"
    assert main(["calibrate", "vignetting", str(hdr), "--illumination", "550", "--out",
                 str(out)]) == 0  # fmt: skip
    assert "disk-pattern background" in capsys.readouterr().out
    assert out.with_suffix(".png").stat().st_size > 0
    bad_mask = tmp_path / "mask.npy"
    np.save(bad_mask, np.ones((10, 10), bool))
    code = main(["calibrate", "vignetting", str(hdr), "--illumination", "550", "--mask",
                 str(bad_mask), "--out", str(tmp_path / "v2.yaml")])  # fmt: skip
    assert code == 2
    assert "(10, 10)" in capsys.readouterr().err
