"""Polynomial bases, least squares and cross-validation for smooth models (§3.2.2, §3.2.4).

The polynomial models of this package — dispersion (:mod:`calibration.polynomial`,
thesis §3.2.4) and vignetting (:mod:`calibration.vignetting`, §3.2.2) — are linear
combinations of products of one-variable polynomials in *normalised* coordinates:

* bivariate: all terms of total degree ≤ d in (x, y);
* trivariate: total degree ≤ d_xy in (x, y), times degree ≤ d_λ in λ.

Basis
-----
The thesis writes the models with monomials xⁱ yʲ λᵏ of normalised coordinates. Their
design matrices grow ill-conditioned with the degree (figures in docs/notes/calibration.md),
so we use the **Legendre** polynomials Pᵢ(u) Pⱼ(v) Pₖ(w) instead, where (u, v, w) are the normalised
coordinates mapped affinely onto [−1, 1] over the fitting data (:class:`Domain`). For
every degree this spans exactly the same space of polynomials as the monomials (Pₙ has
degree n, so the change of basis is triangular and invertible); only the numerical
conditioning differs.

Column order
------------
:func:`exponent_table` orders terms by total (x, y) degree g = i + j, then by j, then by
k. The table of lower degrees is therefore a column subset of that of higher degrees
(in the same order), and for a fixed λ degree b the columns with k ≤ b of degree
d_xy ≤ d are a *prefix* of those with d_xy ≤ D. Cross-validation uses this: one Cholesky
factorisation per (fold, b) serves every spatial degree d (the factor of a leading
principal block is the leading block of the factor).

Least squares and conditioning
------------------------------
:func:`solve_lstsq` solves by QR and reports the 2-norm condition number of the design
matrix from the singular values of R; it refuses a numerically singular design
(condition number > `max_condition`, default 1e10) or one with fewer rows than columns.

Cross-validation (:func:`cross_validate`) works on Gram matrices: the Gram matrix of all
rows is formed once, each split's training Gram matrix is total − validation (the
validation set's Gram matrix is assembled from parts computed once: Algorithm 1's
validation band plus one tenth of the rest), and every candidate is solved from
sub-blocks. For each (split, λ degree) one Cholesky factorisation and one triangular
inverse serve all spatial degrees (see :func:`_validate_group`). The 1-norm condition
number of each candidate's Cholesky factor (whose singular values are those of its
design matrix) screens it: above :data:`GRAM_CONDITION_LIMIT`, or where the
factorisation breaks down, the candidate is solved exactly by QR of its training rows
instead, and skipped when that design is numerically singular or has more columns than
training rows. Validation errors come from the validation Gram matrix
(``‖y‖² − 2 cᵀXᵀy + cᵀXᵀXc``), or directly from the residuals where that expression would
lose precision. BLAS runs at labkit's fixed thread count (:mod:`labkit.blas_threads`).
Its run time is in docs/notes/calibration.md and ``labkit bench calibrate``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.linalg import lapack

from labkit.blas_threads import fixed_blas_threads
from labkit.errors import ConfigError, DataError

#: Default refusal threshold for the 2-norm condition number of a design matrix.
MAX_CONDITION = 1e10
#: Above this estimated condition number of a candidate's design matrix, cross-validation
#: solves it by QR of the training rows instead of from the Gram matrix (whose condition
#: number is the square: 1e5² = 1e10 leaves ~6 significant digits in the coefficients).
GRAM_CONDITION_LIMIT = 1e5
#: Where the Gram form of the validation error keeps less than this fraction of ‖y‖²,
#: the residuals are computed directly (cancellation).
_DIRECT_RESIDUAL_FRACTION = 1e-6
#: Rows per chunk when evaluating a design matrix over many points.
CHUNK_ROWS = 1 << 16


# -- basis ------------------------------------------------------------------------------
def n_terms_xy(degree: int) -> int:
    """Number of (x, y) terms of total degree ≤ `degree`."""
    return (degree + 1) * (degree + 2) // 2


def exponent_table(degree_xy: int, degree_lambda: int | None = None) -> np.ndarray:
    """Exponents (m, 2) = (i, j) or (m, 3) = (i, j, k), in nested order (module docstring).

    Bivariate: i + j ≤ `degree_xy`; trivariate: also k ≤ `degree_lambda`.
    """
    if degree_xy < 0 or (degree_lambda is not None and degree_lambda < 0):
        raise DataError(f"polynomial degrees must be ≥ 0, got {degree_xy}, {degree_lambda}")
    rows: list[tuple[int, ...]] = []
    for g in range(degree_xy + 1):
        for j in range(g + 1):
            if degree_lambda is None:
                rows.append((g - j, j))
            else:
                rows.extend((g - j, j, k) for k in range(degree_lambda + 1))
    width = 2 if degree_lambda is None else 3
    return np.array(rows, dtype=np.int64).reshape(-1, width)


def candidate_columns(
    exponents: np.ndarray, degree_xy: int, degree_lambda: int | None = None
) -> np.ndarray:
    """Indices of the columns of `exponents` in the basis of the given degrees."""
    keep = exponents[:, 0] + exponents[:, 1] <= degree_xy
    if degree_lambda is not None:
        keep &= exponents[:, 2] <= degree_lambda
    return np.flatnonzero(keep)


def legendre_table(t: np.ndarray, degree: int) -> np.ndarray:
    """Legendre polynomials P₀…P_degree at `t`, shape (degree + 1, n) (three-term recurrence)."""
    t = np.asarray(t, dtype=np.float64).ravel()
    out = np.empty((degree + 1, t.size))
    out[0] = 1.0
    if degree >= 1:
        out[1] = t
    for n in range(1, degree):
        out[n + 1] = ((2 * n + 1) * t * out[n] - n * out[n - 1]) / (n + 1)
    return out


def design_matrix(t: np.ndarray, exponents: np.ndarray) -> np.ndarray:
    """Design matrix (n, m) of Legendre products at domain coordinates `t` (n, 2 | 3)."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != exponents.shape[1]:
        raise DataError(
            f"design matrix: need points of {exponents.shape[1]} coordinates, got {t.shape}"
        )
    columns = None
    for v in range(exponents.shape[1]):
        table = legendre_table(t[:, v], int(exponents[:, v].max(initial=0)))
        factor = table[exponents[:, v]]
        columns = factor if columns is None else columns * factor
    assert columns is not None
    return columns.T


