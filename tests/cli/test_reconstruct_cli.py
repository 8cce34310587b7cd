"""labkit reconstruct: known answers on small simulated raws, outputs, one-line errors."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from _helpers import lens_model_file
from PIL import Image

from labkit.cfa import mosaic
from labkit.cli import build_parser, main
from labkit.io import RawImage, SpectralImage, read_spectral_exr, write_raw_exr, write_spectral_exr
from labkit.io.output_folder import RUN_MANIFEST
from labkit.spectra import camera_response
from labkit.spectra.datasets import write_response_csv
from reconstruction import PRIORS

SHAPE = (64, 96)
BANDS = "400,450,500,550,600,650,700"
GREY = np.array([0.3, 0.5, 0.2])


def _read_rgb_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = exr.channels()
        return np.stack([np.asarray(channels[c].pixels) for c in "RGB"], axis=-1)


def _smooth_colour(shape: tuple[int, int] = SHAPE) -> np.ndarray:
    """A smooth positive raw-colour image: a horizontal colour wave on a vertical ramp."""
    yy, xx = np.mgrid[: shape[0], : shape[1]] / np.array(shape)[:, None, None]
    wave = np.sin(2 * np.pi * xx)[..., None] * np.array([1.0, 0.5, -1.0])
    return GREY * (1 + 0.4 * wave + 0.3 * yy[..., None])


def _write_raw(path: Path, colour: np.ndarray, cfa: str = "GBRG") -> Path:
    raw = mosaic(colour, cfa).astype(np.float32)
    write_raw_exr(path, RawImage(raw, cfa, 0.01, "unfiltered"))
    return path


def _dispersion_model(path: Path, shape: tuple[int, int], direction: str = "to_reference"):
    return lens_model_file(path, shape, direction)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Raw EXRs (grey, smooth, RGGB grey, odd-sized), a response CSV and dispersion models."""
    folder = tmp_path_factory.mktemp("reconstruct-inputs")
    response = folder / "response.csv"
    write_response_csv(camera_response("Nikon 5100 (NPL)"), response)
    odd = folder / "odd.exr"
    write_raw_exr(odd, RawImage(np.ones((63, 96), np.float32), "GBRG", 0.01, "unfiltered"))
    spectral = folder / "spectral.exr"
    cube = np.ones((*SHAPE, 2), np.float32)
    write_spectral_exr(spectral, SpectralImage(cube, np.array([500.0, 600.0]), {}))
    return {
        "grey": _write_raw(folder / "grey.exr", np.broadcast_to(GREY, (*SHAPE, 3)).copy()),
        "smooth": _write_raw(folder / "smooth.exr", _smooth_colour()),
        "rggb": _write_raw(folder / "rggb.exr", np.broadcast_to(GREY, (*SHAPE, 3)).copy(), "RGGB"),
        "odd": odd,
        "spectral": spectral,
        "response": response,
        "model": _dispersion_model(folder / "model.yaml", SHAPE),
        "model_small": _dispersion_model(folder / "small.yaml", (32, 48)),
        "model_from": _dispersion_model(folder / "from.yaml", SHAPE, "from_reference"),
    }


