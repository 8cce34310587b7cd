"""`reconstruct`: a spectral (or colour) image from one Bayer raw image (thesis ch. 3).

Steps: validate everything (before any heavy work) → normalise → optionally fit the §6.3
reference spectrum → choose weights on representative patches (Algorithm 3, without
dispersion) → solve every patch on Dask → (§3.9.2 variant: warp the latent image onto the
reference geometry) → undo the normalisation → spectrum at the band centres, raw colour
image and a log.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import nnls

from calibration.dispersion_model import DispersionModel, load_dispersion_model
from calibration.warp import correct_channels, correct_spectral
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index, check_layout
from labkit.errors import DataError
from labkit.spectra import Spectra
from reconstruction.image_formation import LatentSpace, build_formation
from reconstruction.operators import SpectralGradient
from reconstruction.operators.dispersion import check_interpolation
from reconstruction.patches import (
    PatchOptions,
    SolverOptions,
    max_dispersion,
    noise_sigma,
    reconstruct_patches,
    texture,
)
from reconstruction.prior_terms import prior_terms
from reconstruction.problem import SUGGESTED_SMOOTHNESS, Problem
from reconstruction.solvers.admm import absolute_tolerance, default_rtol
from reconstruction.weights import CRITERIA, select_weights

MIN_PAD_PX = 8
"""Smallest default patch overlap, px."""

MAX_RAW_MAGNITUDE = 1e30
"""Largest |raw value| accepted (and smallest non-zero peak, as its inverse): the spectral
and raw-colour outputs are float32 (largest finite 3.4e38, smallest normal 1.2e-38)."""

CORRECTIONS = ("model", "warp")
"""How a dispersion model is undone: Φ inside the problem (3.1), or warping after (§3.9.2)."""

LATENTS = ("spectral", "colour")
"""What is estimated: the spectral image (3.1), or the colour image directly (3.27)."""

REFERENCES = ("mean-colour",)
"""Reference spectra of the §6.3 variant (None: the plain problem)."""

REFERENCE_SMOOTHING = 1e-2
"""Weight w of (6.1)'s spectral-gradient penalty, relative to ‖C‖² (normalised units)."""


class NarrowBandWarning(UserWarning):
    """The image's light looks narrow-band while the spectral smoothness term is on."""


