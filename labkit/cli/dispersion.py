"""``labkit dispersion show MODEL.yaml``, ``labkit dispersion eval MODEL.yaml --x … --y …``
and ``labkit dispersion crop MODEL.yaml --origin ROW,COL --shape ROWS,COLS --out CROP.yaml``:
inspect a dispersion model — what it is, the domain it was calibrated on, its displacement
at given points — and move a whole sensor's model to a crop of its images."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.cli._options import add_extrapolation_option, finite_float


def register(commands: Commands) -> None:
    """Add ``labkit dispersion …``."""
    parser = commands.add_parser(
        "dispersion",
        description="Inspect dispersion models written by `labkit calibrate dispersion`.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    show = actions.add_parser(
        "show",
        help="print what a model is and the domain it was calibrated on",
        description="Print a model's kind, direction, reference and image size, the domain "
        "it was calibrated on (wavelength range, the keypoints' hull and spacing, how much "
        "of the image lies beyond them), how each filter band entered the calibration, and "
        "the model selection (degrees or smoothing, cross-validation error).",
    )
    show.add_argument("model", type=Path, help="dispersion model YAML")
    show.set_defaults(handler=_show)
    evaluate = actions.add_parser(
        "eval",
        help="print the displacement (dx, dy) at given positions and wavelengths",
        description="Evaluate a model: values of --x, --y and --wavelength (or --channel) "
        "are broadcast against each other (give one value or the same number of values for "
        "each). Prints x, y, band, dx, dy in px and whether the point lies inside the "
        "calibrated domain (the wavelength range, and the keypoints' convex hull widened by "
        "one keypoint spacing); outside it the point is clamped to the domain's edge unless "
        "--extrapolation says otherwise.",
    )
    evaluate.add_argument("model", type=Path, help="dispersion model YAML")
    evaluate.add_argument("--x", type=finite_float, nargs="+", required=True, help="column(s), px")
    evaluate.add_argument("--y", type=finite_float, nargs="+", required=True, help="row(s), px")
    evaluate.add_argument(
        "--wavelength",
        type=finite_float,
        nargs="+",
        default=None,
        help="wavelength(s), nm (spectral)",
    )
    evaluate.add_argument("--channel", default=None, help="R or B (colour-channel models)")
    add_extrapolation_option(evaluate)
    evaluate.set_defaults(handler=_eval)
    crop = actions.add_parser(
        "crop",
        help="the model of a whole sensor, moved to a crop of its images",
        description="Write the model for raw images cropped from the calibrated ones: the "
        "displacement at the crop's pixel (x, y) is the sensor's at (x + COL, y + ROW), and "
        "the calibrated domain moves with it (use the crop's origin on the sensor; keep it "
        "even so that the crop keeps the Bayer phase). The crop is recorded in the model's "
        "provenance; reconstruct, correct and evaluate then take the cropped raw images.",
    )
    crop.add_argument("model", type=Path, help="dispersion model YAML of the whole sensor")
    crop.add_argument(
        "--origin", required=True, metavar="ROW,COL", help="the crop's top-left pixel, px"
    )
    crop.add_argument("--shape", required=True, metavar="ROWS,COLS", help="the crop's size, px")
    crop.add_argument("--out", type=Path, required=True, help="the cropped model's YAML file")
    crop.set_defaults(handler=_crop)


def _pair(text: str, option: str) -> tuple[int, int]:
    from labkit.errors import ConfigError

    parts = text.split(",")
    try:
        values = tuple(int(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 2 or min(values) < 0:
        raise ConfigError(f"{option} is {text!r}; expected two whole numbers ≥ 0, e.g. 100,200")
    return values[0], values[1]


def _crop(args: argparse.Namespace) -> int:
    from calibration.dispersion_model import load_dispersion_model
    from labkit.errors import ConfigError

    origin, shape = _pair(args.origin, "--origin"), _pair(args.shape, "--shape")
    if args.out.resolve() == args.model.resolve():
        raise ConfigError(f"--out {args.out} is the input model; give another file")
    model = load_dispersion_model(args.model)
    cropped = model.cropped(origin, shape)
    cropped.save(args.out)
    rows, cols = model.image_shape
    print(
        f"wrote {args.out}: {args.model} ({cols}×{rows} px) on the {shape[1]}×{shape[0]} px "
        f"crop at (row, col) = {origin}"
    )
    return 0


def _eval(args: argparse.Namespace) -> int:
    import numpy as np

    from calibration.dispersion_model import load_dispersion_model
    from labkit.errors import DataError

    loaded = load_dispersion_model(args.model)
    model = loaded.within_domain(args.extrapolation)
    region = model.region
    try:
        x, y = np.broadcast_arrays(np.array(args.x), np.array(args.y))
        if model.variables == "xylambda":
            if args.wavelength is None:
                raise DataError(f"{args.model} is a spectral model; give --wavelength")
            x, y, band = np.broadcast_arrays(x, y, np.array(args.wavelength))
            labels = [f"{b:g} nm" for b in band]
            waves = band
        else:
            if args.channel is None:
                raise DataError(
                    f"{args.model} is a colour-channel model; give --channel "
                    f"({', '.join(model.channels)})"
                )
            labels = [args.channel] * x.size
            waves = None
    except ValueError:
        raise DataError(
            "--x, --y and --wavelength need one value or the same number of values each"
        ) from None
    cx, cy, cw = region.clamp(x, y, waves)
    moved = (cx != x) | (cy != y)
    if cw is not None:
        moved |= cw != waves
    if args.extrapolation == "refuse" and moved.any():
        first = int(np.argmax(moved))
        raise DataError(
            f"({x[first]:g}, {y[first]:g}, {labels[first]}) lies outside the domain "
            f"{args.model} was calibrated on ({_domain_text(region)}); give "
            "--extrapolation clamp or allow"
        )
    if model.variables == "xylambda":
        dx, dy = model.displacement(x, y, waves)
    else:
        dx, dy = model.displacement(x, y, channel=args.channel)
    state = "extrapolated" if args.extrapolation == "allow" else "clamped"
    print(f"# {model.type} model, {model.direction}, reference {model.reference}")
    print(f"# calibrated domain: {_domain_text(region)}")
    print(f"{'x':>9} {'y':>9} {'band':>10} {'dx':>9} {'dy':>9}  domain")
    for i, label in enumerate(labels):
        where = "inside"
        if moved[i]:
            where = state
            if state == "clamped":
                at = f"({cx[i]:.1f}, {cy[i]:.1f}" + ("" if cw is None else f", {cw[i]:.1f} nm")
                where += f" to {at})"
        print(f"{x[i]:>9.2f} {y[i]:>9.2f} {label:>10} {dx[i]:>9.4f} {dy[i]:>9.4f}  {where}")
    return 0


def _domain_text(region) -> str:
    """The calibrated domain in words: wavelength range, hull extent and margin."""
    lo, hi = region.hull_xy.min(axis=0), region.hull_xy.max(axis=0)
    text = f"keypoints over x {lo[0]:.0f}–{hi[0]:.0f}, y {lo[1]:.0f}–{hi[1]:.0f} px"
    if region.spacing_px is not None:
        text += f", trusted {region.margin_px:.0f} px beyond (one keypoint spacing)"
    if region.wavelength_nm is not None:
        text = f"{region.wavelength_nm[0]:.1f}–{region.wavelength_nm[1]:.1f} nm; " + text
    return text


def _show(args: argparse.Namespace) -> int:
    from calibration.dispersion_model import load_dispersion_model
    from calibration.model_domain import domain_use

    model = load_dispersion_model(args.model)
    kind = {"xylambda": "spectral (x, y, λ)", "xy": "colour-channel (x, y), R and B"}
    rows, cols = model.image_shape
    print(f"{args.model}")
    print(f"  model        {model.type}, {kind.get(model.variables, model.variables)}")
    reference = model.reference
    if isinstance(reference, float):
        reference = f"{reference:.1f} nm"
    print(f"  direction    {model.direction}, reference {reference}")
    print(f"  image        {cols}×{rows} px (width × height)")
    crop = model.provenance.get("crop")
    if isinstance(crop, dict):
        print(f"  crop         of the sensor's {crop.get('image_shape')} px images (rows, cols) "
              f"at (row, col) = {crop.get('origin')}")  # fmt: skip
    print(f"  domain       {_domain_text(model.region)}")
    use = domain_use(model, policy="allow")
    print(
        f"               {100 * use.area_outside:.1f} % of the image lies beyond it (up to "
        f"{use.max_outside_px:.0f} px from the keypoints' hull); reconstruct, correct and "
        "evaluate clamp there unless told otherwise (--extrapolation)"
    )
    table = model.provenance.get("bands_table") or []
    if table:
        print("  bands        filter   nominal  effective  purity  used")
        for row in table:
            used = "yes" if row.get("used") else f"no: {row.get('reason', '')}"
            print(
                f"               {row.get('illumination')!s:>6} "
                f"{_number(row, 'nominal_nm', '>8.1f')} {_number(row, 'wavelength_nm', '>10.1f')} "
                f"{_number(row, 'purity', '>7.2f')}  {used}"
            )
    selection = model.selection
    chosen = {k: selection[k] for k in ("method", "degree_xy", "degree_lambda") if k in selection}
    if chosen:
        print("  selection    " + ", ".join(f"{k} {v}" for k, v in chosen.items()))
    if "cv_min" in selection and isinstance(selection["cv_min"], dict):
        error = selection["cv_min"].get("error")
        if isinstance(error, (int, float)):
            print(f"               cross-validated error {error:.3g} px² at its minimum")
    for record in selection.get("extrapolation") or []:
        rms = record.get("rms_px") if isinstance(record, dict) else None
        if isinstance(rms, (int, float)):
            print(
                f"               extrapolating one band step, {record['from_nm']:.1f} → "
                f"{record['band_nm']:.1f} nm (refitted without it): {rms:.3f} px RMS"
            )
    return 0


def _number(row: dict, key: str, spec: str) -> str:
    value = row.get(key)
    return format(value, spec) if isinstance(value, (int, float)) else "—"
