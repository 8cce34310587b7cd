"""Options that several commands share, defined once."""

from __future__ import annotations

import argparse
import math
from typing import Any

from labkit.cfa import CFA_LAYOUTS


def add_cfa_option(parser: argparse.ArgumentParser, *, default: str = "") -> None:
    """``--cfa``: the Bayer layout of a raw mosaic that does not record its own.

    `default` says, in parentheses after the help's first clause, where the layout comes
    from when the option is left out (e.g. ``"the rig's with --rig"``).
    """
    note = f" (default: {default})" if default else ""
    parser.add_argument(
        "--cfa",
        choices=CFA_LAYOUTS,
        default=None,
        help=f"Bayer layout (top-left 2×2 block, row by row) of a raw mosaic that does not "
        f"record it{note}; an error if it contradicts the file's own",
    )


def _whole_number(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{value} is not ≥ {minimum}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: an integer ≥ 1 (argparse names the option in its error)."""
    return _whole_number(text, 1)


def non_negative_int(text: str) -> int:
    """An argparse type: an integer ≥ 0, e.g. a random seed (argparse names the option)."""
    return _whole_number(text, 0)


def finite_float(text: str) -> float:
    """An argparse type: a finite number (not NaN or ±Inf)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def fraction(text: str) -> float:
    """An argparse type: a number in (0, 1] (a fraction, not a percentage)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0 < value <= 1:  # NaN fails this too
        raise argparse.ArgumentTypeError(
            f"{text} is not a fraction in (0, 1]"
            + (f" (for {value:g} % give {value / 100:g})" if 1 < value <= 100 else "")
        )
    return value


#: The choices of ``--extrapolation`` (:data:`calibration.model_domain.EXTRAPOLATIONS`,
#: repeated here so that building a parser imports no numerical code).
EXTRAPOLATION_CHOICES = ("clamp", "refuse", "allow")


def model_domain(
    model: Any, args: argparse.Namespace, *, shape: tuple[int, int], wavelengths=None, what: str
) -> tuple[Any, dict[str, Any], str | None]:
    """`model` as ``--extrapolation`` evaluates it, how far its use on a `shape` image (at
    `wavelengths`, nm) reaches beyond its calibrated domain (JSON-ready), and the warning
    to print and record (None when nothing that matters lies outside). With ``refuse`` and
    something outside, a DataError naming the bands and the fix."""
    from calibration.model_domain import domain_use

    model = model.within_domain(args.extrapolation)
    use = domain_use(
        model,
        shape=shape,
        wavelengths_nm=wavelengths,
        policy=args.extrapolation,
        fix="--extrapolation clamp (the default)",
    )
    return model, use.to_dict(), use.message(what=what)


def add_extrapolation_option(parser: argparse.ArgumentParser, *, model: str = "the model") -> None:
    """``--extrapolation``: what a dispersion model does outside its calibrated domain."""
    parser.add_argument(
        "--extrapolation",
        default="clamp",
        choices=EXTRAPOLATION_CHOICES,
        help=f"where {model} would be used outside the domain it was calibrated on "
        "(wavelengths beyond its bands, pixels farther than one keypoint spacing from its "
        "keypoints): clamp to the domain's edge (default), refuse, or allow the fitted "
        "function there; the output says which bands and how much of the image",
    )
