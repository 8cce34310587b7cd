"""Thin-plate spline models of dispersion, smoothed by generalised cross-validation (§3.2.4).

The second interpolation method of thesis §3.2.4 (the first is
:mod:`calibration.polynomial`): one smoothing thin-plate spline per displacement
component, in (x, y) for colour-channel keypoints and in (x, y, λ) for spectral keypoints,
fitted to keypoints normalised as for polynomials (:class:`~calibration._normalise.Normaliser`:
whitened positions, z-scored wavelengths, jointly scaled displacements). Appendix B.3
compares the two: splines follow the keypoints more closely (also their noise, near the
image edges) and tend to an affine function far from them, but cost O(n³) to fit and O(n)
per evaluated point.

Model
-----
In normalised inputs u (2-D or 3-D) each component j ∈ {x, y} is ::

    f_j(u) = Σ_i c_ij φ(|u − u_i|) + a_0j + Σ_k a_kj u_k

with one centre u_i per keypoint and the biharmonic Green's functions of Wahba (1990,
§2.4) for the penalty ∫ ‖D²f‖²_F of thesis (3.5) (second derivatives, m = 2):

* 2-D: φ(r) = r² log r (= 8π E(r), E the Green's function of Δ² in the plane);
* 3-D: φ(r) = −r (= 8π E(r) in space; r² log r is *not* the 3-D Green's function).

Both are conditionally positive definite of order 2: cᵀ K c ≥ 0 whenever c is orthogonal
to the affine polynomials. Minimising (3.5), Σ_k (f(u_k) − d_k)² + w₃.₅ ∫ ‖D²f‖²,
gives the linear system (Wahba 1990, §1.3 and §2.4; the Geometric Tools splines the
thesis' implementation followed solve the same ``K + w I`` form)::

    (K + w I) c + P a = d,    Pᵀ c = 0,    K_ik = φ(|u_i − u_k|),  P = [1, u]

with **w = 8π w₃.₅** (since ∫ ‖D²f‖² = 8π cᵀ K c for these φ). The smoothing weight
recorded in a model, ``selection["smoothing"]`` and :attr:`SplineField.smoothing`, is this
w of ``K + w I`` in normalised units (normalised inputs and displacements); Algorithm 2's
grid (machine epsilon … 10¹⁰) is applied to it. w → 0 interpolates the keypoints, w → ∞
tends to the least-squares affine fit.

Generalised cross-validation
----------------------------
With P = Q R (Householder QR, Q kept as reflectors; Q = [Q1 Q2], Q2 an orthonormal basis
of the complement of P's columns) and the eigen-decomposition Q2ᵀ K Q2 = U Λ Uᵀ (computed
once), the influence matrix A(w) of the smoother satisfies (Wahba 1990, §1.3 and ch. 4) ::

    (I − A(w)) d = w Q2 U (Λ + w I)⁻¹ Uᵀ Q2ᵀ d,    tr(I − A(w)) = Σ_i w / (λ_i + w)

so V(w) = n ‖(I − A(w)) d‖² / tr(I − A(w))² costs O(n) per w. The x and y components
share the centres and **one** w, chosen by minimising the joint objective whose numerator
is the sum of the two components' numerators (equivalently the mean of their V). Choosing
w per component would make the fitted field depend on the orientation of the image axes;
one w keeps it equivariant under rotations of the image plane, matching the joint
normalisation of the two displacement components (§3.2.4). The effective degrees of
freedom reported are n − tr(I − A(w)) = p + Σ λ_i / (λ_i + w), p = dim + 1.

w is chosen by Algorithm 2 exactly: 15 log-spaced values from machine epsilon to 10¹⁰,
V evaluated at w₂ … w₁₄; then repeatedly a 4-point log grid between the neighbours of
the best value, V evaluated at its two inner points and the better of those two taken
(the outer points bracket the search; the first bracket's lower end, machine epsilon, is
never evaluated, so "the index minimising the objective" is read as over the two inner
points), with the stopping rules on the relative change of V and the iteration counter s
(starting at 2) of the thesis. Every evaluated (w, V) is recorded in
``selection["search"]``.

The coefficients are then c = Q2 U (Λ + w)⁻¹ Uᵀ Q2ᵀ d (reusing the eigen-decomposition)
and a from R a = Q1ᵀ (d − K c − w c). Eigenvalues below zero (round-off; Q2ᵀ K Q2 is
positive semi-definite) are clipped to zero. The condition number of the solved system,
(λ_max + w) / (λ_min + w), is recorded; if GCV picks a w for which it exceeds
:data:`MAX_CONDITION` (near-duplicate keypoints and almost no smoothing), w is raised to
the smallest value meeting the bound and the GCV choice is kept in
``selection["gcv_smoothing"]``.

Large keypoint sets
-------------------
Fitting costs O(n³) time and O(n²) memory and evaluation O(n) per point, so more than
``max_points`` keypoints are reduced first: keypoints of each band (spectral) or of the
channel (colour) are averaged in square cells of the image plane — positions,
displacements (and the band's wavelength) averaged within a cell — with one cell size for
all bands, grown in steps of 5 % from an estimate until the total number of occupied cells
is at most ``max_points``. For spectral keypoints the cap is on the total over all
bands (one spline); for colour channels it is per channel (one spline each). Averaging is
a first-order approximation (its error grows with the field's curvature × cell size²) and
gives centres of unequal noise, which GCV, assuming equal variances, does not know about.
What was done is recorded in ``selection["reduction"]``.

Speed: fitting costs O(n³), mostly the eigen-decomposition of the n² kernel matrix;
evaluation processes blocks of points × centres that fit the caches, with reused buffers,
on a pool of threads (NumPy and SciPy release the GIL); memory is O(points + block).
Figures in docs/notes/calibration.md.

Limitations
-----------
* With dense, low-noise keypoints GCV often picks (near-)interpolation: the spline's
  approximation error between keypoints then exceeds the noise, so smoothing does not pay
  (thesis B.3: splines "retain more of the noise"). w is chosen on a grid; the 3-D kernel
  treats normalised λ and (x, y) isotropically.
* One w for both components (above); equal noise variances assumed by GCV.
* Cost grows as O(n³) / O(n) per point: ``max_points`` trades resolution for speed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from calibration._normalise import Normaliser
from calibration._spline_kernel import PHI_SCALE, psi
from calibration.dispersion_model import SPECTRAL, CalibratedRegion, DispersionModel
from calibration.keypoints import DispersionKeypoints
from calibration.spline_field import KERNELS, SplineField
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import ConfigError, DataError

#: Algorithm 2: lower and upper ends and size of the initial grid of w.
GRID_LOW = float(np.finfo(np.float64).eps)
GRID_HIGH = 1e10
GRID_POINTS = 15
#: Largest accepted condition number (λ_max + w) / (λ_min + w) of the solved system.
MAX_CONDITION = 1e10


# -- GCV ---------------------------------------------------------------------------------
@fixed_blas_threads
def gcv_grid_search(
    objective: Callable[[float], float],
    *,
    tolerance: float = 1e-3,
    min_iterations: int = 3,
    max_iterations: int = 20,
) -> tuple[float, float, list[dict[str, float]]]:
    """Thesis Algorithm 2: minimise `objective` over w ∈ [machine ε, 10¹⁰] by grid search.

    Returns ``(w*, objective(w*), search)``, `search` listing every evaluation as
    ``{"iteration": s, "w": w, "gcv": V}`` (iteration 1 is the initial 15-point grid).
    """
    search: list[dict[str, float]] = []

    def value(w: float, s: int) -> float:
        v = float(objective(w))
        search.append({"iteration": s, "w": float(w), "gcv": v})
        return v

    grid = np.logspace(np.log10(GRID_LOW), np.log10(GRID_HIGH), GRID_POINTS)
    values = [value(w, 1) for w in grid[1:-1]]
    k = int(np.argmin(values)) + 1
    a, b = grid[k - 1], grid[k + 1]
    w_best, e_prev = float(grid[k]), values[k - 1]
    s = 2
    while True:
        grid = np.logspace(np.log10(a), np.log10(b), 4)
        inner = [value(grid[1], s), value(grid[2], s)]
        k = int(np.argmin(inner)) + 1
        e_current = inner[k - 1]
        if e_current <= e_prev:
            w_best = float(grid[k])
            change = abs(e_current - e_prev) / abs(e_prev) if e_prev != 0 else 0.0
            if change < tolerance and s >= min_iterations:
                return w_best, e_current, search
            e_prev = e_current
        s += 1
        if s >= max_iterations:
            return w_best, e_prev, search
        a, b = grid[k - 1], grid[k + 1]


class _Reflectors:
    """Q of the QR factorisation P = Q R, kept as LAPACK Householder reflectors.

    Applying Q or Qᵀ costs O(n · p) per column instead of the O(n²) of a dense Q, so
    Q2ᵀ K Q2 costs O(n² p) rather than two n × n × n products.
    """

    def __init__(self, basis: np.ndarray) -> None:
        (self.raw, self.tau), self.r = scipy.linalg.qr(basis, mode="raw")
        self.p = basis.shape[1]

    def apply(self, matrix: np.ndarray, *, side: str = "L", transpose: bool = False) -> np.ndarray:
        """Q·C, Qᵀ·C (side "L") or C·Q, C·Qᵀ (side "R") for a 2-D C."""
        c = np.asfortranarray(matrix, dtype=np.float64)
        trans = "T" if transpose else "N"
        _, work, info = scipy.linalg.lapack.dormqr(side, trans, self.raw, self.tau, c, -1)
        lwork = int(work[0]) if info == 0 else max(1, c.shape[0], c.shape[1]) * 64
        out, _, info = scipy.linalg.lapack.dormqr(
            side, trans, self.raw, self.tau, c, lwork, overwrite_c=1
        )
        if info != 0:  # pragma: no cover - LAPACK argument errors are programming errors
            raise RuntimeError(f"LAPACK dormqr failed (info {info})")
        return out


@dataclass
class _Decomposition:
    """What GCV and the coefficient solve share for one set of centres."""

    u: np.ndarray  # (n, dim) normalised centres
    kernel: np.ndarray  # (n, n) K
    q: _Reflectors  # P = Q R
    eigenvalues: np.ndarray  # (n − p,) ≥ 0, of Q2ᵀ K Q2
    eigenvectors: np.ndarray  # (n − p, n − p) U
    z: np.ndarray  # (n − p, 2) = Uᵀ Q2ᵀ d

    def gcv(self, w: float) -> float:
        """Joint V(w) = n (‖(I − A)d_x‖² + ‖(I − A)d_y‖²) / tr(I − A)²."""
        f = w / (self.eigenvalues + w)
        numerator = float(np.dot(f * f, np.einsum("ij,ij->i", self.z, self.z)))
        return len(self.u) * numerator / float(f.sum()) ** 2

    def trace_residual(self, w: float) -> float:
        """tr(I − A(w))."""
        return float(np.sum(w / (self.eigenvalues + w)))

    def condition(self, w: float) -> float:
        return float((self.eigenvalues.max() + w) / (self.eigenvalues.min() + w))

    def solve(self, d: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
        """Kernel weights c (n, 2) and affine coefficients a (p, 2) for smoothing w."""
        p = self.q.p
        c = np.zeros((len(self.u), 2))
        c[p:] = self.eigenvectors @ (self.z / (self.eigenvalues + w)[:, None])
        c = self.q.apply(c)  # Q2 U (Λ + w)⁻¹ Uᵀ Q2ᵀ d
        rhs = self.q.apply(d - self.kernel @ c - w * c, transpose=True)[:p]
        a = scipy.linalg.solve_triangular(self.q.r, rhs, check_finite=False)
        return c, a


def _decompose(u: np.ndarray, d: np.ndarray, label: str) -> _Decomposition:
    n, dim = u.shape
    p = dim + 1
    q = _Reflectors(np.column_stack([np.ones(n), u]))
    diag = np.abs(np.diag(q.r))
    if diag.min() <= 1e-10 * diag.max():
        raise DataError(
            f"{label}: the keypoints are degenerate — their positions"
            + (" and wavelengths" if dim == 3 else "")
            + " do not determine an affine function (e.g. each band's keypoints lie on "
            "one line); keypoints must cover a 2-D region of the image in several bands"
        )
    kernel = PHI_SCALE[dim] * psi(u, u, dim)
    projected = q.apply(q.apply(kernel, transpose=True), side="R")[p:, p:]
    projected = 0.5 * (projected + projected.T)
    eigenvalues, eigenvectors = scipy.linalg.eigh(
        projected, check_finite=False, driver="evd", overwrite_a=True
    )
    if not np.all(np.isfinite(eigenvalues)):
        raise DataError(f"{label}: the spline's kernel matrix is not finite")
    eigenvalues = np.maximum(eigenvalues, 0.0)
    z = eigenvectors.T @ q.apply(d, transpose=True)[p:]
    return _Decomposition(u, kernel, q, eigenvalues, eigenvectors, z)


def _fit_field(
    points: np.ndarray,
    displacements: np.ndarray,
    *,
    label: str,
    tolerance: float,
    min_iterations: int,
    max_iterations: int,
) -> tuple[SplineField, dict[str, Any]]:
    """Fit one SplineField to `points` (n, 2 | 3) px / nm and `displacements` (n, 2) px."""
    n, dim = points.shape
    if n < dim + 2:
        raise DataError(
            f"{label}: {n} keypoint{'s' if n != 1 else ''}; a {dim}-D thin-plate spline needs "
            f"at least {dim + 2} (its affine part alone has {dim + 1} coefficients)"
        )
    normaliser = Normaliser.fit(points, displacements, what=label)
    u = normaliser.inputs(points)
    d = normaliser.outputs(displacements)
    dec = _decompose(u, d, label)
    w_gcv, v_gcv, search = gcv_grid_search(
        dec.gcv,
        tolerance=tolerance,
        min_iterations=min_iterations,
        max_iterations=max_iterations,
    )
    w = w_gcv
    report: dict[str, Any] = {}
    lam_min, lam_max = float(dec.eigenvalues.min()), float(dec.eigenvalues.max())
    if dec.condition(w) > MAX_CONDITION:
        w = max(w, (lam_max - MAX_CONDITION * lam_min) / (MAX_CONDITION - 1.0))
        report["gcv_smoothing"] = w_gcv
    c, a = dec.solve(d, w)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a))):
        raise DataError(f"{label}: the thin-plate spline system could not be solved (not finite)")
    field = SplineField(normaliser, u, c, a, w)
    trace = dec.trace_residual(w)
    report = {
        "smoothing": float(w),
        "gcv": float(dec.gcv(w)) if w != w_gcv else float(v_gcv),
        "effective_dof": float(n - trace),
        "condition": dec.condition(w),
        **report,
        "search": search,
    }
    return field, report


# -- keypoint reduction ------------------------------------------------------------------
def _reduce(
    points: np.ndarray, displacements: np.ndarray, labels: np.ndarray, max_points: int
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Average keypoints per band in square spatial cells until at most `max_points` remain."""
    n = len(points)
    if n <= max_points:
        return points, displacements, {"method": "none"}
    xy = points[:, :2]
    lo = xy.min(axis=0)
    span = np.ptp(xy, axis=0)
    _, band_index = np.unique(labels, return_inverse=True)
    n_bands = int(band_index.max()) + 1
    cell = max(
        float(np.sqrt(span[0] * span[1] * n_bands / max_points)),
        float(span.max()) * n_bands / max_points,
        1e-6,
    )
    while True:
        cells = np.floor((xy - lo) / cell).astype(np.int64)
        keys = np.column_stack([band_index, cells])
        unique, inverse = np.unique(keys, axis=0, return_inverse=True)
        if len(unique) <= max_points:
            break
        cell *= 1.05
    inverse = inverse.ravel()
    counts = np.bincount(inverse, minlength=len(unique)).astype(np.float64)

    def average(values: np.ndarray) -> np.ndarray:
        return (
            np.column_stack(
                [np.bincount(inverse, weights=col, minlength=len(unique)) for col in values.T]
            )
            / counts[:, None]
        )

    report = {
        "method": "cell_average",
        "cell_px": float(cell),
        "max_points": int(max_points),
        "keypoints": int(n),
        "centres": len(unique),
        "max_per_cell": int(counts.max()),
    }
    return average(points), average(displacements), report