NARROW_BAND_MISFIT = 0.02
"""Misfit of (6.1)'s smooth fit to the image's mean colour above which the light is taken
to be narrow-band, and a spectral smoothness σ > 0 draws a warning. Simulated rig (mean raw
colour of the ColorChecker and the textured scene): unfiltered light 0.005–0.006; through
the 10 nm filters 400 nm 0.001–0.003, 450 nm 0.081, 500 nm 0.033, 550 nm 0.18, 600 nm
0.024, 650 nm 0.11, 700 nm 0.017 (the filters at the ends of the camera's response pass
mostly leaked broadband light)."""


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct`.

    Attributes
    ----------
    spectral : ndarray (rows, cols, n) float32
        Spectrum at the band centres (spectral latent space) or raw colour R, G, B
        (colour latent space), in the raw image's units per nm (per channel for colour).
    wavelengths_nm : ndarray (n,) or None
        Band centres, nm (None for the colour latent space).
    raw_colour : ndarray (rows, cols, 3) float32
        The latent image in the camera's raw colour space, aberration-free, raw units.
    latent : LatentSpace
    log : dict
        Weights, normalisation, timings, per-patch records (JSON-ready).
    """

    spectral: np.ndarray
    wavelengths_nm: np.ndarray | None
    raw_colour: np.ndarray
    latent: LatentSpace
    log: dict = field(default_factory=dict)

    def save(
        self,
        out: str | Path,
        *,
        provenance: dict[str, Any] | None = None,
        log: dict[str, Any] | None = None,
    ) -> dict[str, Path]:
        """Write ``spectral.exr``, ``raw_colour.exr``, ``preview.png`` and ``log.json``
        into the folder `out`, atomically, the log last; returns the paths by name
        (:func:`reconstruction.output.save_reconstruction`)."""
        from reconstruction.output import save_reconstruction

        return save_reconstruction(self, out, provenance=provenance, log=log)


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


def check_raw(raw: np.ndarray, *, where: str = "the raw image") -> np.ndarray:
    """`raw` as float64 after checking it is a usable Bayer mosaic.

    Usable: a 2-D array of real numbers, even-sized, at least 8×8 px, finite, and with a
    largest |value| of 0 or within [1e-30, 1e30] (:data:`MAX_RAW_MAGNITUDE`).

    `where` names the image in messages (e.g. its file).
    """
    raw = np.asarray(raw)
    if raw.dtype.kind not in "biuf":
        raise DataError(
            f"{where} must hold real numbers, got dtype {raw.dtype}; convert it to float "
            "(complex or text values are not a raw image)"
        )
    if raw.ndim != 2:
        raise DataError(f"{where} must be a 2-D Bayer mosaic, got shape {raw.shape}")
    rows, cols = raw.shape
    if rows % 2 or cols % 2:
        raise DataError(
            f"{where} is {rows}×{cols} px; a Bayer mosaic needs an even number of rows and "
            "columns: crop one row/column (keeping the CFA phase)"
        )
    if min(rows, cols) < 8:
        raise DataError(f"{where} ({rows}×{cols} px) is too small to reconstruct (≥ 8×8 px)")
    bad = ~np.isfinite(raw)
    if bad.any():
        first = np.argwhere(bad)[0]
        raise DataError(
            f"{where} has {int(bad.sum())} NaN/Inf pixel(s), first at (row, col) = "
            f"({first[0]}, {first[1]}); repair or mask them before reconstruction"
        )
    peak = float(np.max(np.abs(raw)))
    if peak > MAX_RAW_MAGNITUDE or 0 < peak < 1 / MAX_RAW_MAGNITUDE:
        raise DataError(
            f"{where} has values up to {peak:.3g} in magnitude; the float32 outputs hold "
            f"{1 / MAX_RAW_MAGNITUDE:g} … {MAX_RAW_MAGNITUDE:g}: rescale the raw image "
            "(e.g. to counts or a fraction of saturation) before reconstruction"
        )
    return raw.astype(np.float64)


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
    if correction == "model" and model.direction != "to_reference":
        raise DataError(
            f"{where} is a {model.direction} model; reconstruction needs to_reference: "
            "recalibrate with `labkit calibrate dispersion --direction to_reference` (or "
            "warp after reconstruction: correction='warp', --correction warp)"
        )
    wanted = "xylambda" if kind == "spectral" else "xy"
    if model.variables != wanted:
        names = {"xylambda": "spectral", "xy": "colour-channel"}
        raise DataError(
            f"{where} is a {names.get(model.variables, model.variables)} model; a {kind} "
            f"reconstruction (--latent {kind}) needs a {names[wanted]} model"
        )
    return model


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


def representative_patches(raw: np.ndarray, size: int, count: int) -> list[tuple[int, int]]:
    """Origins (row, col) of the `count` most textured non-overlapping size×size windows."""
    rows, cols = raw.shape
    size = min(size, rows - rows % 2, cols - cols % 2)
    candidates = [
        (texture(raw[r : r + size, c : c + size]), r, c)
        for r in range(0, rows - size + 1, size)
        for c in range(0, cols - size + 1, size)
    ]
    candidates.sort(reverse=True)
    return [(r, c) for _, r, c in candidates[:count]]


@fixed_blas_threads
def reconstruct(
    raw: np.ndarray,
    *,
    cfa: str,
    response: Spectra | None = None,
    bands: Sequence[float] | None = None,
    dispersion: DispersionModel | str | Path | None = None,
    correction: str = "model",
    interpolation: str = "bilinear",
    prior: str = "L2",
    nonneg: bool = True,
    spectral_smoothness: float | None = None,
    weights: str | Sequence[float] = "auto:dmc",
    latent: str = "spectral",
    reference: str | None = None,
    kernel: str = "gaussian",
    rtol: float | None = None,
    max_iter: int = 1000,
    exact: bool | None = None,
    patch_px: int = 48,
    pad_px: int | None = None,
    flat_threshold: float | None = 0.01,
    weight_patches: Sequence[tuple[int, int]] | int = 1,
    weight_patch_px: int = 64,
    truth: np.ndarray | None = None,
    scheduler: str | object | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Reconstruction:
    """Reconstruct an aberration-free spectral image from one Bayer raw image (problem (3.1)).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic (e.g. an HDR raw image), even size, finite; any linear units.
    cfa : str
        Bayer layout (RGGB, GRBG, GBRG, BGGR).
    response : Spectra, optional
        Camera response R, G, B over wavelength; required for ``latent="spectral"``.
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
    interpolation : {"bilinear", "cubic"}
        Sampling weights of Φ (``correction="model"``): bilinear, as the thesis (§3.2.5),
        or Keys' cubic convolution, which shifts without bilinear's blur and so without
        the overshoot it provokes at edges (measured on the simulated ColorChecker, DMC
        weights: green edge error 0.0265 → 0.0207, spectral RMSE 0.100 → 0.087), at
        about 1.3× the run time (7.5–8.3 s against 6.0–6.3 s).
    prior : str
        A combination of Table 3.1 (``L1``, ``L2``, ``Lap1``, ``Lap2``, ``L1L1``,
        ``L2L2``, ``L1SpatialLap2``, ``L1SpectralLap2``), or ``VTV``: vectorial total
        variation ‖∇xy I‖₂,₁, which places edges at the same position in every band
        (:mod:`reconstruction.prior_terms`).
    nonneg : bool
        Constrain the latent image to be non-negative.
    spectral_smoothness : float, optional
        σ of the spectral roughness term σ‖S I‖² (normalised units; beyond the thesis;
        :class:`~reconstruction.operators.SpectralRoughness`): among the spectra the data
        and the prior cannot tell apart, the solve picks the smoothest rather than the
        smallest, without pulling a patch's mean colour. Default
        :data:`~reconstruction.problem.SUGGESTED_SMOOTHNESS` (1e-3) for a spectral latent
        image: lower spectral, colour and edge errors than σ = 0, weights the DMC
        determines well, and an optimum the default solve reaches within 1e-4. 0 is the
        thesis' problem, for narrow-band light (bandpass filters, lasers, LEDs), whose
        spectra the term biases (measurements in :mod:`reconstruction.problem`). Spectral
        latent only (default 0 for ``latent="colour"``).
    weights : str or sequence of float
        ``"auto:dmc"`` (default; the thesis' demosaicing criterion against bilinear
        demosaicing), ``"auto:dmc-menon"`` / ``"auto:dmc-malvar"`` (the same against a
        stronger demosaic: sharper weights for edge-preserving priors, e.g. VTV; not for
        narrow-band light), ``"auto:mdc"``, ``"auto:msec"`` (needs `truth`), or fixed
        weights (``"fixed:0.01"`` or a sequence), in normalised units
        (:mod:`reconstruction.weights`).
    latent : {"spectral", "colour"}
        Problem (3.1), or direct colour estimation (3.27).
    reference : {None, "mean-colour"}
        ``"mean-colour"``: the §6.3 variant (reconstruct relative to a smooth spectrum
        fitted to the image's mean colour).
    kernel : {"gaussian", "sinc"}
        Kernel of the spectral basis. A response tabulated at exactly the band centres (a
        sensor map, :meth:`calibration.ChannelSensitivity.as_response`) is a discrete model
        whatever the kernel (:class:`~reconstruction.image_formation.LatentSpace`).
    rtol : float, optional
        ADMM relative tolerance per patch; default
        :func:`~reconstruction.solvers.admm.default_rtol`: 1e-5 when
        ``spectral_smoothness`` > 0, which brings each patch's objective within 1e-4 of
        its optimum for every prior, and 1e-4 at σ = 0.
    max_iter : int
        ADMM iteration limit per patch.
    exact : bool, optional
        With non-negativity and L2-type priors, solve every patch exactly (projected-Newton
        active-set method; :func:`~reconstruction.solvers.admm.solve`'s ``exact_nonneg``).
        None (default): with spectral smoothness σ > 0, patches whose initial estimate has
        few values at zero are solved exactly and directly (``direct``: no ADMM, faster
        than ADMM's solve to within 1e-4), the others by ADMM; at σ = 0, ADMM. At σ = 0
        the exact optimum is the poorer image (README, spectral smoothness), and reaching
        it with Φ costs several times the ADMM solve.
    patch_px : int
        Patch size, px (even). Small patches suit the FFT preconditioner: across a patch
        the dispersion departs less from its mean translation.
    pad_px : int, optional
        Overlap on each side, px (even); default the smallest even value ≥ 8 and ≥ twice the
        model's largest displacement.
    flat_threshold : float or None
        Relative texture above the image's noise below which a patch counts as flat
        (None: never skip).
    weight_patches : int or sequence of (row, col)
        How many representative patches to select weights on (chosen by texture), or
        their origins.
    weight_patch_px : int
        Size of those patches, px (even).
    truth : ndarray (rows, cols, n), optional
        True spectral image at the band centres (MSE criterion only; simulation).
    scheduler : str or distributed.Client, optional
        Dask scheduler (see :func:`~reconstruction.patches.reconstruct_patches`).
    progress : callable, optional
        ``progress(done, total)`` per patch.

    Returns
    -------
    Reconstruction

    Raises
    ------
    DataError
        Bad input of any kind, before heavy work starts.
    """
    started = time.perf_counter()
    raw = check_raw(raw)
    cfa = check_layout(cfa)
    if latent == "spectral":
        if response is None:
            raise DataError("spectral reconstruction needs the camera response (R, G, B)")
        space = LatentSpace.spectral(response, bands, kernel=kernel)
    elif latent == "colour":
        if bands is not None:
            raise DataError("direct colour estimation (latent='colour') takes no bands")
        space = LatentSpace.colour()
    else:
        raise DataError(f"unknown latent space {latent!r}; use 'spectral' or 'colour'")
    terms = prior_terms(prior, channels=space.channels)
    if spectral_smoothness is None:
        spectral_smoothness = SUGGESTED_SMOOTHNESS if space.kind == "spectral" else 0.0
    smoothness = float(spectral_smoothness)
    if not (np.isfinite(smoothness) and smoothness >= 0):
        raise DataError(f"spectral_smoothness must be finite and ≥ 0, got {spectral_smoothness}")
    if smoothness > 0 and space.kind != "spectral":
        raise DataError(
            "spectral_smoothness applies to spectral latent images (bands along λ); give 0 "
            "for latent='colour'"
        )
    l1_terms = any(t.norm == 1 for t in terms)
    if rtol is None:
        rtol = default_rtol(smoothness)
    if not (isinstance(rtol, (int, float)) and 0 < rtol < 1):
        raise DataError(f"rtol must be a number in (0, 1), got {rtol!r}")
    # with σ > 0 the optimum is unique and the better image: patches with few values at
    # zero reach it by projected Newton, faster than ADMM comes within 1e-4 of it
    direct = exact is None and smoothness > 0 and nonneg and not l1_terms
    exact = bool(exact)
    if exact and l1_terms:
        raise DataError(
            f"the exact finish (exact=True, --exact) applies to L2-type priors (L2, Lap2, "
            f"L2L2); {prior} has L1 terms, which only ADMM solves: drop it or pick an "
            "L2-type prior"
        )
    criterion, fixed = parse_weights(weights, len(terms))
    # with σ > 0 the patch solves reach the optimum (or within 1e-4 of it), which the
    # selection then scores exactly (reconstruction.weights); not the MDC, whose ideal
    # point needs solves at w = ε, where only the ridge fixes the exact optimum
    exact_weights = smoothness > 0 and not l1_terms and criterion != "mdc"
    if criterion == "msec" and truth is None:
        raise DataError("weights='auto:msec' needs the true spectral image (truth=...)")
    if reference is not None and reference not in REFERENCES:
        raise DataError(f"unknown reference {reference!r}; use None or 'mean-colour' (§6.3)")
    if correction not in CORRECTIONS:
        raise DataError(
            f"unknown correction {correction!r}; use 'model' (Φ in the problem) or 'warp' "
            "(§3.9.2: warp after a dispersion-free solve)"
        )
    model = check_dispersion_model(dispersion, raw.shape, space.kind, correction=correction)
    if correction == "warp" and model is None:
        raise DataError("correction='warp' needs a dispersion model to warp with")
    solve_model = model if correction == "model" else None
    check_interpolation(interpolation)
    reach = 0.0 if solve_model is None else max_dispersion(model, space, (0, 0), raw.shape)
    if pad_px is None:
        pad_px = max(MIN_PAD_PX, 2 * math.ceil(reach))
        pad_px += pad_px % 2
    elif reach > pad_px / 2:
        raise DataError(
            f"the dispersion model shifts the image by up to {reach:.1f} px, more than half "
            f"the patch overlap pad_px={pad_px}; raise pad_px (or leave it to the default)"
        )
    # normalisation: raw to O(1), colour matrices to a largest channel sum of 1
    raw_scale = float(np.mean(raw))
    if not raw_scale > 0:
        raw_scale = max(float(np.max(np.abs(raw))), 1.0)
    y = raw / raw_scale
    noise = noise_sigma(y)
    options = PatchOptions(
        patch_px=patch_px, pad_px=pad_px, flat_threshold=flat_threshold, noise_sigma=noise
    )
    colour_gain = 1.0 / float(space.colour_matrix().sum(axis=1).max())
    notices = []
    if reference == "mean-colour" or smoothness > 0:
        # one fit of (6.1) serves both, on the colour matrix of spectra (before any scale)
        colour_mean = mean_colour(y, cfa)
        fit, misfit = smooth_mean_colour(colour_mean, colour_gain * space.colour_matrix())
        if reference == "mean-colour":
            space = space.with_scale(reference_scale(fit))
        # a non-positive channel mean has no colour to judge
        if smoothness > 0 and np.all(colour_mean > 0) and misfit > NARROW_BAND_MISFIT:
            notices.append(
                f"the image's mean raw colour is {100 * misfit:.0f} % away from that of any "
                "smooth non-negative spectrum: narrow-band light? The spectral smoothness "
                f"term (σ = {smoothness:g}) biases such colours; give spectral_smoothness=0 "
                "(--spectral-smoothness 0) for the thesis' problem"
            )
            warnings.warn(notices[-1], NarrowBandWarning, stacklevel=2)
    atol = absolute_tolerance(y, rtol)  # Algorithm 9 on the whole image

    log: dict = {
        "warnings": notices,
        "latent": space.kind,
        "bands_nm": None if space.centres_nm is None else [float(v) for v in space.centres_nm],
        "prior": prior,
        "nonneg": nonneg,
        "spectral_smoothness": smoothness,
        "exact": exact,
        "direct": direct,
        "rtol": rtol,
        "reference": reference,
        "patch_px": patch_px,
        "pad_px": pad_px,
        "flat_threshold": flat_threshold,
        "noise_sigma": noise * raw_scale,
        "normalisation": {"raw_scale": raw_scale, "colour_gain": colour_gain},
        "reference_scale": [float(v) for v in space.scale],
        "dispersion": None
        if model is None
        else {
            "source": str(dispersion) if isinstance(dispersion, (str, Path)) else "in memory",
            "variables": model.variables,
            "direction": model.direction,
            "correction": correction,
            "interpolation": interpolation if solve_model is not None else None,
            "provenance": model.to_dict().get("provenance", {}),
        },
    }

    t0 = time.perf_counter()
    if fixed is None:
        if isinstance(weight_patches, int):
            origins = representative_patches(y, weight_patch_px, weight_patches)
        else:
            origins = [tuple(int(v) for v in o) for o in weight_patches]
        size = min(weight_patch_px, raw.shape[0], raw.shape[1])
        problems, truths = [], []
        for r, c in origins:
            if (
                r % 2
                or c % 2
                or r < 0
                or c < 0
                or r + size > raw.shape[0]
                or c + size > raw.shape[1]
            ):
                raise DataError(
                    f"weight patch origin ({r}, {c}) must be even and keep a {size}-px patch "
                    "inside the image"
                )
            formation = build_formation(space, (size, size), cfa, colour_gain=colour_gain)
            problems.append(
                Problem(
                    formation,
                    y[r : r + size, c : c + size],
                    terms,
                    (1.0,) * len(terms),
                    nonneg,
                    smoothness=smoothness,
                )
            )
            if truth is not None:
                truths.append(
                    np.asarray(truth, dtype=np.float64)[r : r + size, c : c + size]
                    / (raw_scale * colour_gain)
                )
        truth_matrix = None
        if criterion == "msec":
            truth_matrix = _spectral_matrix(space)
        selection = select_weights(
            problems,
            criterion=criterion,
            truths=truths or None,
            truth_matrix=truth_matrix,
            exact=exact_weights,
        )
        chosen = selection.weights
        log["weights"] = {
            "values": list(chosen),
            "criterion": criterion,
            "criterion_value": selection.value,
            "rounds": selection.rounds,
            "solves": selection.solves,
            "exact": exact_weights,
            "patches": [list(o) for o in origins],
            "patch_px": size,
        }
    else:
        chosen = fixed
        log["weights"] = {"values": list(chosen), "criterion": "fixed"}
    log["weights"]["requested"] = weights if isinstance(weights, str) else list(chosen)
    log["weights"]["seconds"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    solver = SolverOptions(
        terms,
        tuple(chosen),
        nonneg,
        rtol,
        atol,
        max_iter,
        exact=exact,
        direct=direct,
        interpolation=interpolation,
        smoothness=smoothness,
    )
    latent_norm, records = reconstruct_patches(
        y,
        cfa=cfa,
        latent=space,
        colour_gain=colour_gain,
        model=solve_model,
        solver=solver,
        options=options,
        scheduler=scheduler,
        progress=progress,
    )
    log["solve_seconds"] = time.perf_counter() - t1
    latent_image = latent_norm * (raw_scale * colour_gain)
    if correction == "warp":
        t2 = time.perf_counter()
        latent_image = warp_latent(latent_image, space, model)
        log["warp_seconds"] = time.perf_counter() - t2
    spectral = space.spectral_values(latent_image)
    raw_colour = space.raw_colour(latent_image)
    for name, array in (("spectral image", spectral), ("raw colour image", raw_colour)):
        if not np.all(np.isfinite(array)):
            raise DataError(f"reconstruction produced NaN/Inf in the {name}; please report this")
    log["patches"] = _patch_summary(records)
    log["patch_records"] = records
    log["seconds"] = time.perf_counter() - started
    return Reconstruction(
        spectral.astype(np.float32),
        None if space.centres_nm is None else space.centres_nm.copy(),
        raw_colour.astype(np.float32),
        space,
        log,
    )


def warp_latent(latent_image: np.ndarray, space: LatentSpace, model: DispersionModel) -> np.ndarray:
    """Warp a latent image estimated without Φ onto the reference geometry (§3.9.2).

    Spectral channels (basis coefficients) are resampled with the dispersion at their band
    centres; colour channels R and B onto G. Bilinear, so non-negativity is kept.
    """
    if space.kind == "colour":
        return correct_channels(latent_image, model)
    return correct_spectral(latent_image, space.centres_nm, model)


def _spectral_matrix(space: LatentSpace) -> np.ndarray:
    """Matrix mapping a latent pixel to the spectrum at the band centres (incl. scale)."""
    return space.spectral_values(np.eye(space.channels)).T


def _patch_summary(records: list[dict]) -> dict:
    iterations = [r["iterations"] for r in records]
    return {
        "count": len(records),
        "phi_used": sum(r["phi"] == "used" for r in records),
        "phi_skipped_negligible": sum(r["phi"] == "skipped: negligible" for r in records),
        "phi_skipped_flat": sum(r["phi"] == "skipped: flat patch" for r in records),
        "flat": sum(r["flat"] for r in records),
        "converged": sum(r["converged"] for r in records),
        "exact": sum(r["exact"] for r in records),
        "iterations_median": float(np.median(iterations)),
        "iterations_max": int(max(iterations)),
        "cg_iterations_max": int(max(r["cg_max"] for r in records)),
        "patch_seconds_total": float(sum(r["seconds"] for r in records)),
    }
