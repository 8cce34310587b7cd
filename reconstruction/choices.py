"""Every automatic choice of a reconstruction, made in one place (:func:`resolve_choices`).

:class:`~reconstruction.options.ReconstructOptions` holds what the caller asked for, with
``None`` (or a default) where the caller left a choice to labkit; :class:`Choices` holds
what is in effect: one :class:`Choice` per setting, with its value, where it came from
(given, the default, evidence in the image, or following from other choices) and why, in
words and numbers. :func:`~reconstruction.reconstruct.reconstruct` resolves the options
once, before any work, logs every choice in ``log.json`` (``choices``), and the layers
below (:class:`~reconstruction.solve.patches.SolverOptions`,
:func:`~reconstruction.model.image_formation.build_formation`,
:class:`~reconstruction.model.operators.Dispersion`) take these values explicitly: they have no
defaults of their own to disagree with.

Every choice can be overridden by giving the option (``reconstruct(..., option=value)``,
``labkit reconstruct --option VALUE``).

The resolver reads the options through their public fields only (it is called by them, so
it does not import them).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import nnls

from labkit.cfa import channel_index
from reconstruction.model.band_balance import BAND_BALANCE
from reconstruction.model.image_formation import DISCRETE, LatentSpace
from reconstruction.model.operators import SpectralGradient
from reconstruction.model.problem import SUGGESTED_SMOOTHNESS
from reconstruction.solve.solvers.admm import default_rtol

SOURCES = {
    "given": "given",
    "default": "default",
    "image": "from the image",
    "follows": "follows from the inputs and the other choices",
}
"""Where a choice's value came from, and how a summary names it."""

MIN_PAD_PX = 8
"""Smallest default patch overlap, px."""

REFERENCE_SMOOTHING = 1e-2
"""Weight w of (6.1)'s spectral-gradient penalty, relative to ‖C‖² (normalised units)."""


@dataclass(frozen=True)
class Choice:
    """One setting in effect.

    Attributes
    ----------
    value
        The value used (JSON-ready).
    source : {"given", "default", "image", "follows"}
        Given by the caller; the default; chosen from evidence in the image; or a
        consequence of other choices (e.g. the tolerance of the chosen σ).
    reason : str
        Why, in words, with the evidence's figures.
    evidence : mapping
        The figures the choice rests on (JSON-ready), e.g. a misfit and its threshold.
    """

    value: Any
    source: str
    reason: str
    evidence: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"unknown choice source {self.source!r}; use one of {list(SOURCES)}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "value": _plain(self.value),
            "source": self.source,
            "reason": self.reason,
            "evidence": {k: _plain(v) for k, v in self.evidence.items()},
        }


@dataclass(frozen=True)
class ImageFacts:
    """What the resolver reads off one (normalised) raw image.

    Attributes
    ----------
    colour_mean : ndarray (3,) or None
        Mean raw value of each CFA channel (None when no choice needs it).
    smooth_fit : ndarray (n,) or None
        (6.1)'s smooth non-negative spectrum with that mean colour (:func:`smooth_mean_colour`).
    misfit : float or None
        ``‖C s − c‖ / ‖c‖`` of that fit.
    reach_px : float
        Largest displacement of the dispersion model over the image, px (0 without Φ).
    """

    colour_mean: np.ndarray | None = None
    smooth_fit: np.ndarray | None = None
    misfit: float | None = None
    reach_px: float = 0.0