# -- the fitter --------------------------------------------------------------------------
@fixed_blas_threads
def fit_spline_model(
    keypoints: DispersionKeypoints,
    *,
    direction: str = "from_reference",
    max_points: int = 3000,
    rng: np.random.Generator | None = None,
    tolerance: float = 1e-3,
    min_iterations: int = 3,
    max_iterations: int = 20,
) -> DispersionModel:
    """Fit thin-plate spline dispersion models to `keypoints` (thesis §3.2.4, Algorithm 2).

    Spectral keypoints give one 3-D spline in (x, y, λ) (field ``"spectral"``; at least
    two bands); colour-channel keypoints one 2-D spline per channel (fields ``"R"``,
    ``"B"``; keypoints labelled with the reference channel are ignored). The smoothing
    weight of each spline is chosen by GCV (module doc).

    Parameters
    ----------
    direction : {"from_reference", "to_reference"}
        ``to_reference`` fits the swapped keypoints (band positions → displacement back
        to the reference image, :meth:`DispersionKeypoints.swapped`).
    max_points : int
        Most centres per spline; larger keypoint sets are cell-averaged first (module doc).
    rng : numpy.random.Generator, optional
        Unused: GCV and the cell reduction are deterministic. Accepted so that the spline
        and polynomial fitters take the same options.
    tolerance, min_iterations, max_iterations
        Algorithm 2's stopping rule (relative change of V; iteration counter s ≥ 2).

    Returns
    -------
    DispersionModel
        ``type="spline"``; ``selection`` holds ``method="gcv"``, ``kernel``,
        ``seconds`` (fitting time) and, for spectral models, the spline's ``smoothing``
        w, ``gcv`` V(w), ``search`` (every evaluated w and V), ``effective_dof``,
        ``condition`` (and ``gcv_smoothing`` if w had to be raised), ``n_keypoints``,
        ``n_centres`` and ``reduction``. For colour-channel models (as in
        :mod:`calibration.polynomial`) each of these maps channel → value, and
        ``n_keypoints_total`` and ``n_centres_total`` sum over the channels.

    Raises
    ------
    DataError
        One band only, too few keypoints in a band or channel (fewer than dimension + 2),
        or positions that span no area.
    ConfigError
        Invalid options.
    """
    del rng  # accepted for interface compatibility only
    _check_options(direction, max_points, tolerance, min_iterations, max_iterations)
    if direction == "to_reference":
        x, y, dx, dy = keypoints.swapped()
    else:
        x, y, dx, dy = keypoints.x, keypoints.y, keypoints.dx, keypoints.dy
    displacements = np.column_stack([dx, dy])
    options = {
        "tolerance": tolerance,
        "min_iterations": min_iterations,
        "max_iterations": max_iterations,
    }
    selection: dict[str, Any] = {"method": "gcv"}
    started = time.perf_counter()
    if keypoints.spectral:
        fields = _fit_spectral(keypoints, x, y, displacements, max_points, options, selection)
        region = CalibratedRegion.from_points(x, y, keypoints.wavelength_nm)
        variables = "xylambda"
    else:
        fields, keep = _fit_channels(keypoints, x, y, displacements, max_points, options, selection)
        region = CalibratedRegion.from_points(x[keep], y[keep])
        variables = "xy"
    selection["seconds"] = round(time.perf_counter() - started, 3)
    return DispersionModel(
        type="spline",
        variables=variables,
        direction=direction,
        reference=keypoints.reference,
        image_shape=keypoints.image_shape,
        fields=dict(fields),
        region=region,
        selection=selection,
        provenance={**keypoints.meta, "keypoints": keypoints.source, "bands": keypoints.bands},
    )


