"""``labkit dispersion eval MODEL.yaml --x … --y … --wavelength …``: query a model."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._options import finite_float


def register(commands: argparse._SubParsersAction) -> None:
    """Add ``labkit dispersion …``."""
    parser = commands.add_parser(
        "dispersion",
        help="inspect dispersion models",
        description="Inspect dispersion models written by `labkit calibrate dispersion`.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    evaluate = actions.add_parser(
        "eval",
        help="print the displacement (dx, dy) at given positions and wavelengths",
        description="Evaluate a model: values of --x, --y and --wavelength (or --channel) "
        "are broadcast against each other (give one value or the same number of values for "
        "each). Prints x, y, band, dx, dy in px and whether the point lies inside the "
        "calibrated region (the keypoints' convex hull and wavelength range).",
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
    evaluate.set_defaults(handler=_eval)


def _eval(args: argparse.Namespace) -> int:
    import numpy as np

    from calibration.dispersion_model import load_dispersion_model
    from labkit.errors import DataError

    model = load_dispersion_model(args.model)
    try:
        x, y = np.broadcast_arrays(np.array(args.x), np.array(args.y))
        if model.variables == "xylambda":
            if args.wavelength is None:
                raise DataError(f"{args.model} is a spectral model; give --wavelength")
            x, y, band = np.broadcast_arrays(x, y, np.array(args.wavelength))
            dx, dy = model.displacement(x, y, band)
            inside = model.region.contains(x, y, band)
            labels = [f"{b:g} nm" for b in band]
        else:
            if args.channel is None:
                raise DataError(
                    f"{args.model} is a colour-channel model; give --channel "
                    f"({', '.join(model.channels)})"
                )
            dx, dy = model.displacement(x, y, channel=args.channel)
            inside = model.region.contains(x, y)
            labels = [args.channel] * x.size
    except ValueError:
        raise DataError(
            "--x, --y and --wavelength need one value or the same number of values each"
        ) from None
    print(f"# {model.type} model, {model.direction}, reference {model.reference}")
    print(f"{'x':>9} {'y':>9} {'band':>10} {'dx':>9} {'dy':>9}  calibrated")
    for xi, yi, label, a, b, ok in zip(x, y, labels, dx, dy, inside, strict=True):
        print(f"{xi:>9.2f} {yi:>9.2f} {label:>10} {a:>9.4f} {b:>9.4f}  {'yes' if ok else 'no'}")
    return 0