def test_smooth_scene_known_answer(inputs, tmp_path: Path, capsys) -> None:
    """Fixed weight, no dispersion, the thesis' problem (σ = 0: the synthetic colours need
    no smooth spectra) with the default prior (EdgeL2), one quadratic solve: band centres,
    shape, raw colour, log."""
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["smooth"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--weights", "fixed:0.001", "--no-nonneg", "--patch-px", "32",
            "--spectral-smoothness", "0", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "weights: 0.001 (fixed)" in printed
    assert "patches: 6, 0 flat; no dispersion model" in printed
    assert f"wrote {out / 'spectral.exr'}" in printed

    spectral = read_spectral_exr(out / "spectral.exr")
    np.testing.assert_array_equal(spectral.wavelengths_nm, [400, 450, 500, 550, 600, 650, 700])
    assert spectral.cube.shape == (*SHAPE, 7) and spectral.cube.dtype == np.float32
    assert np.all(np.isfinite(spectral.cube))
    meta = spectral.labkit
    assert meta["kind"] == "spectral" and meta["input"] == str(inputs["smooth"])
    assert meta["response"] == str(inputs["response"]) and meta["rig"] is None
    assert meta["prior"] == "EdgeL2" and meta["nonneg"] is False
    assert meta["weights"] == {"requested": "fixed:0.001", "criterion": "fixed", "values": [0.001]}
    assert meta["raw"]["cfa"] == "GBRG" and meta["basis"]["spacing_nm"] == 50.0

    # the data term: the raw colour at each pixel's CFA site reproduces the raw to 0.2 %
    raw_colour = _read_rgb_exr(out / "raw_colour.exr")
    assert raw_colour.shape == (*SHAPE, 3)
    raw = mosaic(_smooth_colour(), "GBRG")
    np.testing.assert_allclose(mosaic(raw_colour, "GBRG"), raw, rtol=2e-3)

    log = json.loads((out / "log.json").read_text())
    assert log["weights"]["values"] == [0.001] and log["weights"]["criterion"] == "fixed"
    assert log["arguments"]["weights"] == "fixed:0.001" and log["arguments"]["bands"] == BANDS
    assert log["bands_nm"] == [400, 450, 500, 550, 600, 650, 700]
    assert log["patches"]["count"] == len(log["patch_records"]) == 6
    assert log["options"]["patch_px"] == 32 and log["options"]["nonneg"] is False
    assert log["spectral_smoothness"] == 0.0

    with Image.open(out / "preview.png") as preview:
        assert preview.size == (SHAPE[1], SHAPE[0]) and preview.mode == "RGB"


def test_flat_grey_with_rig_and_dispersion(
    inputs, sim_rig_path: Path, tmp_path: Path, capsys
) -> None:
    """rigs/simulated.yaml supplies response and CFA; flat patches skip Φ; colour back to 1e-3
    (σ = 0: no smooth spectrum has the colour (0.3, 0.5, 0.2) under the rig's response, and
    the spectral smoothness term would move it)."""
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["grey"]), "--rig", str(sim_rig_path), "--bands", BANDS,
            "--dispersion", str(inputs["model"]), "--weights", "fixed:0.01", "--patch-px", "32",
            "--pad-px", "8", "--spectral-smoothness", "0", "--quiet",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "Φ used on 0, skipped on 6" in printed and "6 flat" in printed
    raw_colour = _read_rgb_exr(out / "raw_colour.exr")
    np.testing.assert_allclose(raw_colour, np.broadcast_to(GREY, (*SHAPE, 3)), rtol=1e-3)
    spectral = read_spectral_exr(out / "spectral.exr")
    assert spectral.cube.min() >= 0, "--nonneg is the default"
    assert spectral.labkit["rig"] == str(sim_rig_path)
    assert spectral.labkit["response"] == "Nikon 5100 (NPL)"
    assert spectral.labkit["dispersion_model"] == str(inputs["model"])
    log = json.loads((out / "log.json").read_text())
    assert log["patches"]["phi_skipped_flat"] + log["patches"]["phi_skipped_negligible"] == 6
    assert log["dispersion"]["variables"] == "xylambda"
    sigma = log["choices"]["spectral_smoothness"]
    assert log["spectral_smoothness"] == 0.0 and sigma["source"] == "given"