def _check_options(
    direction: str, max_points: int, tolerance: float, min_iterations: int, max_iterations: int
) -> None:
    if direction not in ("from_reference", "to_reference"):
        raise ConfigError(f"direction must be from_reference or to_reference, not {direction!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, int | np.integer):
        raise ConfigError(f"max_points must be an integer, got {max_points!r}")
    if max_points < 5:
        raise ConfigError(f"max_points must be at least 5, got {max_points}")
    if not tolerance > 0:
        raise ConfigError(f"tolerance must be positive, got {tolerance}")
    if max_iterations < 2 or min_iterations < 1:
        raise ConfigError(
            "GCV search needs max_iterations ≥ 2 and min_iterations ≥ 1, got "
            f"{max_iterations} and {min_iterations}"
        )


def _fit_spectral(
    keypoints: DispersionKeypoints,
    x: np.ndarray,
    y: np.ndarray,
    displacements: np.ndarray,
    max_points: int,
    options: dict[str, Any],
    selection: dict[str, Any],
) -> dict[str, SplineField]:
    """One spline in (x, y, λ); its selection record goes into `selection`."""
    bands = keypoints.bands
    if len(bands) < 2:
        raise DataError(
            f"spectral keypoints come from {len(bands)} band"
            f"{'s' if len(bands) != 1 else ''} ({', '.join(f'{b:g} nm' for b in bands)}); "
            "a spline in (x, y, λ) needs keypoints from at least 2 filter bands"
        )
    wavelength = keypoints.wavelength_nm
    points = np.column_stack([x, y, wavelength])
    label = f"spectral keypoints ({len(points)} in {len(bands)} bands)"
    centres, values, reduction = _reduce(points, displacements, wavelength, max_points)
    fld, report = _fit_field(centres, values, label=label, **options)
    selection.update(
        kernel=KERNELS[3],
        n_keypoints=len(points),
        n_centres=len(centres),
        reduction=reduction,
        **report,
    )
    return {SPECTRAL: fld}


def _fit_channels(
    keypoints: DispersionKeypoints,
    x: np.ndarray,
    y: np.ndarray,
    displacements: np.ndarray,
    max_points: int,
    options: dict[str, Any],
    selection: dict[str, Any],
) -> tuple[dict[str, SplineField], np.ndarray]:
    """One spline in (x, y) per channel other than the reference; the selection records
    (channel → value, as :mod:`calibration.polynomial`) go into `selection`. Returns the
    fields and which keypoints were used."""
    channels = [c for c in keypoints.bands if c != keypoints.reference]
    if not channels:
        raise DataError(
            f"the keypoints only hold the reference channel {keypoints.reference!r}; "
            "colour-channel keypoints need R or B"
        )
    keep = keypoints.channel != keypoints.reference
    fields: dict[str, SplineField] = {}
    reports: dict[str, dict[str, Any]] = {}
    for channel in channels:
        pick = keypoints.channel == channel
        points = np.column_stack([x[pick], y[pick]])
        label = f"channel {channel} ({int(pick.sum())} keypoints)"
        centres, values, reduction = _reduce(
            points, displacements[pick], keypoints.channel[pick], max_points
        )
        fld, report = _fit_field(centres, values, label=label, **options)
        fields[str(channel)] = fld
        reports[str(channel)] = {
            "n_keypoints": len(points),
            "n_centres": len(centres),
            "reduction": reduction,
            **report,
        }
    keys = dict.fromkeys(key for r in reports.values() for key in r)
    selection.update(
        kernel=KERNELS[2],
        **{key: {c: r[key] for c, r in reports.items() if key in r} for key in keys},
        n_keypoints_total=sum(r["n_keypoints"] for r in reports.values()),
        n_centres_total=sum(r["n_centres"] for r in reports.values()),
    )
    if not keep.all():
        selection["ignored"] = (
            f"{int((~keep).sum())} keypoints of the reference channel {keypoints.reference}"
        )
    return fields, keep
