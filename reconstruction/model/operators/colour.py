"""Spectral-to-colour operator Ω of problem (3.1) (thesis §3.3.1, equation (3.6)).

Ω integrates each pixel's spectrum against the camera's channel responses Q_c(λ),
``I_c = ∫ Q_c(λ) S(λ) dλ`` with G = 1, discretised by the trapezoid rule over the
spectral image's band centres. It is a per-pixel (3 × bands) matrix.
"""

from __future__ import annotations

import numpy as np

from labkit.cfa import CHANNELS
from labkit.errors import DataError
from labkit.spectra import Spectra, integration_matrix
from reconstruction.model.operators._base import LinearOperator


class SpectralToColour(LinearOperator):
    """Ω: (rows, cols, bands) spectral image → (rows, cols, 3) raw colour (R, G, B).

    ``colour[..., c] = Σ_b matrix[c, b] · spectral[..., b]``.

    Parameters
    ----------
    shape : tuple of int
        Image size (rows, cols), pixels.
    matrix : ndarray, shape (3, bands)
        Per-pixel integration matrix; for (3.6) the response times the trapezoid weights,
        units of response × nm (see :meth:`from_response`).

    Notes
    -----
    Float32 inputs are computed in float32 (the matrix is cast); anything else in float64.
    """

    name = "Ω"

    def __init__(self, shape: tuple[int, int], matrix: np.ndarray) -> None:
        size = tuple(int(n) for n in shape)
        matrix = np.asarray(matrix, dtype=np.float64)
        if len(size) != 2 or min(size) < 1:
            raise DataError(
                f"SpectralToColour needs an image size (rows, cols) of positive integers, "
                f"got {size}"
            )
        shape = (size[0], size[1])
        if matrix.ndim != 2 or matrix.shape[0] != 3 or matrix.shape[1] < 1:
            raise DataError(
                f"SpectralToColour needs a (3, bands) matrix (rows R, G, B), got shape "
                f"{matrix.shape}; transpose an (bands, 3) matrix first"
            )
        if not np.all(np.isfinite(matrix)):
            raise DataError("SpectralToColour matrix contains NaN or Inf")
        super().__init__((*shape, matrix.shape[1]), (*shape, 3))
        self.matrix = matrix

    @classmethod
    def from_response(
        cls, shape: tuple[int, int], wavelengths_nm: np.ndarray, response: Spectra
    ) -> SpectralToColour:
        """Ω from camera channel responses by the trapezoid rule, thesis (3.6).

        Parameters
        ----------
        shape : tuple of int
            Image size (rows, cols), pixels.
        wavelengths_nm : ndarray, shape (bands,)
            Band centres of the spectral image, nm, ≥ 2 and strictly increasing.
        response : Spectra
            Channel responses Q_c(λ). If it has channels labelled ``R``, ``G`` and ``B``
            they are used in that order; otherwise it must hold exactly three channels,
            taken as R, G, B. It is linearly interpolated onto the bands and must cover
            their whole range (no extrapolation).

        Raises
        ------
        DataError
            If the response does not cover the bands' wavelength range, or does not have
            three channels.
        """
        wavelengths = np.asarray(wavelengths_nm, dtype=np.float64)
        if wavelengths.ndim != 1 or wavelengths.size < 2 or np.any(np.diff(wavelengths) <= 0):
            raise DataError(
                f"band wavelengths must be ≥ 2 strictly increasing values in nm, got "
                f"{wavelengths!r}"
            )
        if set(CHANNELS) <= set(response.labels):
            response = response.select(list(CHANNELS))
        elif response.values.shape[1] != 3:
            raise DataError(
                f"camera response needs channels R, G, B (or exactly three channels); "
                f"got {list(response.labels)}"
            )
        lo, hi = response.domain
        first, last = float(wavelengths[0]), float(wavelengths[-1])
        if first < lo - 1e-9 or last > hi + 1e-9:
            raise DataError(
                f"camera response covers {lo:g}–{hi:g} nm but the spectral bands span "
                f"{first:g}–{last:g} nm; restrict the bands to the response's range or "
                "supply a response measured over the bands"
            )
        return cls(shape, integration_matrix(wavelengths, response).T)

    def _dtype(self, array: np.ndarray) -> type:
        return np.float32 if array.dtype == np.float32 else np.float64

    def _forward(self, x: np.ndarray) -> np.ndarray:
        dtype = self._dtype(x)
        return x.astype(dtype, copy=False) @ self.matrix.T.astype(dtype)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        dtype = self._dtype(y)
        return y.astype(dtype, copy=False) @ self.matrix.astype(dtype)
