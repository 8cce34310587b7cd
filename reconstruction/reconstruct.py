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

import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.dispersion_model import DispersionModel
from calibration.warp import correct_channels, correct_spectral
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.choices import (
    Choices,
    image_facts,
    reference_scale,
    resolve_choices,
)
from reconstruction.model.band_balance import balance_terms, band_factors
from reconstruction.model.image_formation import LatentSpace, build_formation
from reconstruction.model.prior_terms import PriorTerm
from reconstruction.model.problem import Problem
from reconstruction.options import ReconstructOptions
from reconstruction.result import Reconstruction
from reconstruction.solve.patches import (
    SERIAL_SCHEDULERS,
    PatchOptions,
    SolverOptions,
    default_scheduler,
    max_dispersion,
    noise_sigma,
    reconstruct_patches,
    texture,
)
from reconstruction.solve.solvers.admm import absolute_tolerance
from reconstruction.solve.weights import select_weights
from reconstruction.solve.worker_pool import start_worker_pool

MAX_RAW_MAGNITUDE = 1e30
"""Largest abs(raw value) accepted (and smallest non-zero peak, as its inverse): the spectral
and raw-colour outputs are float32 (largest finite 3.4e38, smallest normal 1.2e-38)."""


class DomainWarning(UserWarning):
    """The dispersion model is used outside the domain it was calibrated on (clamped, or
    extrapolated with ``extrapolation="allow"``); the log's ``dispersion.domain`` says where."""


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
    if (job.options.scheduler or default_scheduler()) == "processes":
        start_worker_pool()  # in the background, while the weights are chosen
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
        factors of `space` (:mod:`reconstruction.model.band_balance`) when γ > 0.
    choices : Choices
        Every setting in effect, with where it came from and why
        (:func:`~reconstruction.choices.resolve_choices`); the stages read them here.
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
    choices: Choices


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
    raw_scale = float(np.mean(raw))
    if not raw_scale > 0:
        raw_scale = max(float(np.max(np.abs(raw))), 1.0)
    y = raw / raw_scale
    colour_gain = 1.0 / float(space.colour_matrix().sum(axis=1).max())
    facts = image_facts(y, o, space, colour_gain=colour_gain, reach_px=reach)
    choices = resolve_choices(o, facts=facts)
    pad_px = choices.pad_px
    if reach > pad_px / 2:
        raise DataError(
            f"the dispersion model shifts the image by up to {reach:.1f} px, more than half "
            f"the patch overlap pad_px={pad_px}; raise pad_px (or leave it to the default)"
        )
    noise = noise_sigma(y)
    patches = PatchOptions(
        patch_px=o.patch_px, pad_px=pad_px, flat_threshold=o.flat_threshold, noise_sigma=noise
    )
    reference = choices["reference"].value
    if reference == "mean-colour":
        space = space.with_scale(reference_scale(facts.smooth_fit))
    smoothness = choices.smoothness
    notices = []
    if domain is not None and domain.outside:
        notices.append(domain.message())
        warnings.warn(notices[-1], DomainWarning, stacklevel=4)
    terms = o.terms
    factors = None
    if choices.balance > 0:
        factors = band_factors(space.colour_matrix(), exponent=choices.balance)
        terms = balance_terms(terms, factors)
    log: dict = {
        "warnings": notices,
        "latent": space.kind,
        "bands_nm": None if space.centres_nm is None else [float(v) for v in space.centres_nm],
        "prior": o.prior,
        "nonneg": o.nonneg,
        "choices": choices.to_dict(),
        "spectral_smoothness": smoothness,
        "band_balance": choices.balance,
        "band_factors": None if factors is None else [float(v) for v in factors],
        "solver": choices.solver,
        "exact": choices.exact,
        "direct": choices.direct,
        "rtol": choices.rtol,
        "reference": reference,
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
        atol=absolute_tolerance(y, choices.rtol),
        log=log,
        terms=terms,
        choices=choices,
    )


def weight_search_workers(scheduler: Any) -> int:
    """Threads the weight search may use: 2 (it solves two weights at a time at most)
    unless the patches run on one thread (a ``sync`` scheduler) or the machine has one core."""
    if isinstance(scheduler, str) and scheduler in SERIAL_SCHEDULERS:
        return 1
    return min(2, os.cpu_count() or 1)


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
                    smoothness=job.choices.smoothness,
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
            exact=job.choices.exact_weights,
            workers=weight_search_workers(o.scheduler),
        )
        chosen = selection.weights
        entry = {
            "values": list(chosen),
            "criterion": criterion,
            "criterion_value": selection.value,
            "rounds": selection.rounds,
            "solves": selection.solves,
            "exact": job.choices.exact_weights,
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
        terms=job.terms,
        weights=tuple(weights),
        nonneg=o.nonneg,
        rtol=job.choices.rtol,
        atol=job.atol,
        max_iter=o.max_iter,
        method=job.choices.solver,
        interpolation=o.interpolation,
        smoothness=job.choices.smoothness,
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
