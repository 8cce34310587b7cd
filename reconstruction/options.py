"""The options of a reconstruction, validated once (:class:`ReconstructOptions`).

:func:`~reconstruction.reconstruct.reconstruct` takes them as keywords or as one object;
``labkit reconstruct`` builds the object from its command line. Every check that does not
need the raw image happens when the object is made, so a bad option fails before any file
is read or any work starts; :meth:`ReconstructOptions.check_image` adds those that need
the image's size (the dispersion model's calibration size, the patch overlap). Errors are
:class:`OptionError`, whose message names the option as the caller spells it: the keyword
for Python, the flag for the command line (:meth:`OptionError.message`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from calibration.dispersion_model import DispersionModel, load_dispersion_model
from calibration.model_domain import DomainUse, domain_use
from calibration.sensitivity import is_sensitivity_file, load_response
from labkit.cfa import check_layout
from labkit.errors import ConfigError, DataError
from labkit.spectra import Spectra
from reconstruction.choices import Choices, resolve_choices
from reconstruction.model.image_formation import DISCRETE, LatentSpace
from reconstruction.model.prior_terms import PriorTerm, prior_terms
from reconstruction.option_table import (
    CORRECTIONS,
    LATENTS,
    OPTION_TABLE,
    REFERENCES,
    OptionValueError,
)
from reconstruction.solve.weights import CRITERIA

__all__ = ["CORRECTIONS", "LATENTS", "REFERENCES", "OptionError", "ReconstructOptions"]


class OptionError(ConfigError, DataError):
    """An invalid reconstruction option.

    A :class:`~labkit.errors.ConfigError`, and a :class:`~labkit.errors.DataError` as
    :func:`~reconstruction.reconstruct.reconstruct` raised for bad options before the
    options object existed. ``str(error)`` names the option by its keyword;
    :meth:`message` by any other spelling.
    """

    def __init__(self, option: str, template: str) -> None:
        self.option = option
        self.template = template
        super().__init__(self.message())

    def message(self, names: Mapping[str, str] | None = None) -> str:
        """The message with every option called ``names[keyword]`` (default: its keyword).

        The template names options as ``{option}`` (the failing one) or ``{keyword}``; any
        other braces (e.g. in a value it quotes) are left as they are.
        """
        names = names or {}

        def name(match: re.Match) -> str:
            key = self.option if match[1] == "option" else match[1]
            return names.get(key, key)

        return _PLACEHOLDER.sub(name, self.template)


def parse_weights(
    weights: str | Sequence[float], count: int
) -> tuple[str, tuple[float, ...] | None]:
    """``"auto:dmc"`` → ("dmc", None); ``"fixed:0.1,0.2"`` or a sequence → ("fixed", values)."""
    if isinstance(weights, str):
        kind, _, rest = weights.partition(":")
        if kind == "auto":
            if rest not in CRITERIA:
                raise DataError(
                    f"unknown weight criterion {rest!r} in {weights!r}; use auto:dmc, "
                    "auto:dmc-malvar, auto:dmc-menon, auto:mdc or auto:msec"
                )
            return rest, None
        if kind != "fixed":
            raise DataError(
                f"weights {weights!r}: use auto:dmc|auto:dmc-menon|auto:mdc|auto:msec or "
                "fixed:W1[,W2]"
            )
        try:
            values = tuple(float(v) for v in rest.split(","))
        except ValueError:
            raise DataError(f"weights {weights!r}: fixed weights must be numbers") from None
    else:
        values = tuple(float(v) for v in weights)
    if len(values) != count:
        raise DataError(f"the prior has {count} term(s) but {len(values)} weight(s) were given")
    if any(not np.isfinite(v) or v < 0 for v in values):
        raise DataError(f"weights must be finite and ≥ 0, got {values}")
    return "fixed", values


@dataclass(frozen=True, eq=False)
class ReconstructOptions:
    """What to reconstruct and how: every option of
    :func:`~reconstruction.reconstruct.reconstruct` but the image, the truth and the
    progress callback. Fields keep the values given; the properties give the values in
    effect (:attr:`smoothness`, :attr:`tolerance`, :attr:`model`, …).

    Parameters
    ----------
    cfa : str
        Bayer layout (RGGB, GRBG, GBRG, BGGR).
    response : Spectra, str, Path or spectral distributions, optional
        Camera response R, G, B over wavelength; required for ``latent="spectral"``. A
        :class:`~labkit.spectra.Spectra`; a colour-science camera dataset name (e.g.
        ``"Nikon 5100 (NPL)"``); a response CSV ``wavelength_nm,R,G,B``; the
        ``sensitivity.yaml``/``.csv`` of ``labkit calibrate sensitivity`` (its bands are
        then the default `bands`); colour-science ``MultiSpectralDistributions`` (e.g.
        ``colour.MSDS_CAMERA_SENSITIVITIES[name]``) or three ``SpectralDistribution``; or
        ``(wavelengths_nm, values)`` with values of shape (n, 3).
    bands : sequence of float, optional
        Band centres, nm, equally spaced; default chosen from the response (§3.3.2).
    dispersion : DispersionModel or path, optional
        ``to_reference`` model of this camera and image size: spectral for
        ``latent="spectral"``, colour-channel for ``latent="colour"``. None: no Φ.
    correction : {"model", "warp"}
        ``"model"``: Φ inside the problem (3.1)/(3.27). ``"warp"``: the §3.9.2 variant —
        solve without Φ (sparser, faster, immune to model errors), then warp every latent
        channel onto the reference geometry (bilinear; spectral channels at their band
        centres); the model may then have either direction.
    extrapolation : {"clamp", "refuse", "allow"}
        Where Φ's model would be evaluated outside the domain it was calibrated on
        (wavelengths beyond its bands, pixels farther than one keypoint spacing from its
        keypoints; :mod:`calibration.model_domain`): move those inputs to the domain's edge
        (default), stop with an error, or evaluate the fitted function there. Any of them
        is reported in the log's ``warnings`` and ``dispersion.domain``.
    interpolation : {"cubic", "bilinear"}
        Sampling weights of Φ (``correction="model"``): Keys' cubic convolution (default,
        beyond the thesis), which shifts without bilinear's blur and so without the
        overshoot it provokes at edges, or bilinear, as the thesis (§3.2.5), at a lower
        run time (figures in docs/notes/solver.md).
    prior : str
        ``EdgeL2`` (default): the L2 prior weighted per pixel and direction by the raw
        image's own edges (:mod:`reconstruction.model.edge_weights`), so that pixels a Bayer
        channel does not sample are filled along edges rather than across; a combination
        of Table 3.1 (``L1``, ``L2``, ``Lap1``, ``Lap2``, ``L1L1``, ``L2L2``,
        ``L1SpatialLap2``, ``L1SpectralLap2``); or ``VTV``: vectorial total variation
        ‖∇xy I‖₂,₁, which places edges at the same position in every band
        (:mod:`reconstruction.model.prior_terms`).
    nonneg : bool
        Constrain the latent image to be non-negative.
    spectral_smoothness : float, optional
        σ of the spectral roughness term σ‖S I‖² (normalised units; beyond the thesis;
        :class:`~reconstruction.model.operators.SpectralRoughness`): among the spectra the data
        and the prior cannot tell apart, the solve picks the smoothest rather than the
        smallest, without pulling a patch's mean colour. Default
        :data:`~reconstruction.model.problem.SUGGESTED_SMOOTHNESS` (1e-3) for a spectral latent
        image: lower spectral, colour and edge errors than σ = 0, weights the DMC
        determines well, and an optimum the default solve reaches within 1e-4; on the
        validation matrix (``labkit bench matrix``) the lower spectral error on every row,
        narrow-band light included, though there it biases the raw colour (measurements
        in :mod:`reconstruction.model.problem`). 0 is the thesis' problem. Spectral latent only
        (default 0 for ``latent="colour"``). The log's ``choices`` records the image's
        mean-colour misfit of (6.1) as evidence.
    band_balance : float, optional
        γ in [0, 1] of the L2 and EdgeL2 priors' band balance
        (:mod:`reconstruction.model.band_balance`; beyond the thesis): band b's spatial gradient
        is weighed by ``f_b ∝ (its share of the camera's response) ** γ``, so that a band
        the camera barely senses is not smoothed over many more pixels than the others.
        Default :data:`~reconstruction.model.band_balance.BAND_BALANCE` (0.5) for EdgeL2 with
        spectral smoothness σ > 0, which ties a weakly sensed band to its neighbours; 0
        (every band alike, the thesis) otherwise, the only value the other priors, σ = 0
        and a colour latent image take. The plain L2 prior takes it if asked for, but not
        by default: its weight search on the real frames then picks a weight four times
        smaller and a worse image (docs/notes/band-balance.md).
    weights : str or sequence of float
        ``"auto:dmc"`` (default; the thesis' demosaicing criterion against bilinear
        demosaicing), ``"auto:dmc-menon"`` / ``"auto:dmc-malvar"`` (the same against a
        stronger demosaic: sharper weights for edge-preserving priors, e.g. VTV; not for
        narrow-band light), ``"auto:mdc"``, ``"auto:msec"`` (needs `truth`), or fixed
        weights (``"fixed:0.01"`` or a sequence), in normalised units
        (:mod:`reconstruction.solve.weights`).
    latent : {"spectral", "colour"}
        Problem (3.1), or direct colour estimation (3.27).
    reference : {"auto", "mean-colour", None}
        ``"mean-colour"``: the §6.3 variant (reconstruct relative to a smooth spectrum
        fitted to the image's mean colour, which puts the bands on one scale); None: the
        plain problem; ``"auto"`` (default): mean-colour where the response leaves the
        bands' relative scales unknown — a sensor map with the same G in every band, the
        thesis' normalisation (:func:`~reconstruction.choices.unlevelled_green`) — else
        None. The choice is logged in ``choices``.
    kernel : {"gaussian", "sinc"}
        Kernel of the spectral basis. A response tabulated at exactly the band centres (a
        sensor map, :meth:`calibration.ChannelSensitivity.as_response`) is a discrete model
        whatever the kernel (:class:`~reconstruction.model.image_formation.LatentSpace`).
    rtol : float, optional
        ADMM relative tolerance per patch; default
        :func:`~reconstruction.solve.solvers.admm.default_rtol`: 1e-5 when
        ``spectral_smoothness`` > 0, which brings each patch's objective within 1e-4 of
        its optimum for every prior, and 1e-4 at σ = 0.
    max_iter : int
        ADMM iteration limit per patch.
    exact : bool, optional
        With non-negativity and L2-type priors, solve every patch exactly (projected-Newton
        active-set method; the ``"exact"`` method of :func:`~reconstruction.solve.solvers.solve`).
        None (default): with spectral smoothness σ > 0, patches whose initial estimate has
        few values at zero are solved exactly and directly (``direct``: no ADMM, faster
        than ADMM's solve to within 1e-4), the others by ADMM; at σ = 0, ADMM. At σ = 0
        the exact optimum is the poorer image (docs/notes/solver.md, spectral smoothness),
        and reaching it with Φ costs several times the ADMM solve.
    patch_px : int
        Patch size, px (even). Small patches suit the FFT preconditioner: across a patch
        the dispersion departs less from its mean translation.
    pad_px : int, optional
        Overlap on each side, px (even); default the smallest even value ≥ 8 and ≥ twice the
        model's largest displacement.
    flat_threshold : float or None
        Largest same-channel step above the image's noise, relative to a patch's mean
        level, below which the patch counts as flat and skips Φ (None: never skip).
    weight_patches : int or sequence of (row, col)
        How many representative patches to select weights on (chosen by texture), or
        their origins.
    weight_patch_px : int
        Size of those patches, px (even).
    scheduler : str or distributed.Client, optional
        Dask scheduler of the patches (see
        :func:`~reconstruction.solve.patches.reconstruct_patches`); default
        :func:`~reconstruction.solve.patches.default_scheduler`.

    Raises
    ------
    OptionError
        An option is invalid, or options contradict each other; the message says which
        and how to fix it.
    """

    cfa: str
    response: Spectra | str | Path | Any | None = None
    bands: Sequence[float] | None = None
    dispersion: DispersionModel | str | Path | None = None
    correction: str = "model"
    extrapolation: str = "clamp"
    interpolation: str = "cubic"
    prior: str = "EdgeL2"
    nonneg: bool = True
    spectral_smoothness: float | None = None
    band_balance: float | None = None
    weights: str | Sequence[float] = "auto:dmc"
    latent: str = "spectral"
    reference: str | None = "auto"
    kernel: str = "gaussian"
    rtol: float | None = None
    max_iter: int = 1000
    exact: bool | None = None
    patch_px: int = 48
    pad_px: int | None = None
    flat_threshold: float | None = 0.01
    weight_patches: Sequence[tuple[int, int]] | int = 1
    weight_patch_px: int = 64
    scheduler: str | object | None = None

    def __post_init__(self) -> None:
        try:
            layout = check_layout(self.cfa)
        except DataError as error:
            raise OptionError("cfa", f"{{option}}: {error}") from None
        object.__setattr__(self, "cfa", layout)
        self._load_response()
        for spec in OPTION_TABLE:  # each option's own type and bounds, as the CLI checks them
            try:
                object.__setattr__(self, spec.name, spec.check(getattr(self, spec.name)))
            except OptionValueError as error:
                raise OptionError(spec.name, error.template) from None
        if self.bands is not None:
            object.__setattr__(self, "bands", tuple(float(b) for b in self.bands))
        self.space  # noqa: B018  (built now: a response that cannot serve fails here)
        self._check_weights()
        if self.spectral_smoothness and self.latent != "spectral":
            raise OptionError(
                "spectral_smoothness",
                "{option} applies to {latent} spectral (bands along λ); give 0, or leave it "
                "out, with {latent} colour",
            )
        self._check_band_balance()
        if self.exact and self.l1_terms:
            raise OptionError(
                "exact",
                f"the exact finish ({{option}}) applies to L2-type priors (L2, Lap2, L2L2); "
                f"{self.prior} has L1 terms, which only ADMM solves: drop it or pick an "
                "L2-type prior",
            )
        if self.correction == "warp" and self.dispersion is None:
            raise OptionError(
                "correction", "{option} warp needs a dispersion model ({dispersion}) to warp with"
            )
        self.model  # noqa: B018  (loaded now: a missing or malformed file fails here)

    def _load_response(self) -> None:
        """Make `response` a Spectra, keeping its name (a path or dataset) for the records;
        a sensor map's bands become the default bands."""
        source = self.response
        object.__setattr__(self, "_response_source", "in memory" if source is not None else None)
        if source is None or isinstance(source, Spectra):
            return
        try:
            response = load_response(source)
        except DataError as error:
            raise OptionError("response", f"{{option}}: {error}") from None
        object.__setattr__(self, "response", response)
        if isinstance(source, str | Path):
            object.__setattr__(self, "_response_source", str(source))
            if self.bands is None and self.latent == "spectral" and is_sensitivity_file(source):
                object.__setattr__(self, "bands", tuple(float(w) for w in response.wavelengths))

    @property
    def response_source(self) -> str | None:
        """Where the response came from: its path or dataset name, ``"in memory"`` or None."""
        return getattr(self, "_response_source", None)

    def _check_band_balance(self) -> None:
        gamma = self.band_balance
        if not gamma:
            return
        if self.latent != "spectral":
            raise OptionError(
                "band_balance",
                "{option} applies to {latent} spectral (bands along λ); give 0, or leave it "
                "out, with {latent} colour",
            )
        if self.smoothness == 0:
            raise OptionError(
                "band_balance",
                "{option} needs spectral smoothness ({spectral_smoothness} > 0), which ties a "
                "weakly sensed band to its neighbours; at {spectral_smoothness} 0 the weight "
                "search picks a weight that leaves such bands noisy: give {option} 0, or "
                "leave it out",
            )
        if not any(t.balanceable for t in self.terms):
            raise OptionError(
                "band_balance",
                f"{{option}} applies to the L2 and EdgeL2 priors; {self.prior} has no L2 "
                "gradient term: give 0, or leave it out",
            )

    def _check_weights(self) -> None:
        count = len(self.terms)
        text = self.weights if isinstance(self.weights, str) else None
        kind = None if text is None else text.partition(":")[0]
        if kind is not None and kind not in ("auto", "fixed"):
            raise OptionError(
                "weights",
                f"{{option}} {text!r}: use auto:dmc, auto:dmc-menon, auto:dmc-malvar, "
                "auto:mdc, auto:msec or fixed:W[,W…] (one weight per prior term)",
            )
        given = len(text.partition(":")[2].split(",")) if kind == "fixed" else None
        if text is None:
            given = len(self.weights)
        if given is not None and given != count:
            raise OptionError(
                "weights",
                f"{{option}} {self.weights!r}: {{prior}} {self.prior} has {count} term(s), so "
                f"give {count} weight(s)",
            )
        try:
            self._parsed_weights  # noqa: B018  (parsed now: its errors name the option)
        except DataError as error:
            raise OptionError("weights", f"{{option}}: {error}") from None

    # -- derived -----------------------------------------------------------------------
    @cached_property
    def space(self) -> LatentSpace:
        """The latent space (before the §6.3 reference scale, which needs the image)."""
        if self.latent == "colour":
            if self.bands is not None:
                raise OptionError(
                    "bands", "direct colour estimation (latent colour) takes no {option}"
                )
            return LatentSpace.colour()
        if self.response is None:
            raise OptionError(
                "response", "spectral reconstruction needs the camera response ({option})"
            )
        try:
            space = LatentSpace.spectral(self.response, self.bands, kernel=self.kernel)
        except DataError as error:
            option = "bands" if self.bands is not None else "response"
            raise OptionError(option, f"{{option}}: {error}") from None
        light = filter_light(space.centres_nm, self.model) if space.kernel == DISCRETE else None
        return space if light is None else space.with_band_light(light)

    @cached_property
    def model(self) -> DispersionModel | None:
        """The dispersion model (loaded when `dispersion` is a path), clamped to its
        calibrated domain unless `extrapolation` is ``"allow"``."""
        if self.dispersion is None:
            return None
        model = self.dispersion
        if not isinstance(model, DispersionModel):
            model = load_dispersion_model(model)
        return model.within_domain(self.extrapolation)

    def domain_use(self, shape: tuple[int, int]) -> DomainUse | None:
        """How far the model's use on a `shape` image reaches beyond its domain (None
        without a model); raises for ``extrapolation="refuse"`` when it does."""
        model = self.model
        if model is None:
            return None
        space = self.space
        if space.kind == "colour":
            waves = None
        elif space.kernel == DISCRETE or self.correction == "warp":
            waves = space.phi_nm
        else:
            waves = space.support_nm  # the ends of the range Φ is sampled over
        return domain_use(
            model,
            shape=shape,
            wavelengths_nm=waves,
            policy=self.extrapolation,
            fix="{extrapolation} clamp (the default)",
        )

    @property
    def solve_model(self) -> DispersionModel | None:
        """The dispersion model inside the problem (None for §3.9.2's warp afterwards)."""
        return self.model if self.correction == "model" else None

    @property
    def dispersion_source(self) -> str | None:
        """Where the model came from: its path, ``"in memory"`` or None."""
        if self.dispersion is None:
            return None
        return str(self.dispersion) if isinstance(self.dispersion, (str, Path)) else "in memory"

    @cached_property
    def terms(self) -> tuple[PriorTerm, ...]:
        """The prior's terms (Table 3.1)."""
        try:
            return prior_terms(self.prior, channels=self.space.channels)
        except DataError as error:
            raise OptionError("prior", f"{{option}}: {error}") from None

    @cached_property
    def choices(self) -> Choices:
        """The automatic choices that need no image, resolved
        (:func:`~reconstruction.choices.resolve_choices`; the reconstruction resolves them
        again with the image's evidence)."""
        return resolve_choices(self)

    @property
    def smoothness(self) -> float:
        """σ in effect before the image is seen (:attr:`choices`)."""
        return self.choices.smoothness

    @property
    def balance(self) -> float:
        """γ of the band balance in effect before the image is seen (:attr:`choices`)."""
        return self.choices.balance

    @property
    def tolerance(self) -> float:
        """ADMM's relative tolerance in effect before the image is seen (:attr:`choices`)."""
        return self.choices.rtol

    @property
    def l1_terms(self) -> bool:
        return any(t.norm == 1 for t in self.terms)

    @cached_property
    def _parsed_weights(self) -> tuple[str, tuple[float, ...] | None]:
        return parse_weights(self.weights, len(self.terms))

    @property
    def criterion(self) -> str:
        """The weight criterion (``"fixed"`` for fixed weights)."""
        return self._parsed_weights[0]

    @property
    def fixed_weights(self) -> tuple[float, ...] | None:
        return self._parsed_weights[1]

    @property
    def direct(self) -> bool:
        """Patches with few values at zero are solved exactly and directly (:attr:`choices`)."""
        return self.choices.direct

    @property
    def exact_weights(self) -> bool:
        """Weights are scored on exact optima (:attr:`choices`)."""
        return self.choices.exact_weights

    def check_image(
        self, shape: tuple[int, int], *, where: str = "the dispersion model"
    ) -> DomainUse | None:
        """The checks that need the raw image's size `shape` (rows, cols); returns how far
        the dispersion model's use reaches beyond its domain (:meth:`domain_use`). `where`
        names the dispersion model in messages."""
        check_dispersion_model(
            self.model, shape, self.latent, where=where, correction=self.correction
        )
        try:
            return self.domain_use(shape)
        except DataError as error:
            raise OptionError("extrapolation", f"{where}: {error}") from None

    def as_dict(self) -> dict[str, Any]:
        """The options as given (the response and dispersion model by name), JSON-ready."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "response" and value is not None:
                value = self.response_source
            elif f.name == "dispersion":
                value = self.dispersion_source
            elif f.name == "scheduler" and value is not None and not isinstance(value, str):
                value = type(value).__name__
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out


def filter_light(centres_nm: np.ndarray, model: DispersionModel | None) -> np.ndarray | None:
    """The effective wavelength of the filter behind each band, from `model`'s record of its
    calibration (``provenance.bands_table``: each filter's nominal and effective wavelength),
    or None when the model records none of these bands.

    A response tabulated per filter (a sensor map, thesis Algorithm 12) names its bands by
    the filters' nominal wavelengths, but the light each band holds — and so its dispersion
    — sits at the filter's effective wavelength (filter × light × camera; e.g. 686.6 nm
    for a "700 nm" filter). Bands the table does not name keep their centre.
    """
    if model is None or model.variables != "xylambda":
        return None
    table = model.provenance.get("bands_table") or []
    effective = {}
    for row in table:
        if not isinstance(row, Mapping):
            continue
        nominal, light = row.get("nominal_nm"), row.get("wavelength_nm")
        if isinstance(nominal, (int, float)) and isinstance(light, (int, float)):
            if math.isfinite(nominal) and math.isfinite(light):
                effective[float(nominal)] = float(light)
    light_nm = np.array(
        [
            next((light for nominal, light in effective.items() if abs(nominal - c) <= 0.5), c)
            for c in np.asarray(centres_nm, dtype=np.float64)
        ]
    )
    if np.allclose(light_nm, centres_nm):
        return None
    return light_nm


def check_dispersion_model(
    model: DispersionModel | str | Path | None,
    shape: tuple[int, int],
    kind: str,
    *,
    where: str = "the dispersion model",
    correction: str = "model",
) -> DispersionModel | None:
    """Load `model` (if a path) and check it suits a `kind` reconstruction of `shape` px.

    Φ inside the problem (``correction="model"``) needs a ``to_reference`` model; warping
    afterwards (``"warp"``) takes either direction.
    """
    if model is None:
        return None
    if not isinstance(model, DispersionModel):
        model = load_dispersion_model(model)
    if tuple(model.image_shape) != tuple(shape):
        raise DataError(
            f"{where} was calibrated for {model.image_shape[0]}×{model.image_shape[1]} px "
            f"images but the raw image is {shape[0]}×{shape[1]} px; use a model calibrated "
            "with this camera at this image size"
        )
    names = {"xylambda": "spectral", "xy": "colour-channel"}
    wanted = "xylambda" if kind == "spectral" else "xy"
    wrong_kind = model.variables != wanted
    wrong_direction = correction == "model" and model.direction != "to_reference"
    if not (wrong_kind or wrong_direction):
        return model
    # one message for both problems, so that following it cannot meet the other; options
    # are named as the caller spells them (OptionError.message: --latent or latent)
    have = names.get(model.variables, model.variables)
    reference = "G" if kind == "colour" else "600"
    if wrong_kind and wrong_direction:
        template = (
            f"{where} is a {have} {model.direction} model, but a {kind} reconstruction "
            f"({{latent}} {kind}) with {{correction}} model needs a {names[wanted]} "
            f"to_reference model: calibrate one with `labkit calibrate dispersion HDR "
            f"--reference {reference} --direction to_reference`, or give a {names[wanted]} "
            f"model of either direction with {{correction}} warp (warping after the "
            "reconstruction)"
        )
    elif wrong_kind:
        other = "spectral" if kind == "colour" else "colour"
        template = (
            f"{where} is a {have} model, but a {kind} reconstruction ({{latent}} {kind}) "
            f"needs a {names[wanted]} model: calibrate one with `labkit calibrate dispersion "
            f"HDR --reference {reference}"
            + (" --direction to_reference`" if correction == "model" else "`")
            + f", or reconstruct with {{latent}} {other}"
        )
    else:
        template = (
            f"{where} is a {model.direction} model, but {{correction}} model needs a "
            "to_reference one: recalibrate with `labkit calibrate dispersion --direction "
            "to_reference`, or warp after the reconstruction with {correction} warp"
        )
    raise OptionError("dispersion", template)


_PLACEHOLDER = re.compile(
    r"\{(option|" + "|".join(f.name for f in fields(ReconstructOptions)) + r")\}"
)
