"""A small container for sampled spectra, and wavelength-grid resampling."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from labkit.errors import DataError

Extrapolation = Literal["zero", "constant", "error"]


def wavelength_grid(start_nm: float, stop_nm: float, step_nm: float) -> np.ndarray:
    """Wavelengths start_nm, start_nm + step_nm, … up to and including `stop_nm`, in nm.

    The last sample is the largest one ≤ `stop_nm` (it equals `stop_nm` when the range is a
    multiple of the step).
    """
    if step_nm <= 0 or stop_nm <= start_nm:
        raise DataError(
            f"wavelength grid {start_nm}–{stop_nm} nm with step {step_nm} nm is empty; "
            "use start < stop and a positive step"
        )
    count = int(np.floor((stop_nm - start_nm) / step_nm + 1e-9)) + 1
    return start_nm + step_nm * np.arange(count, dtype=np.float64)


@dataclass(frozen=True)
class Spectra:
    """One or more spectra sampled on a common wavelength grid.

    Attributes
    ----------
    wavelengths : ndarray, shape (n,)
        Strictly increasing sample wavelengths, nm.
    values : ndarray, shape (n, k)
        One column per spectrum (relative units unless stated by the producer).
    labels : tuple of str, length k
        Column names, e.g. ``("R", "G", "B")`` or ColorChecker patch names.
    """

    wavelengths: np.ndarray
    values: np.ndarray
    labels: tuple[str, ...]

    def __post_init__(self) -> None:
        w = np.asarray(self.wavelengths, dtype=np.float64)
        v = np.asarray(self.values, dtype=np.float64)
        if v.ndim == 1:
            v = v[:, None]
        if w.ndim != 1 or w.size < 2 or v.shape[0] != w.size:
            raise DataError(
                f"spectra need ≥ 2 wavelengths and one value row per wavelength; "
                f"got wavelengths {w.shape} and values {v.shape}"
            )
        if np.any(np.diff(w) <= 0):
            raise DataError("spectrum wavelengths must be strictly increasing (nm)")
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(v))):
            raise DataError("spectrum contains NaN or Inf; clean the source data first")
        if len(self.labels) != v.shape[1]:
            raise DataError(f"{len(self.labels)} labels for {v.shape[1]} spectra")
        object.__setattr__(self, "wavelengths", w)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "labels", tuple(self.labels))

    @property
    def domain(self) -> tuple[float, float]:
        """First and last sampled wavelength, nm."""
        return float(self.wavelengths[0]), float(self.wavelengths[-1])

    def __getitem__(self, label: str) -> np.ndarray:
        """The values of the spectrum named `label`, shape (n,)."""
        try:
            return self.values[:, self.labels.index(label)]
        except ValueError:
            raise KeyError(f"no spectrum named {label!r}; have {list(self.labels)}") from None

    def select(self, labels: Sequence[str]) -> Spectra:
        """A new container holding only `labels`, in that order."""
        columns = [self.labels.index(name) for name in labels]
        return Spectra(self.wavelengths, self.values[:, columns], tuple(labels))

    def scaled(self, factor: float | np.ndarray) -> Spectra:
        """Values multiplied by `factor` (a scalar or one factor per wavelength)."""
        factor = np.asarray(factor, dtype=np.float64)
        if factor.ndim == 1:
            factor = factor[:, None]
        return Spectra(self.wavelengths, self.values * factor, self.labels)

    def resample(self, wavelengths: np.ndarray, *, extrapolate: Extrapolation = "zero") -> Spectra:
        """Linearly interpolate onto `wavelengths` (nm).

        Parameters
        ----------
        wavelengths : ndarray, shape (m,)
            Target grid, nm, strictly increasing.
        extrapolate : {"zero", "constant", "error"}
            Outside the sampled domain: zero (e.g. a sensor response beyond its
            measurement), the nearest end value, or raise :class:`DataError`.
        """
        target = np.asarray(wavelengths, dtype=np.float64)
        lo, hi = self.domain
        outside = (target < lo - 1e-9) | (target > hi + 1e-9)
        if extrapolate == "error" and outside.any():
            raise DataError(
                f"spectra {list(self.labels)[:3]}… cover {lo:g}–{hi:g} nm but "
                f"{target[outside].min():g}–{target[outside].max():g} nm was requested; "
                "restrict the wavelengths or supply data that covers them"
            )
        columns = [np.interp(target, self.wavelengths, col) for col in self.values.T]
        values = np.stack(columns, axis=1)
        if extrapolate == "zero":
            values[outside] = 0.0
        return Spectra(target, values, self.labels)


def hat_weights(values: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Linear-interpolation weights φ_j(v_i), shape (n_nodes, n_values); columns sum to 1.

    φ_j is the hat function of node j on the increasing `nodes`; beyond the end nodes the
    weights stay at the nearest node (constant extension). One node gives weight 1.
    """
    values = np.asarray(values, dtype=np.float64)
    nodes = np.asarray(nodes, dtype=np.float64)
    if nodes.size == 1:
        return np.ones((1, values.size))
    position = np.interp(values, nodes, np.arange(nodes.size, dtype=np.float64))
    lower = np.clip(np.floor(position).astype(int), 0, nodes.size - 2)
    frac = position - lower
    weights = np.zeros((nodes.size, values.size))
    columns = np.arange(values.size)
    weights[lower, columns] = 1.0 - frac
    weights[lower + 1, columns] += frac
    return weights


def trapezoid_weights(wavelengths: np.ndarray) -> np.ndarray:
    """Weights w such that ``sum(w * f)`` is the trapezoid-rule integral of f, nm.

    Thesis (3.6) integrates spectra against responses this way.
    """
    w = np.asarray(wavelengths, dtype=np.float64)
    if w.ndim != 1 or w.size < 2 or np.any(np.diff(w) <= 0):
        raise DataError("trapezoid weights need ≥ 2 strictly increasing wavelengths (nm)")
    gaps = np.diff(w)
    weights = np.zeros_like(w)
    weights[:-1] += gaps / 2
    weights[1:] += gaps / 2
    return weights
