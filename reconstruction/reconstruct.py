"""`reconstruct`: a spectral (or colour) image from one Bayer raw image (thesis ch. 3).

The options are validated once, as a :class:`~reconstruction.options.ReconstructOptions`,
before any work; the job then runs in four named stages:

1. :func:`prepare_problem` — check the image against the options, normalise it, fit the
   §6.3 reference spectrum;
2. :func:`choose_weights` — fixed, or chosen on representative patches (§3.6, without
   dispersion);
3. :func:`solve_patches` — every patch on Dask (§3.8.1);
4. :func:`assemble` — undo the normalisation, warp for the §3.9.2 variant, the spectrum at
   the band centres, the raw colour image and the log.

The result is a :class:`~reconstruction.result.Reconstruction`, whose ``save`` writes the
files (:mod:`reconstruction.result`).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import nnls

from calibration.dispersion_model import DispersionModel
from calibration.warp import correct_channels, correct_spectral
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index
from labkit.errors import DataError
from reconstruction.band_balance import balance_terms, band_factors
from reconstruction.image_formation import LatentSpace, build_formation
from reconstruction.operators import SpectralGradient
from reconstruction.options import ReconstructOptions
from reconstruction.patches import (
    PatchOptions,
    SolverOptions,
    max_dispersion,
    noise_sigma,
    reconstruct_patches,
    texture,
)
from reconstruction.prior_terms import PriorTerm
from reconstruction.problem import Problem
from reconstruction.result import Reconstruction
from reconstruction.solvers.admm import absolute_tolerance
from reconstruction.weights import select_weights

MIN_PAD_PX = 8
"""Smallest default patch overlap, px."""

MAX_RAW_MAGNITUDE = 1e30
"""Largest abs(raw value) accepted (and smallest non-zero peak, as its inverse): the spectral
and raw-colour outputs are float32 (largest finite 3.4e38, smallest normal 1.2e-38)."""

REFERENCE_SMOOTHING = 1e-2
"""Weight w of (6.1)'s spectral-gradient penalty, relative to ‖C‖² (normalised units)."""


class DomainWarning(UserWarning):
    """The dispersion model is used outside the domain it was calibrated on (clamped, or
    extrapolated with ``extrapolation="allow"``); the log's ``dispersion.domain`` says where."""


class NarrowBandWarning(UserWarning):
    """The image's light looks narrow-band while a spectral smoothness term was asked for
    (left to the default, σ is 0 for such images instead)."""


NARROW_BAND_MISFIT = 0.02
"""Misfit of (6.1)'s smooth fit to the image's mean colour above which the light is taken
to be narrow-band: the default spectral smoothness then gives way to σ = 0 (logged), and
an explicit σ > 0 draws a warning. On the simulated rig it
lies above the misfit of unfiltered light and below that of most of the 10 nm filters;
the filters at the ends of the camera's response stay below it, because what they pass is
mostly leaked broadband light (figures in the README, spectral smoothness)."""