@dataclass(frozen=True, eq=False)
class Domain:
    """Affine map of normalised coordinates onto [−1, 1]: ``t = (u − centre) / half_width``."""

    centre: np.ndarray
    half_width: np.ndarray

    @classmethod
    def fit(cls, u: np.ndarray) -> Domain:
        """The map taking the range of each column of `u` (n, k) onto [−1, 1]."""
        u = np.asarray(u, dtype=np.float64)
        lo, hi = u.min(axis=0), u.max(axis=0)
        half = (hi - lo) / 2.0
        half = np.where(half > 0, half, 1.0)
        return cls((hi + lo) / 2.0, half)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        return (np.asarray(u, dtype=np.float64) - self.centre) / self.half_width

    def to_dict(self) -> dict[str, Any]:
        return {"centre": self.centre.tolist(), "half_width": self.half_width.tolist()}


def whitening(xy: np.ndarray, *, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Offset (2,) and matrix (2, 2) centring `xy` (n, 2) and whitening its covariance.

    ``M (p − offset)`` has zero mean and unit variance along each principal direction
    (thesis §3.2.2, the affine homography T_xy).
    """
    xy = np.asarray(xy, dtype=np.float64)
    offset = xy.mean(axis=0)
    eigvals, eigvecs = np.linalg.eigh(np.cov((xy - offset).T))
    if eigvals[0] <= 1e-9 * max(eigvals[1], 1e-300):
        raise DataError(f"{what}: the pixels lie on a line or a point and span no area")
    return offset, (eigvecs / np.sqrt(eigvals)).T


# -- least squares ----------------------------------------------------------------------
@fixed_blas_threads
def solve_lstsq(
    X: np.ndarray, Y: np.ndarray, *, max_condition: float = MAX_CONDITION, what: str = "fit"
) -> tuple[np.ndarray, float]:
    """Least-squares coefficients of ``X c ≈ Y`` and the 2-norm condition number of X.

    Solved by QR; the condition number comes from the singular values of R (those of X).

    Raises
    ------
    DataError
        Fewer rows than columns, or condition number > `max_condition`.
    """
    n, m = X.shape
    if n < m:
        raise DataError(f"{what}: {n} data points cannot determine {m} coefficients")
    q, r = np.linalg.qr(X)
    qty = q.T @ Y
    cond = condition_number_triangular(r)
    if not cond <= max_condition:
        raise DataError(
            f"{what}: the design matrix is numerically singular (condition number "
            f"{cond:.3g} > {max_condition:.3g})"
        )
    coef = np.linalg.solve(r, qty)
    return coef, cond


def condition_number_triangular(r: np.ndarray) -> float:
    """2-norm condition number of a square matrix from its singular values (inf if singular)."""
    s = np.linalg.svd(r, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


# -- cross-validation -------------------------------------------------------------------
def kfold_splits(n: int, folds: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Validation index arrays of a random `folds`-fold partition of ``range(n)``."""
    if folds < 2:
        raise DataError(f"cross-validation needs at least 2 folds, got {folds}")
    if n < folds:
        raise DataError(f"{folds}-fold cross-validation needs at least {folds} points, got {n}")
    return [np.sort(part) for part in np.array_split(rng.permutation(n), folds)]


@dataclass
class CVResult:
    """Validation errors of every candidate in every split.

    Attributes
    ----------
    errors : ndarray (splits, groups, sizes)
        Mean over validation rows of the squared Euclidean residual (summed over output
        columns), in the units² of Y; NaN where the candidate was skipped.
    skipped : dict of (group, size index) to str
        Why a candidate was skipped.
    exact_solves : int
        Candidates (per split) solved by QR rather than from the Gram matrix.
    """

    errors: np.ndarray
    skipped: dict[tuple[int, int], str] = field(default_factory=dict)
    exact_solves: int = 0

    def mean_std(self) -> tuple[np.ndarray, np.ndarray]:
        """Sample mean and sample standard deviation (ddof 1) over splits, (groups, sizes)."""
        mean = self.errors.mean(axis=0)
        std = self.errors.std(axis=0, ddof=1) if self.errors.shape[0] > 1 else np.zeros_like(mean)
        return mean, std


@fixed_blas_threads
def cross_validate(
    X: np.ndarray,
    Y: np.ndarray,
    parts: Sequence[np.ndarray],
    splits: Sequence[Sequence[int]],
    groups: Sequence[tuple[np.ndarray, Sequence[int]]],
    *,
    max_condition: float = MAX_CONDITION,
    progress: Callable[[int, int], None] | None = None,
) -> CVResult:
    """Cross-validation errors of nested least-squares candidates.

    Parameters
    ----------
    X : ndarray (n, m)
        Design matrix at the largest degrees (every candidate uses a subset of columns).
    Y : ndarray (n, k)
        Targets.
    parts : sequence of int arrays
        Disjoint sets of rows from which validation sets are assembled (their Gram
        matrices are computed once each).
    splits : sequence of sequences of int
        Each split's validation rows are the union of these `parts`; its training rows
        are all the others.
    groups : sequence of (columns, sizes)
        Candidate (g, s) uses columns ``columns[:sizes[s]]``; `sizes` ascending.
    max_condition : float
        Candidates whose training design matrix has a larger condition number are skipped.
    progress : callable(done, total), optional
        Called after each split.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64).reshape(len(X), -1)
    n_sizes = max(len(sizes) for _, sizes in groups)
    result = CVResult(np.full((len(splits), len(groups), n_sizes), np.nan))
    gram = X.T @ X
    moment = X.T @ Y
    part_rows = [np.asarray(p, dtype=np.intp) for p in parts]
    part_stats = []
    for rows in part_rows:
        xp, yp = X[rows], Y[rows]
        part_stats.append((xp.T @ xp, xp.T @ yp, float(np.sum(yp * yp))))
    for s, members in enumerate(splits):
        valid = np.concatenate([part_rows[i] for i in members])
        gram_v = sum(part_stats[i][0] for i in members)
        moment_v = sum(part_stats[i][1] for i in members)
        sum_sq_v = sum(part_stats[i][2] for i in members)
        split = _Split(X, Y, valid, gram - gram_v, moment - moment_v, gram_v, moment_v, sum_sq_v)
        for g, (cols, sizes) in enumerate(groups):
            _validate_group(result, split, s, g, np.asarray(cols, np.intp), sizes,
                            max_condition)  # fmt: skip
        if progress is not None:
            progress(s + 1, len(splits))
    for g, i in result.skipped:
        result.errors[:, g, i] = np.nan
    return result


@dataclass
class _Split:
    """Gram matrices of one split's training and validation rows."""

    X: np.ndarray
    Y: np.ndarray
    valid: np.ndarray
    gram_t: np.ndarray
    moment_t: np.ndarray
    gram_v: np.ndarray
    moment_v: np.ndarray
    sum_sq_v: float
    _train: np.ndarray | None = None

    @property
    def train(self) -> np.ndarray:
        if self._train is None:
            keep = np.ones(len(self.X), dtype=bool)
            keep[self.valid] = False
            self._train = np.flatnonzero(keep)
        return self._train


def _validate_group(
    result: CVResult,
    split: _Split,
    s: int,
    g: int,
    cols: np.ndarray,
    sizes: Sequence[int],
    max_condition: float,
) -> None:
    """Validation errors of the candidates ``cols[:p]``, p in `sizes`, of one split.

    One Cholesky factorisation L Lᵀ of the training Gram block serves every prefix: with
    L⁻¹ explicit, the coefficients of prefix p are ``c_p[r] = Σ_{q<p} L⁻¹[q, r] z[q]``
    (z = L⁻¹ Xᵀy; zero for r ≥ p since L⁻¹ is lower triangular), and the exact 1-norm
    condition number of L_p (whose singular values are those of the candidate's design
    matrix; the 1- and 2-norm condition numbers agree within a factor p) is the product
    of the largest column sums of |L| and |L⁻¹| over their first p rows. Both are one
    matrix product with the (candidates × u) indicator of the first p rows.
    """
    todo = [i for i in range(len(sizes)) if (g, i) not in result.skipped]
    if not todo:
        return
    n_train = len(split.X) - split.valid.size
    factor, info = lapack.dpotrf(
        np.asfortranarray(split.gram_t[np.ix_(cols, cols)]), lower=1, clean=1
    )
    usable = cols.size if info == 0 else max(info - 1, 0)
    k = split.Y.shape[1]
    coefs: dict[int, np.ndarray] = {}
    if usable:
        lower = factor[:usable, :usable]
        inverse, info_inv = lapack.dtrtri(lower, lower=1)
        if info_inv == 0 and np.all(np.isfinite(inverse)):
            cand = [i for i in todo if int(sizes[i]) <= min(usable, n_train)]
            if cand:
                # rows of `prefix`: indicator of the first p rows, one per candidate
                prefix = np.arange(usable) < np.array([int(sizes[i]) for i in cand])[:, None]
                prefix = prefix.astype(np.float64)
                z = inverse @ split.moment_t[cols[:usable]]  # (u, k)
                cond = (prefix @ np.abs(lower)).max(axis=1) * (prefix @ np.abs(inverse)).max(
                    axis=1
                )  # cond₁(L_p)
                solved = np.stack([(prefix * z[:, o]) @ inverse for o in range(k)], axis=-1)
                for row, i in enumerate(cand):
                    if cond[row] <= GRAM_CONDITION_LIMIT:
                        coefs[i] = solved[row]  # (u, k), zero beyond p
    width = max(usable, 1)
    for i in todo:
        p = int(sizes[i])
        if i in coefs:
            continue
        if p > n_train:
            _skip_larger(result, g, i, len(sizes), f"{p} coefficients > {n_train} training points")
            break
        result.exact_solves += 1
        try:
            coef, _ = solve_lstsq(
                split.X[np.ix_(split.train, cols[:p])],
                split.Y[split.train],
                max_condition=max_condition,
            )
        except DataError as exc:
            _skip_larger(result, g, i, len(sizes), str(exc).split(": ", 1)[-1])
            break
        coefs[i] = coef  # (p, k); p > usable possible
        width = max(width, p)
    if not coefs:
        return
    order = sorted(coefs)
    padded = np.zeros((width, len(order), k))
    for column, i in enumerate(order):
        c = coefs[i]
        rows = min(len(c), width)
        padded[:rows, column] = c[:rows]
    flat = padded.reshape(width, -1)
    gv = split.gram_v[np.ix_(cols[:width], cols[:width])]
    mv = split.moment_v[cols[:width]]  # (width, k)
    quad = np.sum(flat * (gv @ flat), axis=0).reshape(len(order), k).sum(axis=1)
    cross = np.einsum("rck,rk->c", padded, mv)
    sse = split.sum_sq_v - 2.0 * cross + quad
    xv = yv = None
    for column, i in enumerate(order):
        value = float(sse[column])
        if value <= _DIRECT_RESIDUAL_FRACTION * split.sum_sq_v:
            if xv is None:
                xv, yv = split.X[split.valid], split.Y[split.valid]
            p = int(sizes[i])
            residual = yv - xv[:, cols[:p]] @ padded[:p, column]
            value = float(np.sum(residual * residual))
        result.errors[s, g, i] = max(value, 0.0) / max(split.valid.size, 1)


def _skip_larger(result: CVResult, g: int, i: int, n_sizes: int, reason: str) -> None:
    """Skip candidate (g, i) and all larger ones of group g (a column superset is no better)."""
    for k in range(i, n_sizes):
        result.skipped.setdefault((g, k), reason)


# -- model selection --------------------------------------------------------------------
def one_standard_error_1d(mean: np.ndarray, std: np.ndarray) -> int:
    """Smallest index whose mean error is within one std of the minimum (NaN = skipped)."""
    mean = np.asarray(mean, dtype=np.float64)
    if not np.any(np.isfinite(mean)):
        raise DataError("no candidate model could be cross-validated")
    best = int(np.nanargmin(mean))
    ok = np.isfinite(mean) & (mean - mean[best] <= std[best])
    return int(np.flatnonzero(ok)[0])


def one_standard_error_2d(mean: np.ndarray, std: np.ndarray) -> tuple[int, int]:
    """Degrees (d, b) by thesis Algorithm 1, lines 18–21, from tables indexed [d, b].

    e_min is the smallest mean error and s the standard deviation at that (d, b); b is the
    smallest λ degree with some e_db − e_min ≤ s, then d the smallest spatial degree with
    e_db − e_min ≤ s at that b.
    """
    mean = np.asarray(mean, dtype=np.float64)
    if not np.any(np.isfinite(mean)):
        raise DataError("no candidate model could be cross-validated")
    d0, b0 = np.unravel_index(int(np.nanargmin(mean)), mean.shape)
    ok = np.isfinite(mean) & (mean - mean[d0, b0] <= std[d0, b0])
    b = int(np.flatnonzero(ok.any(axis=0))[0])
    d = int(np.flatnonzero(ok[:, b])[0])
    return d, b


def table(values: np.ndarray) -> list:
    """(Nested) lists of floats for YAML, None where a value is NaN (a skipped candidate)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim > 1:
        return [table(row) for row in values]
    return [float(v) if np.isfinite(v) else None for v in values]


def check_count(name: str, value: object, *, least: int) -> int:
    """`value` as an int of at least `least` (a bool is not a count); a ConfigError naming
    `name` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < least:
        wanted = "a non-negative integer" if least == 0 else f"an integer ≥ {least}"
        raise ConfigError(f"{name} must be {wanted}, got {value!r}")
    return int(value)
