"""``labkit correct warp IMAGE --model MODEL.yaml --out OUT``: undo dispersion by warping.

The baseline the thesis compares against (Rudakova and Monasse): each colour channel,
or each spectral band, is resampled (bilinear) onto the reference geometry with a
dispersion model (``from_reference``; a ``to_reference`` model is inverted on the fly).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from labkit.cli._commands import Commands
from labkit.cli._options import add_cfa_option, add_extrapolation_option, model_domain


def register(commands: Commands) -> None:
    """Add ``labkit correct …``."""
    parser = commands.add_parser(
        "correct",
        description="Corrections that use a calibrated dispersion model.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    warp = actions.add_parser(
        "warp",
        help="warp colour channels or spectral bands onto the reference (Rudakova–Monasse)",
        description="A raw Bayer mosaic is demosaiced bilinearly and its Red and Blue "
        "channels are warped onto Green with a colour-channel model (`--reference G`); the "
        "result is an RGB EXR plus a PNG preview. The mosaic is a raw EXR (from `labkit "
        "hdr`, or from other software: channel 'raw' or the only channel), a single-channel "
        "uint8/uint16/float TIFF or PNG (integers scaled by the container's maximum) or a "
        "camera raw file read by LibRaw (DNG, NEF, CR2, ARW, …; black level subtracted; "
        "Bayer sensors only); --cfa gives the layout of a file that does not record it. A "
        "spectral EXR has every band warped onto the reference band with a spectral model; "
        "the result is a spectral EXR. Either model "
        "direction works (a to_reference model is inverted by fixed-point iteration).",
    )
    warp.add_argument(
        "image",
        type=Path,
        help="raw Bayer mosaic (raw EXR, single-channel TIFF/PNG, camera raw file) or spectral EXR",
    )
    add_cfa_option(warp)
    warp.add_argument("--model", type=Path, required=True, help="dispersion model YAML")
    warp.add_argument("--out", type=Path, required=True, help="corrected EXR to write")
    warp.add_argument(
        "--order", type=int, choices=[0, 1, 3], default=1, help="interpolation order (default 1)"
    )
    add_extrapolation_option(warp)
    warp.set_defaults(handler=_warp)


def _warp(args: argparse.Namespace) -> int:
    from calibration.dispersion_model import load_dispersion_model
    from calibration.warp import correct_channels, correct_spectral
    from labkit.errors import ConfigError, DataError
    from labkit.io import (
        SpectralImage,
        demosaic_bilinear,
        read_mosaic,
        to_display,
        write_png,
        write_rgb_exr,
        write_spectral_exr,
    )
    from labkit.io.output_folder import (
        check_output_files,
        staged_output_files,
        verify_output_file,
    )

    check_output_files([args.out, args.out.with_suffix(".png")], inputs=[args.image, args.model])
    if args.image.is_file():
        verify_output_file(args.image, what="image")
    model = load_dispersion_model(args.model)
    provenance: dict[str, Any] = {"input": str(args.image), "dispersion_model": str(args.model)}
    try:
        raw = read_mosaic(args.image, cfa=args.cfa)
    except DataError:  # a spectral EXR, or the mosaic's error stands
        spectral = _spectral_or_none(args.image)
        if spectral is None:
            raise
        raw = None
    if raw is not None:
        if model.variables != "xy":
            raise DataError(
                f"{args.image} is a raw mosaic: warping its colour channels needs a "
                f"colour-channel model (`labkit calibrate dispersion --reference G`), but "
                f"{args.model} is a spectral model"
            )
        model = _within_domain(model, args, raw.raw.shape, None, provenance)
        rgb = demosaic_bilinear(raw.raw, raw.cfa).astype("float32")
        corrected = correct_channels(rgb, model, order=args.order)
        preview = args.out.with_suffix(".png")
        with staged_output_files([args.out, preview], command="labkit correct warp") as staged:
            write_rgb_exr(staged[0], corrected, {**raw.labkit, **provenance, "corrected": "warp"})
            write_png(staged[1], to_display(corrected))
        print(f"warped R and B onto G with {args.model}; wrote {args.out} and {preview}")
        return 0
    if args.cfa is not None:
        raise ConfigError(
            f"{args.image} is a spectral image: --cfa applies to raw mosaics only; drop it"
        )
    if model.variables != "xylambda":
        raise DataError(
            f"{args.image} is a spectral image: warping its bands needs a spectral model "
            f"(`labkit calibrate dispersion --reference 600`), but {args.model} is a "
            "colour-channel model"
        )
    model = _within_domain(
        model, args, spectral.cube.shape[:2], spectral.wavelengths_nm, provenance
    )
    cube = correct_spectral(spectral.cube, spectral.wavelengths_nm, model, order=args.order)
    with staged_output_files([args.out], command="labkit correct warp") as staged:
        write_spectral_exr(
            staged[0],
            SpectralImage(cube, spectral.wavelengths_nm, {**spectral.labkit, **provenance}),
        )
    print(f"warped {cube.shape[2]} bands with {args.model}; wrote {args.out}")
    return 0


def _within_domain(model: Any, args: argparse.Namespace, shape, wavelengths, provenance: dict):
    """The model as --extrapolation evaluates it; what lies outside its domain is printed
    and recorded in `provenance` (refused with --extrapolation refuse)."""
    model, domain, message = model_domain(
        model, args, shape=shape, wavelengths=wavelengths, what=str(args.model)
    )
    provenance["dispersion_domain"] = domain
    if message:
        provenance["warnings"] = [message]
        print(f"warning: {message}")
    return model


def _spectral_or_none(path: Path) -> Any:
    """The spectral image in `path` (a labkit spectral EXR), or None if it is not one."""
    from labkit.errors import DataError
    from labkit.io import read_spectral_exr

    if path.suffix.lower() != ".exr" or not path.is_file():
        return None
    try:
        return read_spectral_exr(path)
    except DataError:
        return None
