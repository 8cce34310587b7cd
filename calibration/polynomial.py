"""Polynomial models of dispersion, degrees chosen by cross-validation (thesis §3.2.4).

Spectral keypoints (between filter bands) get one **trivariate** polynomial in (x, y, λ):
total degree ≤ d_xy in (x, y) times degree ≤ d_λ in λ, fitted to all bands at once.
Colour-channel keypoints get one **bivariate** polynomial in (x, y) per channel (R and
B relative to G), after Rudakova and Monasse.

Both fit the x and y components of the displacement as two columns of one least-squares
problem, in normalised coordinates (:mod:`calibration._normalise`: whitened (x, y),
z-scored λ, jointly normalised displacements) and on a Legendre basis of those
coordinates (:mod:`calibration._polybasis`, the same polynomial space as monomials).

Degree selection
----------------
Errors are **mean squared Euclidean prediction errors in px²**: the mean over the
validation keypoints of (dx − d̂x)² + (dy − d̂y)².

*Spectral* — thesis Algorithm 1. For each candidate (d_xy, d_λ) ∈ {0…max_degree_xy} ×
{0…N_λ − 2}: for each validation band i, the band's keypoints V_i plus one of 10 random
tenths of the other keypoints form the validation set, the remaining nine tenths the
training set; e_db and s_db are the sample mean and sample standard deviation of the
10 × (number of validation bands) errors. The thesis validates on the bands i = 2…N_λ − 1
only (``validation="interior"``: every fold interpolates in λ); by default every band is
validated (``"every-band"``), so the shortest and the longest bands' folds judge each
candidate on extrapolating one band step beyond its data too, and a degree in λ whose
tails swing is paid for in the selection. With e_min the smallest e_db and s the s_db
there, d_λ is the smallest b with some e_db − e_min ≤ s, then d_xy the smallest d with
e_db − e_min ≤ s at that b. (This "one-standard-error" rule uses the standard deviation of
the fold errors, as the thesis' Algorithm 1 does, not the standard error of their mean: it
is deliberately conservative.) The tenths are drawn independently for each validation
band. The chosen model's error one band step beyond its data is then measured at both ends
(refitted without the end band, predicting it) and recorded in
``selection["extrapolation"]``: the figure a user weighs before evaluating the model
outside its calibrated range (:mod:`calibration.model_domain`).

*Colour channels* — per channel, 10-fold cross-validation over degrees 0…max_degree_xy
(thesis: "tenfold cross-validation, as done for vignetting correction"), and the same
one-standard-error rule: the smallest degree whose mean error is within one sample
standard deviation (of the 10 fold errors) of the minimum.

Candidates whose training design matrix has more columns than rows, or a condition
number above `max_condition`, are skipped and listed in the model's selection report.
The normalisation is fitted once, to all keypoints: it only reparametrises the same
polynomial space, so it does not change what a fold's training data determine.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration import _polybasis as pb
from calibration._normalise import Normaliser
from calibration.dispersion_model import SPECTRAL, CalibratedRegion, DispersionModel
from calibration.keypoints import DispersionKeypoints
from calibration.polynomial_field import PolynomialField
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import ConfigError, DataError

#: Largest spatial degree the thesis considers.
MAX_DEGREE_XY = 12

#: Which bands a spectral model's degree selection holds out in turn.
VALIDATIONS = {
    "every-band": "every band, the shortest and longest too (extrapolation is judged)",
    "interior": "the bands between the shortest and the longest (as the thesis)",
}
#: Fewest keypoints a band or channel must have (a plane through them needs three).
MIN_KEYPOINTS = 3

Progress = Callable[[int, int, str], None]


# -- fitting ------------------------------------------------------------------------------
@dataclass
class _Fit:
    """One fitted field and its selection report."""

    field: PolynomialField
    report: dict[str, Any]


@fixed_blas_threads
def fit_polynomial_model(
    keypoints: DispersionKeypoints,
    *,
    direction: str = "from_reference",
    max_degree_xy: int = MAX_DEGREE_XY,
    max_degree_lambda: int | None = None,
    folds: int = 10,
    rng: np.random.Generator | None = None,
    max_condition: float = pb.MAX_CONDITION,
    validation: str = "every-band",
    progress: Progress | None = None,
) -> DispersionModel:
    """Fit a polynomial dispersion model, choosing its degrees by cross-validation.

    Parameters
    ----------
    keypoints : DispersionKeypoints
        Spectral keypoints (≥ 3 bands; the reference band's zero displacements are data
        like any other band) or colour-channel keypoints (one field per channel; keypoints
        of the reference channel itself, if any, are ignored).
    direction : {"from_reference", "to_reference"}
        ``to_reference`` fits ``keypoints.swapped()``: band positions → displacement back
        to the reference image.
    max_degree_xy : int
        Largest total degree in (x, y) tried (thesis: 12).
    max_degree_lambda : int, optional
        Largest degree in λ tried; default and upper limit N_λ − 2.
    folds : int
        Random folds per validation band (spectral) or per channel (thesis: 10).
    rng : numpy.random.Generator, optional
        Source of the random folds; default ``numpy.random.default_rng(0)`` (reproducible).
    max_condition : float
        Candidates whose design matrix has a larger 2-norm condition number are skipped;
        the final model's must be below it.
    validation : {"every-band", "interior"}
        Spectral keypoints: which bands are held out in turn (:data:`VALIDATIONS`; the
        thesis: ``"interior"``).
    progress : callable(done, total, message), optional
        Called after each cross-validation split.

    Returns
    -------
    DispersionModel
        ``type="polynomial"``; ``selection`` holds the CV error tables (px², mean squared
        Euclidean error, ``None`` where skipped), their standard deviations, the chosen
        degrees, the final design matrix's condition number and the skipped candidates.

    Raises
    ------
    DataError
        Fewer than 3 bands for a spectral model, a band or channel with too few keypoints,
        or no candidate model possible.
    ConfigError
        Invalid direction, degrees or folds.
    """
    if direction not in ("from_reference", "to_reference"):
        raise ConfigError(f"direction must be from_reference or to_reference, not {direction!r}")
    pb.check_count("max_degree_xy", max_degree_xy, least=0)
    if max_degree_lambda is not None:
        pb.check_count("max_degree_lambda", max_degree_lambda, least=0)
    pb.check_count("folds", folds, least=2)
    if validation not in VALIDATIONS:
        raise ConfigError(f"validation must be one of {', '.join(VALIDATIONS)}, not {validation!r}")
    rng = np.random.default_rng(0) if rng is None else rng
    if direction == "to_reference":
        x, y, dx, dy = keypoints.swapped()
    else:
        x, y, dx, dy = keypoints.x, keypoints.y, keypoints.dx, keypoints.dy
    xy = np.column_stack([x, y])
    d = np.column_stack([dx, dy])
    started = time.perf_counter()

    if keypoints.spectral:
        wavelength = keypoints.wavelength_nm
        fit = _fit_spectral(
            xy, wavelength, d,
            max_degree_xy=int(max_degree_xy),
            max_degree_lambda=max_degree_lambda,
            folds=int(folds),
            rng=rng,
            max_condition=max_condition,
            validation=validation,
            progress=progress,
        )  # fmt: skip
        fields = {SPECTRAL: fit.field}
        selection = fit.report
        region = CalibratedRegion.from_points(x, y, wavelength)
        variables = "xylambda"
    else:
        fields, selection, keep = _fit_channels(
            keypoints, xy, d,
            max_degree=int(max_degree_xy),
            folds=int(folds),
            rng=rng,
            max_condition=max_condition,
            progress=progress,
        )  # fmt: skip
        region = CalibratedRegion.from_points(x[keep], y[keep])
        variables = "xy"
    selection["seconds"] = round(time.perf_counter() - started, 3)
    provenance = {**keypoints.meta, "keypoints": keypoints.source, "bands": keypoints.bands}
    return DispersionModel(
        type="polynomial",
        variables=variables,
        direction=direction,
        reference=keypoints.reference,
        image_shape=keypoints.image_shape,
        fields=fields,
        region=region,
        selection=selection,
        provenance=provenance,
    )


def _fit_channels(
    keypoints: DispersionKeypoints,
    xy: np.ndarray,
    d: np.ndarray,
    *,
    max_degree: int,
    folds: int,
    rng: np.random.Generator,
    max_condition: float,
    progress: Progress | None,
) -> tuple[dict[str, Any], dict[str, Any], np.ndarray]:
    """One field per colour channel other than the reference: the fields, the selection
    record (each channel's degree, CV tables, condition number) and which keypoints were
    used."""
    fields, reports = {}, {}
    channels = [c for c in keypoints.bands if c != keypoints.reference]
    if not channels:
        raise DataError(
            f"the colour-channel keypoints hold only the reference channel "
            f"{keypoints.reference!r}; nothing to model"
        )
    for c in channels:
        rows = keypoints.channel == c
        fit = _fit_channel(
            xy[rows], d[rows], str(c),
            max_degree=max_degree,
            folds=folds,
            rng=rng,
            max_condition=max_condition,
            progress=progress,
        )  # fmt: skip
        fields[str(c)] = fit.field
        reports[str(c)] = fit.report
    keep = np.isin(keypoints.channel, channels)
    selection = {
        "method": "cv-1se",
        "error_units": "px^2 (mean squared Euclidean prediction error)",
        "folds": folds,
        **{
            key: {c: r[key] for c, r in reports.items()}
            for key in (
                "degree_xy",
                "cv_error",
                "cv_std",
                "condition_number",
                "skipped",
                "n_keypoints",
            )
        },
        "degree_lambda": None,
        "n_keypoints_total": int(keep.sum()),
    }
    return fields, selection, keep


def _checked_bands(
    wavelength: np.ndarray, max_degree_lambda: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The bands, each keypoint's band index, the keypoints per band and the largest degree
    in λ (N_λ − 2 by default); an error for fewer than 3 bands, a band with too few
    keypoints, or a degree in λ the bands cannot determine."""
    bands = np.unique(wavelength)
    n_bands = len(bands)
    if n_bands < 3:
        raise DataError(
            f"the keypoints cover {n_bands} band(s) ({', '.join(f'{b:g} nm' for b in bands)}); "
            "a spectral dispersion model needs at least 3 bands (its degree is validated on "
            "the bands between the shortest and longest wavelength); with fewer bands fit a "
            "colour-channel model instead"
        )
    band_index = np.searchsorted(bands, wavelength)
    counts = np.bincount(band_index, minlength=n_bands)
    for b, c in zip(bands, counts, strict=True):
        if c < MIN_KEYPOINTS:
            raise DataError(
                f"band {b:g} nm has {c} keypoint(s); each band needs at least {MIN_KEYPOINTS} "
                f"for a polynomial dispersion model ({len(wavelength)} keypoints in "
                f"{n_bands} bands)"
            )
    limit = n_bands - 2
    if max_degree_lambda is None:
        max_degree_lambda = limit
    elif max_degree_lambda > limit:
        raise DataError(
            f"max_degree_lambda {max_degree_lambda} is too high for {n_bands} bands: "
            f"the degree in λ can be at most N_λ − 2 = {limit}"
        )
    return bands, band_index, counts, max_degree_lambda


def _band_splits(
    band_index: np.ndarray, n_bands: int, validation: str, folds: int, rng: np.random.Generator
) -> tuple[list[np.ndarray], list[list[int]], range]:
    """Thesis Algorithm 1's cross-validation: each validated band held out with one of
    `folds` random parts of the rest. Returns the parts, the splits (pairs of part indices)
    and the validated bands' indices."""
    parts: list[np.ndarray] = []
    splits: list[list[int]] = []
    validated = range(n_bands) if validation == "every-band" else range(1, n_bands - 1)
    for i in validated:
        parts.append(np.flatnonzero(band_index == i))
        band_part = len(parts) - 1
        rest = np.flatnonzero(band_index != i)
        for tenth in np.array_split(rng.permutation(rest), folds):
            parts.append(np.sort(tenth))
            splits.append([band_part, len(parts) - 1])
    return parts, splits, validated


def _fit_spectral(
    xy: np.ndarray,
    wavelength: np.ndarray,
    d: np.ndarray,
    *,
    max_degree_xy: int,
    max_degree_lambda: int | None,
    folds: int,
    rng: np.random.Generator,
    max_condition: float,
    validation: str,
    progress: Progress | None,
) -> _Fit:
    """Trivariate polynomial with degrees by thesis Algorithm 1 (validated on
    `validation`'s bands)."""
    bands, band_index, counts, max_degree_lambda = _checked_bands(wavelength, max_degree_lambda)
    n_bands = len(bands)
    points = np.column_stack([xy, wavelength])
    normaliser = Normaliser.fit(points, d, what="spectral keypoints")
    u = normaliser.inputs(points)
    domain = pb.Domain.fit(u)
    t = domain(u)
    target = normaliser.outputs(d)
    exps = pb.exponent_table(max_degree_xy, max_degree_lambda)
    X = pb.design_matrix(t, exps)

    parts, splits, validated = _band_splits(band_index, n_bands, validation, folds, rng)
    groups = []
    for b in range(max_degree_lambda + 1):
        cols = pb.candidate_columns(exps, max_degree_xy, b)
        sizes = [pb.n_terms_xy(dd) * (b + 1) for dd in range(max_degree_xy + 1)]
        groups.append((cols, sizes))
    report_progress = (
        None
        if progress is None
        else lambda done, total: progress(done, total, "cross-validating polynomial degrees")
    )
    cv = pb.cross_validate(
        X, target, parts, splits, groups, max_condition=max_condition, progress=report_progress
    )
    px2 = normaliser.displacement_scale**2
    mean, std = cv.mean_std()  # (b, d)
    mean, std = mean.T * px2, std.T * px2  # [d, b], px²
    if not np.any(np.isfinite(mean)):
        raise DataError(
            f"no polynomial dispersion model can be fitted to {len(wavelength)} keypoints in "
            f"{n_bands} bands (fewest in one band: {counts.min()} at "
            f"{bands[np.argmin(counts)]:g} nm): every candidate degree was skipped "
            f"({_first_reason(cv.skipped)})"
        )
    degree_xy, degree_lambda = pb.one_standard_error_2d(mean, std)
    cols = pb.candidate_columns(exps, degree_xy, degree_lambda)
    coef, cond = pb.solve_lstsq(
        X[:, cols], target, max_condition=max_condition, what="spectral polynomial model"
    )
    field = PolynomialField(normaliser, domain, exps[cols], coef)
    extrapolation = [
        _extrapolation_error(X[:, cols], target, band_index, end, bands, normaliser)
        for end in (0, n_bands - 1)
    ]
    skipped = [
        {"degree_xy": i, "degree_lambda": g, "reason": reason}
        for (g, i), reason in sorted(cv.skipped.items(), key=lambda kv: (kv[0][1], kv[0][0]))
    ]
    best = np.unravel_index(int(np.nanargmin(mean)), mean.shape)
    report = {
        "method": "cv-1se",
        "error_units": "px^2 (mean squared Euclidean prediction error)",
        "degree_xy": degree_xy,
        "degree_lambda": degree_lambda,
        "cv_error": pb.table(mean),
        "cv_std": pb.table(std),
        "cv_min": {
            "degree_xy": int(best[0]),
            "degree_lambda": int(best[1]),
            "error": float(mean[best]),
        },
        "condition_number": cond,
        "skipped": skipped,
        "n_keypoints": len(wavelength),
        "folds": folds,
        "validation": validation,
        "validation_bands": [float(bands[i]) for i in validated],
        "extrapolation": extrapolation,
        "max_degree_xy": max_degree_xy,
        "max_degree_lambda": int(max_degree_lambda),
        "exact_solves": cv.exact_solves,
    }
    return _Fit(field, report)


def _extrapolation_error(
    X: np.ndarray,
    target: np.ndarray,
    band_index: np.ndarray,
    end: int,
    bands: np.ndarray,
    normaliser: Normaliser,
) -> dict[str, float | None]:
    """The chosen model's error one band step beyond its data: refitted without the end
    band `end` (its columns `X`), RMS Euclidean error predicting that band, px (None when
    the other bands cannot determine the model)."""
    inner = end + 1 if end == 0 else end - 1
    held = band_index == end
    record: dict[str, float | None] = {
        "band_nm": float(bands[end]),
        "from_nm": float(bands[inner]),
        "step_nm": float(abs(bands[end] - bands[inner])),
        "rms_px": None,
    }
    try:
        coef, _ = pb.solve_lstsq(X[~held], target[~held], what="extrapolation check")
    except DataError:
        return record
    error = normaliser.displacement_scale**2 * np.sum((X[held] @ coef - target[held]) ** 2, 1)
    record["rms_px"] = float(np.sqrt(np.mean(error)))
    return record


def _fit_channel(
    xy: np.ndarray,
    d: np.ndarray,
    channel: str,
    *,
    max_degree: int,
    folds: int,
    rng: np.random.Generator,
    max_condition: float,
    progress: Progress | None,
) -> _Fit:
    """Bivariate polynomial of one colour channel, degree by 10-fold CV and the 1-SE rule."""
    n = len(xy)
    if n < max(MIN_KEYPOINTS, folds):
        raise DataError(
            f"channel {channel} has {n} keypoint(s); a polynomial dispersion model with "
            f"{folds}-fold cross-validation needs at least {max(MIN_KEYPOINTS, folds)}"
        )
    normaliser = Normaliser.fit(xy, d, what=f"channel {channel} keypoints")
    u = normaliser.inputs(xy)
    domain = pb.Domain.fit(u)
    target = normaliser.outputs(d)
    exps = pb.exponent_table(max_degree)
    X = pb.design_matrix(domain(u), exps)
    splits = pb.kfold_splits(n, folds, rng)
    sizes = [pb.n_terms_xy(dd) for dd in range(max_degree + 1)]
    report_progress = (
        None
        if progress is None
        else lambda done, total: progress(done, total, f"cross-validating channel {channel}")
    )
    cv = pb.cross_validate(
        X, target, splits, [[j] for j in range(len(splits))], [(np.arange(len(exps)), sizes)],
        max_condition=max_condition, progress=report_progress,
    )  # fmt: skip
    mean, std = cv.mean_std()
    px2 = normaliser.displacement_scale**2
    mean, std = mean[0] * px2, std[0] * px2
    if not np.any(np.isfinite(mean)):
        raise DataError(
            f"no polynomial dispersion model can be fitted to the {n} keypoints of channel "
            f"{channel}: every candidate degree was skipped ({_first_reason(cv.skipped)})"
        )
    degree = pb.one_standard_error_1d(mean, std)
    cols = np.arange(sizes[degree])
    coef, cond = pb.solve_lstsq(
        X[:, cols], target, max_condition=max_condition, what=f"channel {channel} polynomial model"
    )
    return _Fit(
        PolynomialField(normaliser, domain, exps[cols], coef),
        {
            "degree_xy": degree,
            "cv_error": pb.table(mean),
            "cv_std": pb.table(std),
            "condition_number": cond,
            "skipped": [
                {"degree_xy": i, "reason": reason} for (_, i), reason in sorted(cv.skipped.items())
            ],
            "n_keypoints": n,
        },
    )


def _first_reason(skipped: Mapping[tuple[int, int], str]) -> str:
    """The reason the smallest candidate was skipped."""
    if not skipped:
        return "no candidates"
    key = min(skipped, key=lambda k: (k[1], k[0]))
    return skipped[key]