@dataclass(frozen=True)
class Choices:
    """The settings in effect for one reconstruction (:func:`resolve_choices`).

    Index by option name (``choices["spectral_smoothness"]`` is a :class:`Choice`); the
    properties give the values the solve uses.
    """

    entries: Mapping[str, Choice]

    def __getitem__(self, name: str) -> Choice:
        return self.entries[name]

    def __contains__(self, name: object) -> bool:
        return name in self.entries

    @property
    def smoothness(self) -> float:
        return float(self["spectral_smoothness"].value)

    @property
    def balance(self) -> float:
        return float(self["band_balance"].value)

    @property
    def rtol(self) -> float:
        return self["rtol"].value

    @property
    def solver(self) -> str:
        return self["solver"].value

    @property
    def exact(self) -> bool:
        return self.solver == "exact"

    @property
    def direct(self) -> bool:
        return self.solver == "direct-or-admm"

    @property
    def exact_weights(self) -> bool:
        return bool(self["exact_weights"].value)

    @property
    def pad_px(self) -> int | None:
        return self["pad_px"].value if "pad_px" in self else None

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Every choice, JSON-ready (``log.json``'s ``choices``)."""
        return {name: choice.to_dict() for name, choice in self.entries.items()}


def resolve_choices(options: Any, *, facts: ImageFacts | None = None) -> Choices:
    """Resolve every automatic choice of `options` (a
    :class:`~reconstruction.options.ReconstructOptions`), with the image's `facts` when
    given (:func:`image_facts`; without them, the choices that need an image are those
    made before it is read).

    Returns
    -------
    Choices
        ``bands``, ``spectral_smoothness``, ``band_balance``, ``reference``, ``weights``,
        ``exact_weights``, ``rtol``, ``solver``, ``correction``, ``interpolation`` and
        ``extrapolation`` (with a dispersion model), and ``pad_px`` (with `facts`).
    """
    o = options
    entries: dict[str, Choice] = {}
    entries["bands"] = _bands(o)
    entries["spectral_smoothness"] = _smoothness(o, facts)
    smoothness = _number(entries["spectral_smoothness"].value)
    terms = o.terms
    entries["band_balance"] = _balance(o, entries["spectral_smoothness"], terms)
    entries["reference"] = _reference(o)
    criterion = o.criterion
    entries["weights"] = Choice(
        o.weights if isinstance(o.weights, str) else list(o.weights),
        "default" if o.weights == "auto:dmc" else "given",
        f"weights chosen on the most textured patch by the {criterion} criterion"
        if criterion != "fixed"
        else "fixed weights",
        {"criterion": criterion},
    )
    l1 = o.l1_terms
    exact_weights = smoothness > 0 and not l1 and criterion not in ("mdc", "fixed")
    entries["exact_weights"] = Choice(
        exact_weights,
        "follows",
        "weights scored on exact patch optima (σ > 0, L2-type prior)"
        if exact_weights
        else "weights scored on ADMM solves (σ = 0, an L1 term, the MDC or fixed weights)",
    )
    entries["rtol"] = (
        Choice(o.rtol, "given", "as asked")
        if o.rtol is not None
        else Choice(
            default_rtol(smoothness),
            "follows",
            "brings each patch within 1e-4 of its optimum"
            if smoothness > 0
            else "ADMM's default at σ = 0",
            {"spectral_smoothness": smoothness},
        )
    )
    entries["solver"] = _solver(o, smoothness, l1)
    if o.dispersion is not None:
        entries["correction"] = _named(o.correction, "model", CORRECTION_REASONS)
        if o.correction == "model":
            entries["interpolation"] = _named(o.interpolation, "cubic", INTERPOLATION_REASONS)
        entries["extrapolation"] = _named(o.extrapolation, "clamp", EXTRAPOLATION_REASONS)
    if facts is not None:
        entries["pad_px"] = _pad(o, facts)
    return Choices(entries)


def image_facts(
    y: np.ndarray, options: Any, space: LatentSpace, *, colour_gain: float, reach_px: float
) -> ImageFacts:
    """What :func:`resolve_choices` needs from the normalised raw image `y`: the mean colour
    and (6.1)'s fit to it when a choice or the §6.3 reference uses them, and Φ's reach."""
    before = options.choices  # resolved without the image
    if before["reference"].value != "mean-colour" and before.smoothness == 0:
        return ImageFacts(reach_px=reach_px)
    colour_mean = mean_colour(y, options.cfa)
    fit, misfit = smooth_mean_colour(colour_mean, colour_gain * space.colour_matrix())
    return ImageFacts(colour_mean, fit, misfit, reach_px)


# -- the rules --------------------------------------------------------------------------
CORRECTION_REASONS = {
    "model": "the dispersion inside the reconstruction problem",
    "warp": "solve without the dispersion, then warp the result",
}
INTERPOLATION_REASONS = {
    "cubic": "Keys' cubic convolution: shifts without bilinear's blur",
    "bilinear": "bilinear sampling, as the thesis",
}
EXTRAPOLATION_REASONS = {
    "clamp": "the model is evaluated inside its calibrated domain only",
    "refuse": "stop where the model would leave its calibrated domain",
    "allow": "the fitted function is evaluated outside its domain too",
}


def _named(value: str, default: str, reasons: Mapping[str, str]) -> Choice:
    """A named option's choice: the default or given, with the reason its name carries."""
    return Choice(value, "default" if value == default else "given", reasons.get(value, "as asked"))


def _bands(o: Any) -> Choice:
    space = o.space
    if space.kind == "colour":
        return Choice(None, "follows", "direct colour estimation: R, G, B, no bands")
    centres = [float(v) for v in space.centres_nm]
    evidence = {"count": len(centres), "first_nm": centres[0], "last_nm": centres[-1]}
    if o.bands is not None:
        return Choice(centres, "given", "as asked", evidence)
    if space.kernel == DISCRETE:
        return Choice(centres, "follows", "the response's own bands (a sensor map)", evidence)
    return Choice(centres, "default", "from the camera response's bandlimit", evidence)


def _smoothness(o: Any, facts: ImageFacts | None) -> Choice:
    evidence = {} if facts is None or facts.misfit is None else {"mean_colour_misfit": facts.misfit}
    if o.spectral_smoothness is not None:
        return Choice(_number(o.spectral_smoothness), "given", "as asked", evidence)
    if o.latent != "spectral":
        return Choice(0.0, "follows", "a colour latent image has no wavelength axis")
    # no switch to σ = 0 for light that looks narrow-band: on the validation matrix σ > 0
    # gave the lower spectral error on every row, narrow-band light included (docs: choices)
    return Choice(
        SUGGESTED_SMOOTHNESS,
        "default",
        "the smoothest of the spectra the data and the prior cannot tell apart",
        evidence,
    )


def _reference(o: Any) -> Choice:
    if o.reference != "auto":
        return Choice(o.reference, "given", "as asked")
    if o.latent != "spectral":
        return Choice(None, "follows", "direct colour estimation: no reference spectrum")
    green = unlevelled_green(o.space)
    if green is not None:
        return Choice(
            "mean-colour",
            "follows",
            "the response leaves the bands' scales unknown (a sensor map with the same G in "
            "every band, the thesis' normalisation), so the bands are put on one scale by the "
            "reference spectrum from the mean colour: a smooth spectrum with the image's "
            "mean colour",
            {"green_per_band": green},
        )
    return Choice(None, "default", "the response gives the bands' scales: no reference spectrum")


def unlevelled_green(space: LatentSpace) -> float | None:
    """The G value every band of a sensor map shares (the thesis' normalisation, which
    leaves the bands' relative scales unknown), or None: a response with G levels per band,
    or one that is not a sensor map."""
    if space.kind != "spectral" or space.kernel != DISCRETE:
        return None
    green = space.colour_matrix()[1]
    if green.size < 2 or not np.allclose(green, green[0], rtol=1e-6, atol=0.0):
        return None
    return float(green[0])


def _balance(o: Any, smoothness: Choice, terms: tuple) -> Choice:
    if o.band_balance is not None:
        return Choice(_number(o.band_balance), "given", "as asked")
    if o.latent != "spectral":
        return Choice(0.0, "follows", "a colour latent image has no bands to balance")
    if smoothness.value == 0:
        return Choice(0.0, "follows", "no band balance at σ = 0 (it needs σ > 0)")
    if not any(t.guided for t in terms):
        return Choice(0.0, "default", f"every band alike with the {o.prior} prior")
    return Choice(
        BAND_BALANCE, "default", "weakly sensed bands keep their edges (EdgeL2 with σ > 0)"
    )


def _solver(o: Any, smoothness: float, l1: bool) -> Choice:
    if o.exact:
        return Choice("exact", "given", "every patch by the exact active-set method")
    if o.exact is None and smoothness > 0 and o.nonneg and not l1:
        return Choice(
            "direct-or-admm",
            "follows",
            "patches with few values at zero exactly and directly, the others by ADMM "
            "(σ > 0, non-negative, L2-type prior)",
        )
    why = "σ = 0" if smoothness == 0 else "an L1 term" if l1 else "signed" if not o.nonneg else ""
    return Choice("admm", "follows" if o.exact is None else "given", f"ADMM ({why or 'as asked'})")


def _pad(o: Any, facts: ImageFacts) -> Choice:
    reach = facts.reach_px
    evidence = {"reach_px": reach}
    if o.pad_px is not None:
        return Choice(o.pad_px, "given", "as asked", evidence)
    pad = max(MIN_PAD_PX, 2 * math.ceil(reach))
    pad += pad % 2
    return Choice(
        pad,
        "image" if pad > MIN_PAD_PX else "default",
        f"≥ twice Φ's largest displacement ({reach:.1f} px) and ≥ {MIN_PAD_PX}",
        evidence,
    )


# -- evidence ---------------------------------------------------------------------------
def mean_colour(raw: np.ndarray, cfa: str) -> np.ndarray:
    """Mean raw value of each CFA channel (R, G, B)."""
    index = channel_index(cfa, raw.shape)
    return np.array([raw[index == c].mean() for c in range(3)])


def smooth_mean_colour(colour_mean: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, float]:
    """(6.1): a smooth non-negative spectrum s with the image's mean colour, and its misfit.

    Solves ``argmin_s ‖C s − c‖² + w‖∇λ s‖², s ≥ 0`` with c = `colour_mean` (the mean raw
    colour, :func:`mean_colour`) and w = :data:`REFERENCE_SMOOTHING`·‖C‖², by NNLS on the
    stacked system. Returns s and ``‖C s − c‖ / ‖c‖`` (0 when c is black).
    """
    n = colour.shape[1]
    if n == 3 and np.allclose(colour, np.diag(np.diag(colour))):
        s = np.maximum(colour_mean / np.diag(colour), 0.0)
    else:
        d = SpectralGradient((1, 1, n)).spectral_matrix
        w = REFERENCE_SMOOTHING * float(np.sum(colour**2))
        s, _ = nnls(
            np.vstack([colour, np.sqrt(w) * d]), np.concatenate([colour_mean, np.zeros(n - 1)])
        )
    size = float(np.linalg.norm(colour_mean))
    misfit = float(np.linalg.norm(colour @ s - colour_mean)) / size if size > 0 else 0.0
    return s, misfit


def reference_scale(spectrum: np.ndarray) -> np.ndarray:
    """Per-channel scale r of §6.3 from :func:`smooth_mean_colour`'s spectrum: scaled to
    mean 1 and floored at 1 % of its peak, so every channel keeps a positive scale."""
    if not np.any(spectrum > 0):
        return np.ones(spectrum.size)
    s = np.maximum(spectrum, 0.01 * spectrum.max())
    return s / s.mean()


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, np.ndarray)):
        return [_plain(v) for v in value]
    return value