def test_a_model_lacking_bands_is_clamped_and_the_outputs_say_so(
    inputs, tmp_path: Path, capsys
) -> None:
    """The model was calibrated over 450–650 nm; the camera sees 400–700 nm. Φ is clamped to
    the model's range, and the summary, log.json and the EXR header say so; with
    --extrapolation refuse the command stops before any work and writes nothing."""
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["smooth"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--dispersion", str(inputs["model"]), "--weights", "fixed:0.01",
            "--patch-px", "32", "--quiet", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    warning = next(line for line in printed.splitlines() if "outside the domain" in line)
    assert warning.startswith("warning: the dispersion model is used outside the domain")
    assert "(clamped)" in warning and "→ 450.0" in warning and "→ 650.0" in warning
    log = json.loads((out / "log.json").read_text())
    domain = log["dispersion"]["domain"]
    assert domain["policy"] == "clamp" and domain["calibrated_nm"] == [450.0, 650.0]
    assert domain["outside_nm"][0] < 450 and domain["outside_nm"][-1] > 650
    assert any("outside the domain" in w for w in log["warnings"])
    header = read_spectral_exr(out / "spectral.exr").labkit
    assert header["extrapolation"] == "clamp"
    assert any("outside the domain" in w for w in header["warnings"])

    refused = tmp_path / "refused"
    assert main([*args[:-1], str(refused), "--extrapolation", "refuse"]) == 2
    error = capsys.readouterr().err
    assert "--dispersion" in error and "--extrapolation" in error and "nm" in error
    assert not refused.exists()


def test_the_choices_labkit_made_are_printed_and_logged(
    sim_rig_path: Path, tmp_path: Path, capsys
) -> None:
    """A flat green mosaic like the ColorChecker's through the rig's 550 nm filter (its
    smooth fit misses it by 19 % at these bands): the default σ stays, printed among the
    choices labkit made with the band balance that goes with it, and the log records the
    misfit as evidence; no warning. A given σ is not listed."""
    raw = _write_raw(tmp_path / "green.exr", np.broadcast_to([0.057, 1.0, 0.088], (*SHAPE, 3)))
    base = ["reconstruct", str(raw), "--rig", str(sim_rig_path), "--bands", BANDS, "--quiet",
            "--weights", "fixed:0.01", "--patch-px", "32"]  # fmt: skip
    assert main([*base, "--out", str(tmp_path / "default")]) == 0
    captured = capsys.readouterr()
    assert "choices labkit made (give the option to override):" in captured.out
    assert "  --spectral-smoothness 0.001: the smoothest" in captured.out
    assert "  --band-balance 0.5: weakly sensed bands keep their edges" in captured.out
    assert "  --reference none: the response gives the bands' scales" in captured.out
    assert "warning" not in captured.out and "Warning" not in captured.err
    log = json.loads((tmp_path / "default" / "log.json").read_text())
    assert log["spectral_smoothness"] == 1e-3 and log["warnings"] == []
    sigma = log["choices"]["spectral_smoothness"]
    assert sigma["source"] == "default" and sigma["evidence"]["mean_colour_misfit"] > 0.18

    out = tmp_path / "asked"
    assert main([*base, "--spectral-smoothness", "0", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "--spectral-smoothness" not in captured.out.split("choices labkit made")[1]
    log = json.loads((out / "log.json").read_text())
    assert log["spectral_smoothness"] == 0.0 and log["band_balance"] == 0.0


def test_cubic_interpolation_keeps_a_grey_scene_grey(inputs, tmp_path: Path, capsys) -> None:
    """--interpolation cubic: Φ with Keys weights (they sum to 1) on every patch (flat
    detection off) leaves a flat grey scene grey to 1 % (0.45 % measured; ADMM's tolerance
    with Φ, bilinear weights give 0.3 %), and the log says which weights."""
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["grey"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--dispersion", str(inputs["model"]), "--interpolation", "cubic",
            "--flat-threshold", "none",
            "--weights", "fixed:0.01", "--patch-px", "32", "--pad-px", "8", "--quiet",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    raw_colour = _read_rgb_exr(out / "raw_colour.exr")
    np.testing.assert_allclose(raw_colour, np.broadcast_to(GREY, (*SHAPE, 3)), rtol=1e-2)
    assert np.median(np.abs(raw_colour / GREY - 1)) < 1e-3
    log = json.loads((out / "log.json").read_text())
    assert log["patches"]["phi_used"] > 0
    assert log["dispersion"]["interpolation"] == "cubic"
    assert read_spectral_exr(out / "spectral.exr").labkit["interpolation"] == "cubic"


def test_warp_correction_takes_a_from_reference_model(inputs, tmp_path: Path, capsys) -> None:
    """§3.9.2: solve without Φ, then warp; a flat grey scene stays grey to 1e-3."""
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["grey"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--dispersion", str(inputs["model_from"]),
            "--correction", "warp", "--weights", "fixed:0.01", "--patch-px", "32",
            "--quiet", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    assert "solved without the dispersion, then warped" in capsys.readouterr().out
    raw_colour = _read_rgb_exr(out / "raw_colour.exr")
    np.testing.assert_allclose(raw_colour, np.broadcast_to(GREY, (*SHAPE, 3)), rtol=1e-3)
    log = json.loads((out / "log.json").read_text())
    assert log["dispersion"]["correction"] == "warp"
    assert log["dispersion"]["direction"] == "from_reference"
    assert log["patches"]["phi_used"] == 0 and log["warp_seconds"] >= 0
    assert read_spectral_exr(out / "spectral.exr").labkit["correction"] == "warp"


def test_colour_latent_writes_no_spectral_image(inputs, tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["grey"]), "--latent", "colour", "--weights", "fixed:0.01",
            "--patch-px", "32", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["labkit-run.json", "log.json", "preview.png", "raw_colour.exr"]
    np.testing.assert_allclose(
        _read_rgb_exr(out / "raw_colour.exr"), np.broadcast_to(GREY, (*SHAPE, 3)), rtol=1e-3
    )
    assert json.loads((out / "log.json").read_text())["spectral_smoothness"] == 0.0


def test_progress_bar_only_on_a_terminal(
    inputs, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = ["reconstruct", str(inputs["grey"]), "--response", str(inputs["response"]),
            "--weights", "fixed:0.01", "--patch-px", "32"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert "patch" not in capsys.readouterr().err, "stderr is not a terminal: no bar"
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    assert "6/6" in capsys.readouterr().err
    assert main([*args, "--quiet", "--out", str(tmp_path / "c")]) == 0
    assert "patch" not in capsys.readouterr().err


def test_tcp_scheduler_gives_the_same_image(inputs, tmp_path: Path, capsys) -> None:
    """--scheduler tcp://… runs the same patches on a dask.distributed cluster."""
    from distributed import LocalCluster

    args = ["reconstruct", str(inputs["smooth"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--weights", "fixed:0.001", "--no-nonneg",
            "--patch-px", "32"]  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "local")]) == 0
    with LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, protocol="tcp://", host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:  # fmt: skip
        address = cluster.scheduler_address
        assert main([*args, "--scheduler", address, "--out", str(tmp_path / "tcp")]) == 0
    local = read_spectral_exr(tmp_path / "local" / "spectral.exr").cube
    remote = read_spectral_exr(tmp_path / "tcp" / "spectral.exr").cube
    np.testing.assert_allclose(remote, local, rtol=1e-6, atol=1e-9)
    log = json.loads((tmp_path / "tcp" / "log.json").read_text())
    assert log["options"]["scheduler"] == address and log["patches"]["count"] == 6


def test_unreachable_scheduler_is_refused_before_work(inputs, tmp_path: Path, capsys) -> None:
    import socket

    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    out = tmp_path / "out"
    args = ["reconstruct", str(inputs["grey"]), "--response", str(inputs["response"]),
            "--scheduler", f"tcp://127.0.0.1:{port}", "--out", str(out)]  # fmt: skip
    assert main(args) == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err
    assert not out.exists()


def test_help_documents_every_option(capsys) -> None:
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    parser = commands.choices["reconstruct"]
    assert main(["reconstruct", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for action in parser._actions:
        assert action.help, f"{action.option_strings or action.dest} has no help"
        for option in action.option_strings:
            assert option in text
    for option in ("--rig", "--response", "--bands", "--dispersion", "--prior", "--nonneg",
                   "--no-nonneg", "--weights", "--latent", "--reference", "--rtol", "--patch-px",
                   "--pad-px", "--scheduler", "--out", "--quiet", "--correction",
                   "--exact", "--spectral-smoothness", "--band-balance",
                   "--extrapolation"):  # fmt: skip
        assert option in text
    for prior in PRIORS:
        assert prior in text, f"prior {prior} is missing from the --prior help"
    for word in ("auto:dmc", "auto:mdc", "fixed:W", "mean-colour", "spectral.exr",
                 "raw_colour.exr", "preview.png", "log.json", "tcp://"):  # fmt: skip
        assert word in text


@pytest.mark.parametrize(
    ("raw", "options", "message"),
    [
        ("missing", ["--response", "R"], "raw image {missing} does not exist"),
        ("spectral", ["--response", "R"], "no 'raw' channel"),
        ("odd", ["--response", "R"], "63×96 px; a Bayer mosaic needs an even number"),
        ("grey", [], "needs the camera response: give --rig RIG.yaml or --response"),
        ("grey", ["--response", "R", "--rig", "RIG"], "either --rig"),
        ("grey", ["--response", "missing.csv"], "--response: camera response file"),
        ("rggb", ["--rig", "RIG"], "CFA layouts disagree: {rggb} says RGGB, {rig} says GBRG"),
        ("grey", ["--response", "R", "--bands", "400,4x0"], "--bands '400,4x0': expected comma"),
        ("grey", ["--response", "R", "--bands", "500,400"], "increasing order"),
        ("grey", ["--response", "R", "--bands", "400,450,520"], "equally spaced"),
        ("grey", ["--response", "R", "--bands", "300,400,500"], "not covered by the camera"),
        ("grey", ["--response", "R", "--prior", "TV"],
         "unknown --prior 'TV'; use one of " + ", ".join(PRIORS)),
        ("grey", ["--response", "R", "--weights", "best"], "--weights 'best': use auto:dmc"),
        ("grey", ["--response", "R", "--weights", "fixed:0.1,0.2"], "L2 has 1 term(s)"),
        ("grey", ["--response", "R", "--weights", "fixed:x"], "must be numbers"),
        ("grey", ["--response", "R", "--weights", "auto:msec"], "only the Python API"),
        ("grey", ["--response", "R", "--weights", "auto:dmc-ari"],
         "unknown criterion 'dmc-ari'; use auto:dmc, auto:dmc-menon, auto:dmc-malvar"),
        ("grey", ["--response", "R", "--dispersion", "model_small"],
         "calibrated for 32×48 px images but the raw image is 64×96 px"),
        ("grey", ["--response", "R", "--dispersion", "model_from"],
         "is a from_reference model, but --correction model needs a to_reference one"),
        ("grey", ["--response", "R", "--correction", "warp"],
         "--correction warp needs a dispersion model (--dispersion)"),
        ("grey", ["--response", "R", "--correction", "tilt"], "unknown --correction 'tilt'"),
        ("grey", ["--response", "R", "--interpolation", "sinc"],
         "unknown --interpolation 'sinc'"),
        ("grey", ["--response", "R", "--prior", "L1", "--exact"], "L1 has L1 terms"),
        ("grey", ["--response", "R", "--dispersion", "missing.yaml"], "does not exist"),
        ("grey", ["--response", "R", "--latent", "colour", "--bands", BANDS], "no --bands"),
        ("grey", ["--response", "R", "--patch-px", "30.5"], "--patch-px is '30.5'"),
        ("grey", ["--response", "R", "--scheduler", "mpi"], "--scheduler is 'mpi'"),
        ("grey", ["--response", "R", "--spectral-smoothness", "-1"],
         "--spectral-smoothness is '-1'; expected a finite number ≥ 0 such as 1e-3"),
        ("grey", ["--response", "R", "--latent", "colour", "--spectral-smoothness", "1e-3"],
         "--spectral-smoothness applies to --latent spectral"),
        ("grey", ["--response", "R", "--band-balance", "1.5"],
         "--band-balance is '1.5'; expected a number in [0, 1]"),
        ("grey", ["--response", "R", "--band-balance", "nan"],
         "--band-balance is 'nan'; expected a number in [0, 1] such as 0.5"),
        ("grey", ["--response", "R", "--latent", "colour", "--dispersion", "model_from"],
         "is a spectral from_reference model, but a colour reconstruction (--latent colour) "
         "with --correction model needs a colour-channel to_reference model"),
        ("grey", ["--response", "R", "--latent", "colour", "--dispersion", "model"],
         "is a spectral model, but a colour reconstruction (--latent colour) needs a "
         "colour-channel model"),
        ("grey", ["--response", "R", "--prior", "VTV", "--band-balance", "0.5"],
         "--band-balance applies to the L2 and EdgeL2 priors"),
        ("grey", ["--response", "R", "--spectral-smoothness", "0", "--band-balance", "0.5"],
         "--band-balance needs spectral smoothness (--spectral-smoothness > 0)"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_and_writes_nothing(
    inputs, sim_rig_path: Path, tmp_path: Path, capsys, raw: str, options: list, message: str
) -> None:
    names = {**inputs, "missing": tmp_path / "missing.exr", "rig": sim_rig_path}
    values = {"R": str(inputs["response"]), "RIG": str(sim_rig_path)}
    values.update({k: str(v) for k, v in inputs.items()})
    options = [values.get(o, str(tmp_path / o) if o.startswith("missing") else o) for o in options]
    out = tmp_path / "out"
    assert main(["reconstruct", str(names[raw]), *options, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("labkit: error: ") and err.count("\n") == 1, err
    assert message.format(**{k: str(v) for k, v in names.items()}) in err
    assert not out.exists(), "nothing is written on error"


def test_out_that_is_a_file_is_refused(inputs, tmp_path: Path, capsys) -> None:
    out = tmp_path / "taken"
    out.write_text("keep me")
    args = ["reconstruct", str(inputs["grey"]), "--response", str(inputs["response"]),
            "--out", str(out)]  # fmt: skip
    assert main(args) == 2
    assert "exists and is not a folder" in capsys.readouterr().err
    assert out.read_text() == "keep me"


def test_a_measured_sensor_map_is_a_response_with_its_own_bands(tmp_path: Path, capsys) -> None:
    """``--response sensitivity.yaml`` (labkit calibrate sensitivity): the thesis' sensor map.

    The raw image is made as Algorithm 13 makes its synthetic raw images, Σ_b (r_b, 1, b_b)·M_b
    from smooth band images M_b; the reconstruction takes the map's four bands and its data
    term reproduces that raw image."""
    from calibration import ChannelSensitivity

    wavelengths = np.array([450.0, 500.0, 550.0, 600.0])
    r, b = np.array([0.3, 0.09, 0.05, 2.5]), np.array([4.8, 0.9, 0.07, 0.02])
    n = wavelengths.size
    table = ChannelSensitivity(
        wavelengths, tuple(f"{w:g}" for w in wavelengths), r, b, np.zeros(n), np.zeros(n),
        np.full(n, np.nan), np.full(n, np.nan), np.ones(n, bool), np.ones(n, bool),
        ("",) * n, ("",) * n,
    )  # fmt: skip
    table.to_yaml(tmp_path / "sensitivity.yaml")
    yy, xx = np.mgrid[: SHAPE[0], : SHAPE[1]] / np.array(SHAPE)[:, None, None]
    bands = np.stack([0.05 * (1 + 0.5 * np.sin(2 * np.pi * (xx + k / 4)) + yy) for k in range(n)])
    colour = np.einsum("bc,bij->ijc", np.column_stack([r, np.ones(n), b]), bands)
    raw = _write_raw(tmp_path / "raw.exr", colour)
    out = tmp_path / "out"
    args = ["reconstruct", str(raw), "--response", str(tmp_path / "sensitivity.yaml"),
            "--weights", "fixed:0.0001", "--no-nonneg", "--spectral-smoothness", "0",
            "--patch-px", "32", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    spectral = read_spectral_exr(out / "spectral.exr")
    np.testing.assert_array_equal(spectral.wavelengths_nm, wavelengths)
    assert spectral.labkit["response"] == str(tmp_path / "sensitivity.yaml")
    raw_colour = _read_rgb_exr(out / "raw_colour.exr")
    np.testing.assert_allclose(
        mosaic(raw_colour, "GBRG"), mosaic(colour, "GBRG"), rtol=5e-3, atol=1e-4
    )
    # a map without Green levels (G = 1 in every band) leaves the bands' scales unknown:
    # the §6.3 reference puts them on one scale, and the log says why
    log = json.loads((out / "log.json").read_text())
    reference = log["choices"]["reference"]
    assert log["reference"] == "mean-colour" and reference["source"] == "follows"
    assert reference["evidence"] == {"green_per_band": 1.0}
    # the same file given to the Python API: the map's bands by default too
    from reconstruction import ReconstructOptions

    options = ReconstructOptions(cfa="GBRG", response=tmp_path / "sensitivity.yaml")
    assert options.bands == tuple(wavelengths)
    assert options.as_dict()["response"] == str(tmp_path / "sensitivity.yaml")


def test_the_python_api_writes_what_the_cli_writes(inputs, tmp_path: Path) -> None:
    """Reconstruction.save, given the same problem, writes the same files and images as
    `labkit reconstruct`; the CLI's log adds only its provenance and arguments."""
    from labkit.io import read_mosaic
    from reconstruction import reconstruct

    cli_out, api_out = tmp_path / "cli", tmp_path / "api"
    args = ["reconstruct", str(inputs["smooth"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--weights", "fixed:0.001", "--patch-px", "32",
            "--spectral-smoothness", "0", "--out", str(cli_out)]  # fmt: skip
    assert main(args) == 0
    raw = read_mosaic(inputs["smooth"])
    result = reconstruct(
        raw.raw,
        cfa=raw.cfa,
        response=camera_response("Nikon 5100 (NPL)"),
        bands=[float(b) for b in BANDS.split(",")],
        weights="fixed:0.001",
        spectral_smoothness=0,
        patch_px=32,
    )
    paths = result.save(api_out)
    written = sorted([RUN_MANIFEST, *(p.name for p in paths.values())])
    assert sorted(p.name for p in cli_out.iterdir()) == written
    cli_cube = read_spectral_exr(cli_out / "spectral.exr")
    api_cube = read_spectral_exr(api_out / "spectral.exr")
    np.testing.assert_allclose(api_cube.cube, cli_cube.cube, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(api_cube.wavelengths_nm, cli_cube.wavelengths_nm)
    np.testing.assert_allclose(
        _read_rgb_exr(api_out / "raw_colour.exr"),
        _read_rgb_exr(cli_out / "raw_colour.exr"),
        rtol=1e-5,
        atol=1e-7,
    )
    for key in ("prior", "nonneg", "spectral_smoothness", "weights", "basis"):
        assert api_cube.labkit[key] == cli_cube.labkit[key], key
    cli_log = json.loads((cli_out / "log.json").read_text())
    api_log = json.loads((api_out / "log.json").read_text())
    assert set(api_log) < set(cli_log)
    assert set(cli_log) - set(api_log) == {
        "command", "input", "raw", "rig", "response", "dispersion_model", "arguments",
        "options"}  # fmt: skip


@pytest.mark.parametrize(
    ("values", "match"),
    [
        (lambda r: np.ones_like(r), "are saturated"),
        (lambda r: -r, "holds no light"),
        (lambda r: np.zeros_like(r), "holds no light"),
    ],
)
def test_a_raw_without_usable_light_is_refused(tmp_path: Path, capsys, values, match) -> None:
    raw = np.random.default_rng(5).uniform(0.1, 0.9, (32, 32)).astype(np.float32)
    path = tmp_path / "raw.exr"
    write_raw_exr(path, RawImage(values(raw), "GBRG", 0.01, "unfiltered"))
    out = tmp_path / "out"
    status = main(["reconstruct", str(path), "--response", "Nikon 5100 (NPL)", "--out", str(out)])
    err = capsys.readouterr().err
    assert status == 2 and match in err and err.count("\n") == 1
    assert not out.exists()


def test_a_scheduler_that_accepts_and_never_answers_is_an_error(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """No hang: a tcp:// address that takes the connection and stays silent times out."""
    import socket
    import threading
    import time

    import reconstruction.solve.patches

    monkeypatch.setattr(reconstruction.solve.patches, "SCHEDULER_TIMEOUT_S", 2.0)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held: list[socket.socket] = []
    accepting = threading.Thread(
        target=lambda: [held.append(server.accept()[0]) for _ in range(8)], daemon=True
    )
    accepting.start()
    raw = np.random.default_rng(6).uniform(0.1, 0.9, (32, 32)).astype(np.float32)
    path = tmp_path / "raw.exr"
    write_raw_exr(path, RawImage(raw, "GBRG", 0.01, "unfiltered"))
    port = server.getsockname()[1]
    start = time.monotonic()
    status = main(["reconstruct", str(path), "--response", "Nikon 5100 (NPL)", "--weights",
                   "fixed:0.01", "--scheduler", f"tcp://127.0.0.1:{port}",
                   "--out", str(tmp_path / "out")])  # fmt: skip
    err = capsys.readouterr().err
    server.close()
    assert status == 2 and "did not answer within 2 s" in err and err.count("\n") == 1
    assert time.monotonic() - start < 60
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("option", "content", "message"),
    [
        ("--response", b"\x89PNG\r\n\x1a\n\xff\xfe\x00", "cannot be read as text"),
        ("--response", b"wavelength_nm,R,G,B\n400,nan,1,1\n500,1,1,1\n", "NaN or Inf"),
        ("--response", b"wavelength_nm,R,G,B\n400,1,1\n500,1,1,1\n", "ragged row"),
        ("--dispersion", b"\xff\xfe\x00\x01" * 16, "cannot be read as YAML text"),
    ],
)
def test_binary_or_malformed_side_files_are_clear_errors(
    inputs, tmp_path: Path, capsys, option: str, content: bytes, message: str
) -> None:
    side = tmp_path / ("side.csv" if option == "--response" else "side.yaml")
    side.write_bytes(content)
    response = [] if option == "--response" else ["--response", str(inputs["response"])]
    out = tmp_path / "out"
    status = main(["reconstruct", str(inputs["grey"]), *response, option, str(side),
                   "--out", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert status == 2 and message in err and str(side) in err and err.count("\n") == 1
    assert not out.exists()


def _openssl(*args: str, cwd: Path) -> None:
    import shutil
    import subprocess

    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make test certificates")
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def _certificates(folder: Path, name: str) -> dict[str, str]:
    """A CA and a certificate it signed (for scheduler, workers and client alike)."""
    folder.mkdir()
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out",
             "ca.pem", "-days", "2", "-subj", f"/CN={name}-ca", cwd=folder)  # fmt: skip
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "key.pem", "-out", "req.csr",
             "-subj", f"/CN={name}", cwd=folder)  # fmt: skip
    _openssl("x509", "-req", "-in", "req.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "cert.pem", "-days", "2", cwd=folder)  # fmt: skip
    return {k: str(folder / f) for k, f in [("ca", "ca.pem"), ("cert", "cert.pem"),
                                            ("key", "key.pem")]}  # fmt: skip


def _tls_config(files: dict[str, str]) -> dict[str, str]:
    return {
        "distributed.comm.tls.ca-file": files["ca"],
        "distributed.comm.tls.client.cert": files["cert"],
        "distributed.comm.tls.client.key": files["key"],
    }


def test_tls_scheduler_uses_dasks_tls_configuration(inputs, tmp_path: Path, capsys) -> None:
    """--scheduler tls://… authenticates with the certificates of Dask's configuration; a
    client without them, or with another CA's, is refused before any work."""
    import dask
    from distributed import LocalCluster, Security

    cluster_files = _certificates(tmp_path / "cluster", "labkit-test")
    stranger = _certificates(tmp_path / "stranger", "stranger")
    security = Security(
        tls_ca_file=cluster_files["ca"], require_encryption=True,
        **{f"tls_{role}_{kind}": cluster_files[kind] for role in ("scheduler", "worker", "client")
           for kind in ("cert", "key")},
    )  # fmt: skip
    args = ["reconstruct", str(inputs["smooth"]), "--response", str(inputs["response"]),
            "--bands", BANDS, "--weights", "fixed:0.001", "--no-nonneg",
            "--patch-px", "32"]  # fmt: skip
    with LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, protocol="tls://", host="127.0.0.1",
        dashboard_address=None, security=security,
    ) as cluster:  # fmt: skip
        address = cluster.scheduler_address
        assert address.startswith("tls://")
        with dask.config.set({"distributed.comm.tls.ca-file": None,
                              "distributed.comm.tls.client.cert": None}):  # fmt: skip
            assert main([*args, "--scheduler", address, "--out", str(tmp_path / "none")]) == 2
        assert "needs TLS credentials" in capsys.readouterr().err
        with dask.config.set(_tls_config(stranger)):
            assert main([*args, "--scheduler", address, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert "TLS handshake failed" in err and err.count("\n") == 1
        with dask.config.set(_tls_config(cluster_files)):
            assert main([*args, "--scheduler", address, "--out", str(tmp_path / "tls")]) == 0
    assert not (tmp_path / "none").exists() and not (tmp_path / "bad").exists()
    log = json.loads((tmp_path / "tls" / "log.json").read_text())
    assert log["options"]["scheduler"] == address and log["patches"]["count"] == 6