def check_raw(raw: np.ndarray, *, where: str = "the raw image") -> np.ndarray:
    """`raw` as float64 after checking it is a usable Bayer mosaic.

    Usable: a 2-D array of real numbers, even-sized, at least 8×8 px, finite, and with a
    largest abs(value) of 0 or within [1e-30, 1e30] (:data:`MAX_RAW_MAGNITUDE`). A flat
    image (zeros, a constant) is usable here and comes back flat; the file entry points
    (``labkit reconstruct``) refuse images without usable light
    (:func:`labkit.io.light.check_light`).

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
    options: ReconstructOptions | None = None,
    /,
    *,
    truth: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    **keywords: Any,
) -> Reconstruction:
    """Reconstruct an aberration-free spectral image from one Bayer raw image (problem (3.1)).

    The job runs in four stages: :func:`prepare_problem` (normalise, fit the §6.3
    reference, check the image against the options), :func:`choose_weights` (on
    representative patches, without dispersion), :func:`solve_patches` (every patch, on
    Dask) and :func:`assemble` (undo the normalisation, warp for §3.9.2, the outputs).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic (e.g. an HDR raw image), even size, finite; any linear units.
    options : ReconstructOptions, optional
        The problem and how to solve it; or give its fields as keywords (``cfa=…``,
        ``response=…``, …; :class:`~reconstruction.options.ReconstructOptions` documents
        each). Keywords given with `options` replace its fields.
    truth : ndarray (rows, cols, n), optional
        True spectral image at the band centres (``weights="auto:msec"`` only; simulation).
    progress : callable, optional
        ``progress(done, total)`` per patch.

    Returns
    -------
    Reconstruction

    Raises
    ------
    OptionError
        An invalid option, before anything else is done.
    DataError
        A raw image or option unusable for it, before heavy work starts.
    """
    started = time.perf_counter()
    if options is None:
        options = ReconstructOptions(**keywords)
    elif keywords:
        options = replace(options, **keywords)
    job = prepare_problem(raw, options, truth=truth)
    weights = choose_weights(job, truth=truth)
    latent, records = solve_patches(job, weights, progress=progress)
    result = assemble(job, latent, records)
    result.log["seconds"] = time.perf_counter() - started
    return result


@dataclass(eq=False)
class PreparedProblem:
    """The problem of one image, normalised and checked (:func:`prepare_problem`).

    Attributes
    ----------
    options : ReconstructOptions
    raw : ndarray (rows, cols) float64
        The raw image as given.
    y : ndarray (rows, cols) float64
        The raw image divided by `raw_scale`.
    raw_scale, colour_gain : float
        The normalisation: raw to O(1), colour matrices to a largest channel sum of 1.
    space : LatentSpace
        The latent space, with the §6.3 reference scale when asked for.
    patches : PatchOptions
        Patch size, overlap (resolved from the dispersion's reach), flatness threshold and
        the image's noise level.
    atol : float
        ADMM's absolute tolerance (Algorithm 9 on the whole image).
    log : dict
        The log so far (JSON-ready).
    terms : tuple of PriorTerm
        The prior's terms as the patches solve them: the L2 gradient terms with the band
        factors of `space` (:mod:`reconstruction.band_balance`) when γ > 0.
    """

    options: ReconstructOptions
    raw: np.ndarray
    y: np.ndarray
    raw_scale: float
    colour_gain: float
    space: LatentSpace
    patches: PatchOptions
    atol: float
    log: dict
    terms: tuple[PriorTerm, ...]


def prepare_problem(
    raw: np.ndarray, options: ReconstructOptions, *, truth: np.ndarray | None = None
) -> PreparedProblem:
    """Stage 1: check `raw` against `options`, normalise it, fit the §6.3 reference.

    Raises
    ------
    DataError
        An unusable raw image, a dispersion model for another image size or a patch
        overlap below its reach, or ``auto:msec`` without `truth`.
    """
    raw = check_raw(raw)
    o = options
    if o.criterion == "msec" and truth is None:
        raise DataError("weights='auto:msec' needs the true spectral image (truth=...)")
    domain = o.check_image(raw.shape)
    space = o.space
    model, solve_model = o.model, o.solve_model
    reach = 0.0 if solve_model is None else max_dispersion(model, space, (0, 0), raw.shape)
    pad_px = o.pad_px
    if pad_px is None:
        pad_px = max(MIN_PAD_PX, 2 * math.ceil(reach))
        pad_px += pad_px % 2
    elif reach > pad_px / 2:
        raise DataError(
            f"the dispersion model shifts the image by up to {reach:.1f} px, more than half "
            f"the patch overlap pad_px={pad_px}; raise pad_px (or leave it to the default)"
        )
    raw_scale = float(np.mean(raw))
    if not raw_scale > 0:
        raw_scale = max(float(np.max(np.abs(raw))), 1.0)
    y = raw / raw_scale
    noise = noise_sigma(y)
    patches = PatchOptions(
        patch_px=o.patch_px, pad_px=pad_px, flat_threshold=o.flat_threshold, noise_sigma=noise
    )
    colour_gain = 1.0 / float(space.colour_matrix().sum(axis=1).max())
    smoothness = o.smoothness
    notices = []
    chosen = None
    if o.reference == "mean-colour" or smoothness > 0:
        # one fit of (6.1) serves both, on the colour matrix of spectra (before any scale)
        colour_mean = mean_colour(y, o.cfa)
        fit, misfit = smooth_mean_colour(colour_mean, colour_gain * space.colour_matrix())
        if o.reference == "mean-colour":
            space = space.with_scale(reference_scale(fit))
        # a non-positive channel mean has no colour to judge
        narrow = smoothness > 0 and np.all(colour_mean > 0) and misfit > NARROW_BAND_MISFIT
        if narrow and o.spectral_smoothness is None:
            # the default σ would bias these colours: the thesis' problem instead
            chosen = (
                f"0 instead of the default {smoothness:g}: the image's mean raw colour is "
                f"{100 * misfit:.0f} % away from that of any smooth non-negative spectrum "
                "(narrow-band light)"
            )
            if o.balance > 0:
                chosen += ", and no band balance (it needs σ > 0)"
            o = replace(o, spectral_smoothness=0.0, band_balance=None)
            smoothness = 0.0
        elif narrow:
            notices.append(
                f"the image's mean raw colour is {100 * misfit:.0f} % away from that of any "
                "smooth non-negative spectrum: narrow-band light? The spectral smoothness "
                f"term (σ = {smoothness:g}) biases such colours; give spectral_smoothness=0 "
                "(--spectral-smoothness 0) for the thesis' problem, or leave it to the default"
            )
            warnings.warn(notices[-1], NarrowBandWarning, stacklevel=4)
    if domain is not None and domain.outside:
        notices.append(domain.message())
        warnings.warn(notices[-1], DomainWarning, stacklevel=4)
    terms = o.terms
    factors = None
    if o.balance > 0:
        factors = band_factors(space.colour_matrix(), exponent=o.balance)
        terms = balance_terms(terms, factors)
    log: dict = {
        "warnings": notices,
        "latent": space.kind,
        "bands_nm": None if space.centres_nm is None else [float(v) for v in space.centres_nm],
        "prior": o.prior,
        "nonneg": o.nonneg,
        "spectral_smoothness": smoothness,
        "spectral_smoothness_chosen": chosen,
        "band_balance": o.balance,
        "band_factors": None if factors is None else [float(v) for v in factors],
        "exact": bool(o.exact),
        "direct": o.direct,
        "rtol": o.tolerance,
        "reference": o.reference,
        "patch_px": o.patch_px,
        "pad_px": pad_px,
        "flat_threshold": o.flat_threshold,
        "noise_sigma": noise * raw_scale,
        "normalisation": {"raw_scale": raw_scale, "colour_gain": colour_gain},
        "reference_scale": [float(v) for v in space.scale],
        "dispersion": None
        if model is None
        else {
            "source": o.dispersion_source,
            "variables": model.variables,
            "direction": model.direction,
            "correction": o.correction,
            "interpolation": o.interpolation if solve_model is not None else None,
            "domain": domain.to_dict(),
            "band_light_nm": None
            if space.band_light_nm is None
            else {
                "values": [float(v) for v in space.band_light_nm],
                "source": "the filters' effective wavelengths recorded by the model "
                "(provenance.bands_table): Φ of each band is evaluated there, not at its "
                "nominal centre",
            },
            "provenance": model.to_dict().get("provenance", {}),
        },
    }
    return PreparedProblem(
        options=o,
        raw=raw,
        y=y,
        raw_scale=raw_scale,
        colour_gain=colour_gain,
        space=space,
        patches=patches,
        atol=absolute_tolerance(y, o.tolerance),
        log=log,
        terms=terms,
    )


def choose_weights(job: PreparedProblem, *, truth: np.ndarray | None = None) -> tuple[float, ...]:
    """Stage 2: the prior weights, fixed or chosen on representative patches (§3.6,
    without dispersion); records the choice in ``job.log["weights"]``.

    Raises
    ------
    DataError
        A weight patch origin that is odd or leaves the image.
    """
    o = job.options
    t0 = time.perf_counter()
    criterion, fixed = o.criterion, o.fixed_weights
    raw = job.raw
    if fixed is None:
        if isinstance(o.weight_patches, (int, np.integer)):
            origins = representative_patches(job.y, o.weight_patch_px, int(o.weight_patches))
        else:
            origins = [tuple(int(v) for v in origin) for origin in o.weight_patches]
        size = min(o.weight_patch_px, raw.shape[0], raw.shape[1])
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
            formation = build_formation(job.space, (size, size), o.cfa, colour_gain=job.colour_gain)
            problems.append(
                Problem(
                    formation,
                    job.y[r : r + size, c : c + size],
                    job.terms,
                    (1.0,) * len(job.terms),
                    o.nonneg,
                    smoothness=o.smoothness,
                )
            )
            if truth is not None:
                truths.append(
                    np.asarray(truth, dtype=np.float64)[r : r + size, c : c + size]
                    / (job.raw_scale * job.colour_gain)
                )
        selection = select_weights(
            problems,
            criterion=criterion,
            truths=truths or None,
            truth_matrix=_spectral_matrix(job.space) if criterion == "msec" else None,
            exact=o.exact_weights,
        )
        chosen = selection.weights
        entry = {
            "values": list(chosen),
            "criterion": criterion,
            "criterion_value": selection.value,
            "rounds": selection.rounds,
            "solves": selection.solves,
            "exact": o.exact_weights,
            "patches": [list(origin) for origin in origins],
            "patch_px": size,
        }
    else:
        chosen = fixed
        entry = {"values": list(chosen), "criterion": "fixed"}
    entry["requested"] = o.weights if isinstance(o.weights, str) else list(chosen)
    entry["seconds"] = time.perf_counter() - t0
    job.log["weights"] = entry
    return tuple(chosen)


def solve_patches(
    job: PreparedProblem,
    weights: Sequence[float],
    *,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, list[dict]]:
    """Stage 3: solve every patch with `weights` (on Dask); the normalised latent image
    and the per-patch records. Weights not chosen by :func:`choose_weights` for this job
    are logged as fixed."""
    o = job.options
    # weights given here rather than by choose_weights (e.g. another image's) are fixed
    job.log.setdefault(
        "weights", {"values": list(weights), "criterion": "fixed", "requested": list(weights)}
    )
    t1 = time.perf_counter()
    solver = SolverOptions(
        job.terms,
        tuple(weights),
        o.nonneg,
        o.tolerance,
        job.atol,
        o.max_iter,
        exact=bool(o.exact),
        direct=o.direct,
        interpolation=o.interpolation,
        smoothness=o.smoothness,
    )
    latent, records = reconstruct_patches(
        job.y,
        cfa=o.cfa,
        latent=job.space,
        colour_gain=job.colour_gain,
        model=job.options.solve_model,
        solver=solver,
        options=job.patches,
        scheduler=o.scheduler,
        progress=progress,
    )
    job.log["solve_seconds"] = time.perf_counter() - t1
    return latent, records


def assemble(job: PreparedProblem, latent: np.ndarray, records: list[dict]) -> Reconstruction:
    """Stage 4: undo the normalisation, warp onto the reference geometry (§3.9.2's
    ``correction="warp"``), and the spectral and raw-colour images with the log.

    Raises
    ------
    DataError
        NaN or Inf in an output (a bug: please report it).
    """
    o, space, log = job.options, job.space, job.log
    if o.correction == "warp":
        t2 = time.perf_counter()
        latent = warp_latent(latent, space, o.model)
        log["warp_seconds"] = time.perf_counter() - t2
    # every step is linear: the normalisation is undone on each output in place, so that
    # no extra image-sized copy of the latent image is made (full-size images: 320 MB each)
    outputs = []
    for name, convert in (
        ("spectral image", space.spectral_values),
        ("raw colour image", space.raw_colour),
    ):
        array = convert(latent)
        array *= job.raw_scale * job.colour_gain
        if not np.all(np.isfinite(array)):
            raise DataError(f"reconstruction produced NaN/Inf in the {name}; please report this")
        outputs.append(array.astype(np.float32))
        del array
    log["patches"] = _patch_summary(records)
    log["patch_records"] = records
    return Reconstruction(
        outputs[0],
        None if space.centres_nm is None else space.centres_nm.copy(),
        outputs[1],
        space,
        log,
    )


def warp_latent(latent_image: np.ndarray, space: LatentSpace, model: DispersionModel) -> np.ndarray:
    """Warp a latent image estimated without Φ onto the reference geometry (§3.9.2).

    Spectral channels (basis coefficients) are resampled with the dispersion at their band
    centres (or the light of their filters, :attr:`LatentSpace.phi_nm`); colour channels R
    and B onto G. Bilinear, so non-negativity is kept.
    """
    if space.kind == "colour":
        return correct_channels(latent_image, model)
    return correct_spectral(latent_image, space.phi_nm, model)


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
