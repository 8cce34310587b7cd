"""One declaration of each reconstruction option: name, flag, type, bounds, help.

:class:`~reconstruction.options.ReconstructOptions` checks its fields against this table,
and ``labkit reconstruct`` generates its flags from it (:func:`OptionSpec.parse` turns a
flag's text into the value, :func:`OptionSpec.check` holds both to the same bounds), so
the command line and the Python API cannot validate an option differently. Options whose
check needs other options (the weights and the prior, the band balance and σ) are checked
by :class:`~reconstruction.options.ReconstructOptions` after these.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.model_domain import EXTRAPOLATIONS
from labkit.errors import DataError
from reconstruction.model.operators.basis import KERNELS
from reconstruction.model.operators.dispersion import INTERPOLATIONS
from reconstruction.model.prior_terms import PRIORS

CORRECTIONS = ("model", "warp")
"""How a dispersion model is undone: Φ inside the problem (3.1), or warping after (§3.9.2)."""

LATENTS = ("spectral", "colour")
"""What is estimated: the spectral image (3.1), or the colour image directly (3.27)."""

REFERENCES = ("auto", "mean-colour")
"""Reference spectra of the §6.3 variant: ``"auto"`` (the mean-colour reference where the
response leaves the bands' scales unknown), ``"mean-colour"`` (None: the plain problem)."""

NONE_TEXT = "none"
"""How a flag spells an option's None (e.g. ``--reference none``)."""


class OptionValueError(DataError):
    """A value outside an option's declared type or bounds; ``template`` names the option
    as ``{option}`` (:class:`~reconstruction.options.OptionError` fills it in)."""

    def __init__(self, template: str) -> None:
        self.template = template
        super().__init__(template.replace("{option}", "the option"))


@dataclass(frozen=True)
class OptionSpec:
    """One option: how it is spelled, what values it takes, what it means.

    Attributes
    ----------
    name : str
        Keyword of :class:`~reconstruction.options.ReconstructOptions`.
    flag : str or None
        Its ``labkit reconstruct`` flag (None: Python only).
    kind : {"choice", "number", "whole", "flag", "text"}
        A string from `choices`; a real number; a whole number; a boolean; free text
        checked elsewhere.
    help : str
        What it does, for ``--help`` and the docs (no measured figures).
    choices : tuple of str
        Allowed strings (``kind="choice"``).
    least, most : float, optional
        Bounds (``number`` / ``whole``); `open_least` / `open_most` exclude them.
    even : bool
        Whole numbers only: even.
    optional : bool
        None is a value (left to labkit, or "none" on the command line).
    metavar : str
        How ``--help`` shows the value.
    default_help : str
        What happens when it is left out, for ``--help``.
    example : str
        A typical value, quoted by messages.
    or_origins : bool
        Whole numbers only: a sequence (of patch origins, checked where they are used) is a
        value too, taken as it is.
    """

    name: str
    flag: str | None
    kind: str
    help: str
    choices: tuple[str, ...] = ()
    least: float | None = None
    most: float | None = None
    open_least: bool = False
    open_most: bool = False
    even: bool = False
    optional: bool = False
    metavar: str = ""
    default_help: str = ""
    example: str = ""
    or_origins: bool = False

    # -- checking ------------------------------------------------------------------------
    def expected(self) -> str:
        """The accepted values, in words (for messages)."""
        words = self._accepted()
        return f"{words} such as {self.example}" if self.example else words

    def _accepted(self) -> str:
        if self.kind == "choice":
            if len(self.choices) > 3:
                return "one of " + ", ".join(self.choices)
            return " or ".join(repr(c) for c in self.choices)
        if self.kind == "flag":
            return "True or False"
        if self.kind == "whole":
            low = "" if self.least is None else f" ≥ {self.least:g}"
            high = "" if self.most is None else f" ≤ {self.most:g}"
            return f"{'an even' if self.even else 'a'} whole number{low}{high}"
        if self.kind == "number":
            if self.least is not None and self.most is not None:
                left = "(" if self.open_least else "["
                right = ")" if self.open_most else "]"
                return f"a number in {left}{self.least:g}, {self.most:g}{right}"
            if self.least is not None:
                return f"a finite number {'>' if self.open_least else '≥'} {self.least:g}"
            return "a finite number"
        return "text"

    def check(self, value: Any) -> Any:
        """`value` (normalised: a float for a number) if the declaration allows it, else an
        :class:`OptionValueError`."""
        if value is None and self.optional:
            return None
        if self.kind == "choice":
            if value not in self.choices:
                raise OptionValueError(f"unknown {{option}} {value!r}; use {self.expected()}")
            return value
        if self.kind == "flag":
            if not isinstance(value, (bool, np.bool_)):
                raise OptionValueError(f"{{option}} is {value!r}; expected {self.expected()}")
            return bool(value)
        if self.kind == "whole":
            if self.or_origins and isinstance(value, Sequence) and not isinstance(value, str):
                return value
            whole = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
            if not whole or not self._within(float(value)) or (self.even and value % 2):
                raise OptionValueError(f"{{option}} is {value!r}; expected {self.expected()}")
            return int(value)
        if self.kind == "number":
            number = math.nan if isinstance(value, str) else _float(value)
            if not (math.isfinite(number) and self._within(number)):
                raise OptionValueError(f"{{option}} is {value!r}; expected {self.expected()}")
            return number
        return value

    def parse(self, text: str) -> Any:
        """The value a flag's `text` gives, checked (:meth:`check`); an
        :class:`OptionValueError` naming the text as given."""
        if self.optional and text == NONE_TEXT:
            return None
        if self.kind not in ("whole", "number"):
            return self.check(text)
        try:
            return self.check(int(text) if self.kind == "whole" else float(text))
        except (ValueError, OptionValueError):
            # the message quotes the text as given, not the number it was read as
            raise OptionValueError(f"{{option}} is {text!r}; expected {self.expected()}") from None

    def _within(self, value: float) -> bool:
        if self.least is not None and (
            value < self.least or (self.open_least and value == self.least)
        ):
            return False
        return not (
            self.most is not None and (value > self.most or (self.open_most and value == self.most))
        )


OPTION_TABLE: tuple[OptionSpec, ...] = (
    OptionSpec(
        "bands",
        "--bands",
        "text",
        "equally spaced band centres, nm, e.g. 400,450,500,550,600,650,700",
        optional=True,
        metavar="NM,NM,…",
        default_help="chosen from the camera response's bandlimit, or a sensor map's own bands",
    ),
    OptionSpec(
        "correction",
        "--correction",
        "choice",
        "model: the dispersion inside the reconstruction problem; warp: solve without the "
        "dispersion, then warp the result onto the reference band (a model of either "
        "direction)",
        choices=CORRECTIONS,
        metavar="|".join(CORRECTIONS),
    ),
    OptionSpec(
        "extrapolation",
        "--extrapolation",
        "choice",
        "where the dispersion model would be evaluated outside the wavelengths and image area "
        "it was calibrated on: clamp to the domain's edge, refuse (stop before any work), or "
        "allow (the fitted function); reported in the output either way",
        choices=EXTRAPOLATIONS,
        metavar="|".join(EXTRAPOLATIONS),
    ),
    OptionSpec(
        "interpolation",
        "--interpolation",
        "choice",
        "sampling weights of Φ: Keys' cubic convolution, which shifts without bilinear's "
        "blur and the overshoot it causes at edges, or bilinear (as the thesis), faster",
        choices=INTERPOLATIONS,
        metavar="|".join(INTERPOLATIONS),
    ),
    OptionSpec(
        "prior",
        "--prior",
        "choice",
        "EdgeL2: the L2 prior weighted by the raw image's own edges, which fills unsampled "
        "pixels along edges rather than across them; a prior of the thesis ("
        + ", ".join(p for p in PRIORS if p not in ("EdgeL2", "VTV"))
        + "); or VTV, vectorial total variation (edges shared by all bands, slower)",
        choices=tuple(PRIORS),
        metavar="PRIOR",
    ),
    OptionSpec(
        "nonneg",
        "--nonneg",
        "flag",
        "constrain the latent image to be non-negative",
    ),
    OptionSpec(
        "spectral_smoothness",
        "--spectral-smoothness",
        "number",
        "weight σ of the spectral roughness term, which picks the smoothest of the spectra the "
        "data and the prior cannot tell apart without pulling each patch's mean colour "
        "(beyond the thesis), in normalised units; 0 is the thesis' problem",
        least=0.0,
        optional=True,
        metavar="SIGMA",
        default_help="1e-3 with --latent spectral, 0 with --latent colour",
        example="1e-3",
    ),
    OptionSpec(
        "band_balance",
        "--band-balance",
        "number",
        "γ of the L2 and EdgeL2 priors' band balance (beyond the thesis): each band's "
        "spatial smoothing is weighed by its share of the camera's response to the power γ, "
        "so that bands the camera barely senses keep their edges; 0 smooths every band alike, "
        "as the thesis",
        least=0.0,
        most=1.0,
        optional=True,
        metavar="GAMMA",
        default_help="0.5 for EdgeL2 with spectral smoothness σ > 0, else 0",
        example="0.5",
    ),
    OptionSpec(
        "weights",
        "--weights",
        "text",
        "regularisation weights: chosen by a search on the most textured patch with the "
        "demosaicing criterion against bilinear demosaicing (auto:dmc, the thesis') or "
        "against Menon's or Malvar's demosaic (auto:dmc-menon, auto:dmc-malvar: sharper "
        "weights for --prior VTV; not for narrow-band light), or the minimum-distance "
        "criterion (auto:mdc); or fixed, one per prior term, in normalised units (fixed:W)",
        metavar="auto:dmc|auto:dmc-menon|auto:dmc-malvar|auto:mdc|fixed:W[,W…]",
    ),
    OptionSpec(
        "latent",
        "--latent",
        "choice",
        "spectral: a spectral image, one channel per band; colour: direct colour estimation, "
        "the camera's R, G, B without the dispersion",
        choices=LATENTS,
        metavar="|".join(LATENTS),
    ),
    OptionSpec(
        "reference",
        "--reference",
        "choice",
        "mean-colour: the reference spectrum from the mean colour, a smooth spectrum fitted "
        "to the image's mean colour that the image is reconstructed relative to, which puts "
        "the bands on one scale; none: the plain problem; "
        "auto: mean-colour where the response leaves the bands' scales unknown (a sensor map "
        "with the same G in every band, the thesis' normalisation), else none",
        choices=REFERENCES,
        optional=True,
        metavar="auto|mean-colour|none",
    ),
    OptionSpec(
        "kernel",
        "--kernel",
        "choice",
        "kernel of the spectral basis (a sensor map's bands are discrete whatever it is)",
        choices=KERNELS,
        metavar="|".join(KERNELS),
    ),
    OptionSpec(
        "rtol",
        "--rtol",
        "number",
        "ADMM relative tolerance per patch",
        least=0.0,
        most=1.0,
        open_least=True,
        open_most=True,
        optional=True,
        metavar="TOL",
        default_help="1e-5, within 1e-4 of the optimum; 1e-4 at spectral smoothness 0",
        example="1e-4",
    ),
    OptionSpec(
        "max_iter",
        "--max-iter",
        "whole",
        "ADMM iteration limit per patch",
        least=1,
        metavar="N",
    ),
    OptionSpec(
        "exact",
        "--exact",
        "flag",
        "--exact: with --nonneg and an L2-type prior, solve every patch exactly "
        "(projected-Newton active-set method) instead of by ADMM alone (at spectral "
        "smoothness 0 ADMM stops short of the optimum at small weights; the exact solve "
        "costs several times more); --no-exact: every patch by ADMM",
        optional=True,
        default_help="with σ > 0, patches with few values at zero are solved exactly and "
        "directly, the rest by ADMM",
    ),
    OptionSpec(
        "patch_px",
        "--patch-px",
        "whole",
        "patch size, px (small patches suit the FFT preconditioner of the dispersion-aware solve)",
        least=8,
        even=True,
        metavar="N",
    ),
    OptionSpec(
        "pad_px",
        "--pad-px",
        "whole",
        "overlap on each side of a patch, px; at least twice the largest dispersion",
        least=2,
        even=True,
        optional=True,
        metavar="N",
        default_help="the smallest even value ≥ 8 that is",
    ),
    OptionSpec(
        "flat_threshold",
        "--flat-threshold",
        "number",
        "largest same-channel step above the image's noise, relative to a patch's level, "
        "below which the patch counts as flat and skips Φ (none: never skip)",
        least=0.0,
        optional=True,
        metavar="T",
    ),
    OptionSpec(
        "weight_patches",
        "--weight-patches",
        "whole",
        "how many of the most textured patches the weights are chosen on",
        least=1,
        or_origins=True,
        metavar="N",
    ),
    OptionSpec(
        "weight_patch_px",
        "--weight-patch-px",
        "whole",
        "size of those patches, px",
        least=8,
        even=True,
        metavar="N",
    ),
)
"""Every declared option, in ``--help`` order."""

OPTIONS = {spec.name: spec for spec in OPTION_TABLE}
"""The declarations by keyword."""


def flags(extra: dict[str, str] | None = None) -> dict[str, str]:
    """How the command line spells each option it sets: ``{keyword: flag}``."""
    names = {spec.name: spec.flag for spec in OPTION_TABLE if spec.flag is not None}
    return {**names, **(extra or {})}


def parse_bands(text: str) -> list[float]:
    """``"400,450,500"`` → [400.0, 450.0, 500.0]: finite, ≥ 2, increasing; an
    :class:`OptionValueError` otherwise (spacing and coverage are the response's to check)."""
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) for v in values):
        raise OptionValueError(
            f"{{option}} {text!r}: expected comma-separated wavelengths in nm, "
            "e.g. 400,450,500,550,600,650,700"
        )
    if len(values) < 2 or any(b <= a for a, b in itertools.pairwise(values)):
        raise OptionValueError(
            f"{{option}} {text!r}: give ≥ 2 band centres in increasing order, "
            "e.g. 400,450,500,550,600,650,700"
        )
    return values


PARSERS: dict[str, Callable[[str], Any]] = {"bands": parse_bands}
"""Flag parsers of the ``text`` options that have one (the others pass their text on)."""


def _float(value: Any) -> float:
    if isinstance(value, bool):
        return math.nan
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan
