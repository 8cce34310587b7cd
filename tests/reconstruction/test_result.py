"""`Reconstruction.save`: the files it writes, their contents, and an atomic log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _problems import RESPONSE

import reconstruction.result
from labkit.errors import DataError
from labkit.io import read_spectral_exr
from labkit.spectra import camera_response
from reconstruction import reconstruct
from reconstruction.result import OUTPUT_FILES

CFA = "GBRG"


def _raw(shape: tuple[int, int] = (32, 32)) -> np.ndarray:
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return 2.0 + np.sin(xx / 5.0) + 0.5 * np.cos(yy / 7.0)


def test_spectral_result_round_trips(tmp_path: Path) -> None:
    result = reconstruct(
        _raw(), cfa=CFA, response=camera_response(RESPONSE), weights="fixed:0.01", patch_px=32
    )
    paths = result.save(tmp_path / "out", provenance={"command": "test", "input": "x.exr"})
    assert [p.name for p in paths.values()] == list(OUTPUT_FILES)
    cube = read_spectral_exr(paths["spectral"])
    np.testing.assert_array_equal(cube.cube, result.spectral)
    np.testing.assert_array_equal(cube.wavelengths_nm, result.wavelengths_nm)
    assert cube.labkit["command"] == "test" and cube.labkit["input"] == "x.exr"
    assert cube.labkit["weights"] == {"requested": "fixed:0.01", "criterion": "fixed",
                                      "values": [0.01]}  # fmt: skip
    log = json.loads(paths["log"].read_text())
    assert log["command"] == "test" and log["outputs"]["preview"] == "preview.png"
    assert (
        log["preview"]["white_balance"] == "grey-world"
        and len(log["preview"]["scene_white_xy"]) == 2
    )
    assert log["patches"]["count"] == result.log["patches"]["count"]


def test_spectral_result_as_xarray_matches_the_saved_file(tmp_path: Path) -> None:
    result = reconstruct(
        _raw(), cfa=CFA, response=camera_response(RESPONSE), weights="fixed:0.01", patch_px=32
    )
    array = result.to_xarray()
    assert array.dims == ("y", "x", "wavelength") and array.shape == result.spectral.shape
    np.testing.assert_array_equal(array["wavelength"].values, result.wavelengths_nm)
    np.testing.assert_array_equal(array.values, result.spectral)
    assert array.attrs["units"] == "raw units per nm"
    saved = read_spectral_exr(result.save(tmp_path)["spectral"]).to_xarray()
    np.testing.assert_array_equal(saved.values, array.values)
    np.testing.assert_array_equal(saved["wavelength"].values, array["wavelength"].values)


def test_colour_result_has_no_spectral_file(tmp_path: Path) -> None:
    result = reconstruct(_raw(), cfa=CFA, latent="colour", weights="fixed:0.01", patch_px=32)
    paths = result.save(tmp_path)
    assert sorted(paths) == ["log", "preview", "raw_colour"]
    assert not (tmp_path / "spectral.exr").exists()
    with pytest.raises(DataError, match="colour latent space: it has no wavelengths"):
        result.to_xarray()


def test_a_failed_write_leaves_no_log(tmp_path: Path, monkeypatch) -> None:
    """The log is written last: a folder without log.json is an incomplete one."""
    result = reconstruct(_raw(), cfa=CFA, latent="colour", weights="fixed:0.01", patch_px=32)

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(reconstruction.result, "write_png", broken)
    with pytest.raises(OSError, match="disk full"):
        result.save(tmp_path)
    assert not (tmp_path / "log.json").exists()
