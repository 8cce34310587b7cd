"""Polynomial displacement fields: evaluation and their entry in model files (§3.2.4).

A :class:`PolynomialField` is one term of a :class:`~calibration.dispersion_model.DispersionModel`:
Legendre polynomials of normalised (x, y[, λ]) for both displacement components.
:func:`calibration.polynomial.fit_polynomial_model` fits them to keypoints.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from calibration import _polybasis as pb
from calibration._model_files import float_array
from calibration._normalise import Normaliser
from labkit.errors import ConfigError, DataError


@dataclass(frozen=True, eq=False)
class PolynomialField:
    """A polynomial displacement field in normalised coordinates.

    ``d(p) = restore(Σ_m c_m · Π_v P_{e_mv}(t_v))`` where ``t = domain(normaliser.inputs(p))``
    and P_n is the Legendre polynomial of degree n.

    Attributes
    ----------
    normaliser : Normaliser
        Input (x, y[, λ]) and output (dx, dy) normalisation.
    domain : Domain
        Affine map of normalised inputs onto [−1, 1] (the keypoints' range).
    exponents : ndarray (m, 2 | 3) int
        Legendre degrees (i, j[, k]) of each term.
    coefficients : ndarray (m, 2)
        Coefficients of the normalised dx and dy.
    """

    normaliser: Normaliser
    domain: pb.Domain
    exponents: np.ndarray
    coefficients: np.ndarray

    kind: ClassVar[str] = "polynomial"
    basis: ClassVar[str] = "legendre"

    def __post_init__(self) -> None:
        exps = np.asarray(self.exponents, dtype=np.int64)
        coef = np.asarray(self.coefficients, dtype=np.float64)
        k = self.normaliser.n_inputs
        if exps.ndim != 2 or exps.shape[1] != k or coef.shape != (exps.shape[0], 2):
            raise DataError(
                f"polynomial field: exponents {exps.shape} and coefficients {coef.shape} "
                f"do not match a field of {k} inputs"
            )
        if np.shape(self.domain.centre) != (k,) or np.shape(self.domain.half_width) != (k,):
            raise DataError(f"polynomial field: the domain must have {k} coordinates")
        object.__setattr__(self, "exponents", exps)
        object.__setattr__(self, "coefficients", coef)
        # evaluation plan: distinct (i, j) pairs × λ degrees → coefficient tensor
        pairs, pair_index = np.unique(exps[:, :2], axis=0, return_inverse=True)
        n_lambda = int(exps[:, 2].max()) + 1 if k == 3 else 1
        tensor = np.zeros((len(pairs), n_lambda, 2))
        tensor[pair_index.ravel(), exps[:, 2] if k == 3 else 0] = coef
        object.__setattr__(self, "_pairs", pairs)
        object.__setattr__(self, "_tensor", tensor)

    @property
    def degree_xy(self) -> int:
        """Total degree in (x, y)."""
        return int((self.exponents[:, 0] + self.exponents[:, 1]).max())

    @property
    def degree_lambda(self) -> int | None:
        """Degree in λ (None for a bivariate field)."""
        return int(self.exponents[:, 2].max()) if self.normaliser.n_inputs == 3 else None

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Displacements (n, 2) px at `points` (n, 2) = (x, y) px or (n, 3) = (x, y, λ nm)."""
        points = np.asarray(points)
        k = self.normaliser.n_inputs
        if points.ndim != 2 or points.shape[1] != k:
            raise DataError(
                f"this polynomial field takes points of shape (n, {k}), got {points.shape}"
            )
        pairs, tensor = self._pairs, self._tensor  # type: ignore[attr-defined]
        n_lambda = tensor.shape[1]
        max_i, max_j = int(pairs[:, 0].max()), int(pairs[:, 1].max())
        out = np.empty((len(points), 2))
        # Elementwise accumulation, no BLAS: as fast as a matrix product for these few
        # terms, and immune to BLAS thread contention (callers may run many in parallel).
        for start in range(0, len(points), pb.CHUNK_ROWS):
            t = self.domain(self.normaliser.inputs(points[start : start + pb.CHUNK_ROWS]))
            px = pb.legendre_table(t[:, 0], max_i)
            py = pb.legendre_table(t[:, 1], max_j)
            pl = pb.legendre_table(t[:, 2], n_lambda - 1) if k == 3 else None
            acc = np.zeros((2, len(t)))
            for (i, j), coef in zip(pairs, tensor, strict=True):  # coef: (n_lambda, 2)
                v = px[i] * py[j]
                if pl is None:
                    acc += coef[0][:, None] * v
                else:
                    spectral = coef[0][:, None] * pl[0]
                    for b in range(1, n_lambda):
                        spectral += coef[b][:, None] * pl[b]
                    acc += spectral * v
            out[start : start + pb.CHUNK_ROWS] = self.normaliser.restore(acc.T)
        return out

    def evaluate_grid(self, xy: np.ndarray, wavelengths_nm: np.ndarray) -> np.ndarray:
        """Displacements (m, w, 2) px at every position of `xy` (m, 2) px for every
        wavelength of `wavelengths_nm` (w,) nm: the field is a sum of (x, y) polynomials
        times λ polynomials, so each factor is evaluated once on its own points (m + w
        rather than m · w evaluations)."""
        if self.normaliser.n_inputs != 3:
            raise DataError("evaluate_grid needs a spectral (x, y, λ) field")
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        waves = np.asarray(wavelengths_nm, dtype=np.float64).ravel()
        pairs, tensor = self._pairs, self._tensor  # type: ignore[attr-defined]
        n_lambda = tensor.shape[1]
        points = np.zeros((len(waves), 3))
        points[:, 2] = waves
        t_lambda = self.domain(self.normaliser.inputs(points))[:, 2]
        # per (x, y) pair: its λ polynomial at every wavelength, (pairs, w, 2)
        spectral = np.einsum("pbk,bw->pwk", tensor, pb.legendre_table(t_lambda, n_lambda - 1))
        out = np.empty((len(xy), len(waves), 2))
        max_i, max_j = int(pairs[:, 0].max()), int(pairs[:, 1].max())
        for start in range(0, len(xy), pb.CHUNK_ROWS):
            chunk = xy[start : start + pb.CHUNK_ROWS]
            t = self.domain(self.normaliser.inputs(np.column_stack([chunk, np.zeros(len(chunk))])))
            px = pb.legendre_table(t[:, 0], max_i)
            py = pb.legendre_table(t[:, 1], max_j)
            spatial = px[pairs[:, 0]] * py[pairs[:, 1]]  # (pairs, chunk)
            acc = np.einsum("pm,pwk->mwk", spatial, spectral)
            out[start : start + pb.CHUNK_ROWS] = self.normaliser.restore(acc)
        return out

    # -- files ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "basis": self.basis,
            "degree_xy": self.degree_xy,
            "degree_lambda": self.degree_lambda,
            "normaliser": self.normaliser.to_dict(),
            "domain": self.domain.to_dict(),
            "exponents": self.exponents.tolist(),
            "coefficients": self.coefficients.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Any, where: str) -> PolynomialField:
        """Read back :meth:`to_dict`, validating every key; errors name `where`.key."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where} must be a mapping")
        for key in (
            "basis",
            "degree_xy",
            "degree_lambda",
            "normaliser",
            "domain",
            "exponents",
            "coefficients",
        ):
            if key not in data:
                raise ConfigError(f"{where}.{key} is missing")
        if data.get("kind", "polynomial") != "polynomial":
            raise ConfigError(f"{where}.kind is {data.get('kind')!r}, expected 'polynomial'")
        if data["basis"] != cls.basis:
            raise ConfigError(f"{where}.basis is {data['basis']!r}; this labkit reads 'legendre'")
        normaliser = Normaliser.from_dict(data["normaliser"], f"{where}.normaliser")
        k = normaliser.n_inputs
        domain_data = data["domain"]
        if not isinstance(domain_data, Mapping):
            raise ConfigError(f"{where}.domain must be a mapping with centre and half_width")
        centre = float_array(domain_data.get("centre"), f"{where}.domain.centre", shape=(k,))
        half = float_array(domain_data.get("half_width"), f"{where}.domain.half_width", shape=(k,))
        if np.any(half <= 0):
            raise ConfigError(f"{where}.domain.half_width must be positive")
        exps = _exponents(data["exponents"], f"{where}.exponents", k)
        coef = float_array(data["coefficients"], f"{where}.coefficients", shape=(len(exps), 2))
        for key, value, want in (
            ("degree_xy", data["degree_xy"], int((exps[:, 0] + exps[:, 1]).max())),
            ("degree_lambda", data["degree_lambda"], int(exps[:, 2].max()) if k == 3 else None),
        ):
            if value != want or isinstance(value, bool):
                raise ConfigError(f"{where}.{key} is {value!r} but the exponents give {want!r}")
        return cls(normaliser, pb.Domain(centre, half), exps, coef)


def _exponents(value: Any, where: str, k: int) -> np.ndarray:
    """Validated exponent table: distinct rows of `k` non-negative integers."""
    try:
        exps = np.asarray(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{where} must be a list of [i, j{', k' if k == 3 else ''}] rows"
        ) from None
    if exps.ndim != 2 or exps.shape[1] != k or exps.shape[0] == 0:
        raise ConfigError(
            f"{where} must be a non-empty list of rows of {k} integers, got shape {exps.shape}"
        )
    if exps.dtype.kind not in "iu" or np.any(exps < 0):
        raise ConfigError(f"{where} must hold non-negative integers")
    if len(np.unique(exps, axis=0)) != len(exps):
        raise ConfigError(f"{where} has repeated rows")
    return exps.astype(np.int64)
