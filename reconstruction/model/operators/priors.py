"""Difference operators of the regularisation priors (thesis §3.5, Table 3.1, (3.14)–(3.20)).

* :class:`Gradient` — spatial gradient ∇_xy (3.15), the operator of prior S₁ (3.14);
* :class:`SpectralGradient` — spectral-spatial mixed gradient ∇_λ∇_xy (3.17)–(3.18),
  the operator of prior S₂;
* :class:`Laplacian` — 5-point spatial Laplacian ∇²_xy (3.20), the operator of prior S₃;
* :class:`WeightedGradient` — ∇_xy with a weight per pixel and direction (the edge-guided
  L2 prior, beyond the thesis).

Conventions
-----------
Images are (rows, cols, k) channels-last; x is the column index (axis 1), y the row index
(axis 0). Gradients stack their two components last: ``[..., 0]`` along x, ``[..., 1]``
along y. Differences are forward differences, ``(D f)[i] = f[i+1] − f[i]``.

Boundary
--------
``boundary="periodic"`` (default): the image wraps around, ``f[n] ≡ f[0]``, so the last
column/row difference is ``f[0] − f[n−1]``. Every spatial operator is then circulant
(diagonalised by the 2-D DFT), which the FFT solver of the normal equations needs;
:meth:`fourier_symbol` gives the per-frequency multipliers.

``boundary="neumann"``: the difference at the far edge (last column/row) is zero. The
Laplacian is then ``D_xᵀD_x + D_yᵀD_y``, i.e. (3.20) inside and mirrored at the edges.
Not circulant: no Fourier symbol.

The spectral difference (3.18) of :class:`SpectralGradient` is never wrapped: k bands
give k − 1 differences (Δλ = one band; the thesis's band spacing is uniform).

Fourier convention
------------------
NumPy's ``fft2`` over axes (0, 1), ``F(u)[ky, kx] = Σ u[y, x] exp(−2πi (ky y/rows + kx x/cols))``.
A periodic forward difference along x multiplies ``F`` by ``exp(2πi kx/cols) − 1``, so
``forward(u) = ifft2(symbol · fft2(u))`` (real part). For the normal equations only
``|symbol|²`` matters (e.g. ``4 − 2cos(2πkx/cols) − 2cos(2πky/rows)`` for ``∇ᵀ∇``, equal to
the Laplacian's symbol).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from labkit.errors import DataError
from reconstruction.model.operators._base import LinearOperator

Boundary = Literal["periodic", "neumann"]
BOUNDARIES = ("periodic", "neumann")


def _check_boundary(boundary: str) -> str:
    if boundary not in BOUNDARIES:
        raise DataError(f"unknown boundary {boundary!r}; use one of {', '.join(BOUNDARIES)}")
    return boundary


def _check_shape(shape: tuple[int, ...], what: str, min_channels: int = 1) -> tuple[int, int, int]:
    values = tuple(int(n) for n in shape)
    if len(values) != 3 or min(values[:2]) < 1 or values[2] < min_channels:
        raise DataError(
            f"{what} needs a domain shape (rows, cols, channels) with rows, cols ≥ 1 and "
            f"channels ≥ {min_channels}, got {values}"
        )
    return values[0], values[1], values[2]


def _along(axis: int, ndim: int, part: slice) -> tuple[slice, ...]:
    index = [slice(None)] * ndim
    index[axis] = part
    return tuple(index)


def _periodic_difference(u: np.ndarray, axis: int, out: np.ndarray, sign: int) -> np.ndarray:
    """``out = roll(u, -sign) − u`` along `axis`, by slices (np.roll copies the whole array)."""
    head, tail = slice(None, -1), slice(1, None)
    first, last = slice(None, 1), slice(-1, None)
    # (source, target): out[target] = u[source] − u[target], the inner run and the wrap
    if sign > 0:  # u[i+1] − u[i]
        pairs = ((tail, head), (first, last))
    else:  # u[i−1] − u[i]
        pairs = ((head, tail), (last, first))
    for source, target in pairs:
        at = _along(axis, u.ndim, target)
        np.subtract(u[_along(axis, u.ndim, source)], u[at], out=out[at])
    return out


def difference(u: np.ndarray, axis: int, boundary: str) -> np.ndarray:
    """Forward difference ``u[i+1] − u[i]`` along `axis` (same shape as `u`)."""
    if boundary == "periodic":
        return _periodic_difference(u, axis, np.empty_like(u), 1)
    out = np.zeros_like(u)
    inner = [slice(None)] * u.ndim
    inner[axis] = slice(0, -1)
    out[tuple(inner)] = np.diff(u, axis=axis)
    return out


def difference_adjoint(v: np.ndarray, axis: int, boundary: str) -> np.ndarray:
    """Adjoint of :func:`difference`: ``v[i−1] − v[i]`` with the boundary's end terms."""
    if boundary == "periodic":
        return _periodic_difference(v, axis, np.empty_like(v), -1)
    n = v.shape[axis]
    kept = np.take(v, np.arange(n - 1), axis=axis)  # the far-edge difference is always 0
    zero = np.zeros_like(np.take(v, [0], axis=axis))
    return np.concatenate([zero, kept], axis=axis) - np.concatenate([kept, zero], axis=axis)


def difference_symbol(n: int) -> np.ndarray:
    """DFT multiplier ``exp(2πi k/n) − 1`` (k = 0 … n−1) of the periodic forward difference."""
    return np.exp(2j * np.pi * np.arange(n) / n) - 1.0


class _SpatialDifference(LinearOperator):
    """Shared boundary handling and Fourier symbols of the spatial difference operators."""

    boundary: str

    def _spatial_shape(self, shape: tuple[int, int] | None) -> tuple[int, int]:
        if self.boundary != "periodic":
            raise DataError(
                f"{self.name} with boundary {self.boundary!r} is not circulant and has no "
                "Fourier symbol; construct it with boundary='periodic' for FFT solvers"
            )
        rows, cols = self.domain_shape[:2] if shape is None else tuple(int(n) for n in shape)
        return rows, cols

    def _gradient_symbol(self, shape: tuple[int, int] | None) -> np.ndarray:
        rows, cols = self._spatial_shape(shape)
        sx = np.broadcast_to(difference_symbol(cols)[None, :], (rows, cols))
        sy = np.broadcast_to(difference_symbol(rows)[:, None], (rows, cols))
        return np.stack([sx, sy], axis=-1)

    def _gradient(self, u: np.ndarray) -> np.ndarray:
        if self.boundary != "periodic":
            return np.stack(
                [difference(u, 1, self.boundary), difference(u, 0, self.boundary)], axis=-1
            )
        out = np.empty((*u.shape, 2), dtype=np.result_type(u))
        _periodic_difference(u, 1, out[..., 0], 1)
        _periodic_difference(u, 0, out[..., 1], 1)
        return out

    def _gradient_adjoint(self, g: np.ndarray) -> np.ndarray:
        if self.boundary != "periodic":
            return difference_adjoint(g[..., 0], 1, self.boundary) + difference_adjoint(
                g[..., 1], 0, self.boundary
            )
        out = _periodic_difference(g[..., 0], 1, np.empty(g.shape[:-1], g.dtype), -1)
        out += _periodic_difference(g[..., 1], 0, np.empty(g.shape[:-1], g.dtype), -1)
        return out


class Gradient(_SpatialDifference):
    """Spatial gradient ∇_xy (3.15): (rows, cols, k) → (rows, cols, k, 2).

    ``out[y, x, c, 0] = u[y, x+1, c] − u[y, x, c]`` and
    ``out[y, x, c, 1] = u[y+1, x, c] − u[y, x, c]``, per channel c.

    Parameters
    ----------
    shape : tuple of int
        Domain shape (rows, cols, k): pixels and channels (bands or colour channels).
    boundary : {"periodic", "neumann"}
        Wrap-around (default, circulant) or zero difference at the last column/row.
    """

    name = "∇xy"

    def __init__(self, shape: tuple[int, int, int], *, boundary: Boundary = "periodic") -> None:
        shape = _check_shape(shape, "Gradient")
        self.boundary = _check_boundary(boundary)
        super().__init__(shape, (*shape, 2))

    def fourier_symbol(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Per-frequency multipliers, complex (rows, cols, 2): ``[..., 0]`` x, ``[..., 1]`` y.

        ``forward(u)[..., c, d] = ifft2(symbol[..., d] · fft2(u[..., c]))`` (periodic only).
        `shape` (rows, cols) defaults to the operator's image size.
        """
        return self._gradient_symbol(shape)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return self._gradient(x)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self._gradient_adjoint(y)


class WeightedGradient(LinearOperator):
    """Spatial gradient with a weight per pixel and direction: ``√w ⊙ ∇xy``.

    ``out[y, x, c, d] = √(w[y, x, d] · f[c]) · (∇xy u)[y, x, c, d]``, so that
    ``‖out‖² = Σ w f |∇xy u|²``: the edge-guided L2 prior's operator
    (:mod:`reconstruction.model.edge_weights`), and with band factors f the band-balanced L2
    priors' (:mod:`reconstruction.model.band_balance`). Periodic boundary, as :class:`Gradient`;
    not circulant unless the weights are constant, so it has no Fourier symbol (the FFT
    solvers take the weights' mean instead).

    Parameters
    ----------
    shape : tuple of int
        Domain shape (rows, cols, k).
    weights : ndarray (rows, cols, 2), optional
        w ≥ 0 of each forward difference, ``[..., 0]`` along x, ``[..., 1]`` along y;
        default 1.
    band_factors : ndarray (k,), optional
        f ≥ 0 of each channel; default 1 (every channel shares the weights).
    """

    name = "√w∇xy"

    def __init__(
        self,
        shape: tuple[int, int, int],
        weights: np.ndarray | None = None,
        band_factors: np.ndarray | None = None,
    ) -> None:
        shape = _check_shape(shape, "WeightedGradient")
        uniform = weights is None
        weights = np.ones((*shape[:2], 2)) if uniform else np.asarray(weights, float)
        if weights.shape != (*shape[:2], 2):
            raise DataError(
                f"WeightedGradient needs weights of shape {(*shape[:2], 2)} (rows, cols, "
                f"direction), got {weights.shape}"
            )
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise DataError("WeightedGradient's weights must be finite and ≥ 0")
        factors = np.ones(shape[2]) if band_factors is None else np.asarray(band_factors, float)
        if factors.shape != (shape[2],):
            raise DataError(
                f"WeightedGradient needs one band factor per channel ({shape[2]}), got shape "
                f"{factors.shape}"
            )
        if not np.all(np.isfinite(factors)) or np.any(factors < 0):
            raise DataError("WeightedGradient's band factors must be finite and ≥ 0")
        super().__init__(shape, (*shape, 2))
        self.weights = weights
        self.band_factors = factors
        self._gradient = Gradient(shape)
        # √w ⊙ √f, broadcast against (rows, cols, k, 2): without weights only the (k, 1)
        # band factors, not a full-size array of ones, multiply every gradient
        per_band = None if band_factors is None else np.sqrt(factors)[:, None]
        if uniform:
            self._root = np.ones((1, 1)) if per_band is None else per_band
        else:
            root = np.sqrt(weights)[:, :, None, :]
            self._root = root if per_band is None else root * per_band

    def _forward(self, x: np.ndarray) -> np.ndarray:
        out = self._gradient.forward(x)
        out *= self._root
        return out

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self._gradient.adjoint(y * self._root)


class SpectralGradient(_SpatialDifference):
    """Spectral-spatial gradient ∇_λ∇_xy (3.17)–(3.18): (rows, cols, k) → (rows, cols, k−1, 2).

    ``out[..., b, d] = (∇_xy u)[..., b+1, d] − (∇_xy u)[..., b, d]`` for b = 0 … k−2: the
    spectral forward difference (one band apart, not wrapped) of the spatial gradient.
    The two differences commute, so this is also ∇_xy of the band differences.

    Parameters
    ----------
    shape : tuple of int
        Domain shape (rows, cols, k), k ≥ 2 spectral bands.
    boundary : {"periodic", "neumann"}
        Spatial boundary, as for :class:`Gradient`.
    """

    name = "∇λ∇xy"

    def __init__(self, shape: tuple[int, int, int], *, boundary: Boundary = "periodic") -> None:
        shape = _check_shape(shape, "SpectralGradient", min_channels=2)
        self.boundary = _check_boundary(boundary)
        rows, cols, k = shape
        super().__init__(shape, (rows, cols, k - 1, 2))

    @property
    def spectral_matrix(self) -> np.ndarray:
        """The spectral difference D_λ as a (k−1, k) matrix: row b is ``e_{b+1} − e_b``."""
        return _spectral_difference_matrix(self.domain_shape[2])

    def fourier_symbol(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Spatial multipliers, complex (rows, cols, 2), as :meth:`Gradient.fourier_symbol`.

        The operator is their Kronecker product with :attr:`spectral_matrix`:
        ``forward(u)[..., :, d] = ifft2(symbol[..., None, d] · fft2(u @ D_λᵀ))``. For the
        normal equations, ``(|s_x|² + |s_y|²) ⊗ D_λᵀD_λ`` per spatial frequency.
        """
        return self._gradient_symbol(shape)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return self._gradient(np.diff(x, axis=2))

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return _spectral_difference_adjoint(self._gradient_adjoint(y))


class SpectralDifference(LinearOperator):
    """Spectral difference ∇_λ alone: (rows, cols, k) → (rows, cols, k−1).

    ``out[..., b] = u[..., b+1] − u[..., b]``: the roughness of each pixel's spectrum. Its
    normal matrix is ``D_λᵀD_λ`` at every spatial frequency (spatial symbol 1).
    """

    name = "∇λ"

    def __init__(self, shape: tuple[int, int, int]) -> None:
        shape = _check_shape(shape, "SpectralDifference", min_channels=2)
        rows, cols, k = shape
        super().__init__(shape, (rows, cols, k - 1))

    @property
    def spectral_matrix(self) -> np.ndarray:
        """D_λ as a (k−1, k) matrix: row b is ``e_{b+1} − e_b``."""
        return _spectral_difference_matrix(self.domain_shape[2])

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return np.diff(x, axis=2)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return _spectral_difference_adjoint(y)


class SpectralRoughness(LinearOperator):
    """Roughness of each pixel's spectrum, with the patch's mean colour left free:
    (rows, cols, k) → (rows, cols, k−1).

    ``S x = D_λ x − D_λ R C x̄``, where x̄ is the patch's mean spectrum (broadcast to every
    pixel) and ``R C x̄`` is the smoothest spectrum of its colour ``C x̄`` (
    :func:`smoothest_metamer`). In the Fourier domain S is ``D_λ`` at every spatial
    frequency but DC, and ``D_λ P`` at DC, with ``P = I − R C`` the part of a spectrum its
    colour does not fix. So ``‖S x‖²`` penalises rough spectra wherever the image varies,
    yet never trades the patch's mean colour for smoothness: only the unseen part of its
    mean spectrum is smoothed (a flat patch of narrow-band light keeps its colour unless
    non-negativity leaves it only rough spectra).

    Parameters
    ----------
    shape : (rows, cols, k)
        Latent image shape, k ≥ 2.
    colour : ndarray (channels, k)
        The per-pixel colour matrix C (any scale).
    """

    name = "∇λ(I − RC̄)"

    def __init__(self, shape: tuple[int, int, int], colour: np.ndarray) -> None:
        shape = _check_shape(shape, "SpectralRoughness", min_channels=2)
        rows, cols, k = shape
        super().__init__(shape, (rows, cols, k - 1))
        d = _spectral_difference_matrix(k)
        self.unseen = d @ (np.eye(k) - smoothest_metamer(colour))
        """D_λ P (k−1 × k): the roughness of a spectrum's part its colour does not fix."""
        self._mean_part = d - self.unseen  # D_λ R C

    def fourier_pieces(self, shape: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """SᵀS as (spatial symbol, k × k matrix) pairs: ``D_λᵀD_λ`` everywhere, corrected
        at DC to ``(D_λP)ᵀ(D_λP)``."""
        k = self.domain_shape[2]
        d = _spectral_difference_matrix(k)
        dc = np.zeros(shape)
        dc[0, 0] = 1.0
        return [(np.ones(shape), d.T @ d), (dc, self.unseen.T @ self.unseen - d.T @ d)]

    def _forward(self, x: np.ndarray) -> np.ndarray:
        mean = x.mean(axis=(0, 1), keepdims=True)
        return np.diff(x, axis=2) - mean @ self._mean_part.T.astype(x.dtype, copy=False)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        rows, cols = y.shape[:2]
        mean = y.sum(axis=(0, 1), keepdims=True) / (rows * cols)
        return _spectral_difference_adjoint(y) - mean @ self._mean_part.astype(y.dtype, copy=False)


METAMER_CONDITION_LIMIT = 1e10
"""Largest condition number of the smoothest-metamer system before it counts as singular."""


def smoothest_metamer(colour: np.ndarray) -> np.ndarray:
    """``R C`` (k × k): a spectrum → the smoothest spectrum of the same colour.

    The smoothest spectrum is ``argmin ‖D_λ s‖²`` over s with ``C s = C x``: with N an
    orthonormal basis of C's null space (the metamers' directions), ``s = x − N z`` and
    ``z = (NᵀD_λᵀD_λN)⁻¹ NᵀD_λᵀD_λ x``. C is normalised first (its scale is arbitrary) and
    its rank found by SVD; with as many channels as bands there are no metamers
    (the identity).

    Raises
    ------
    DataError
        When a constant spectrum gives zero colour (no smoothest metamer exists).
    """
    c = np.asarray(colour, dtype=np.float64)
    k = c.shape[1]
    c = c / np.linalg.norm(c)
    _, singular, vt = np.linalg.svd(c)
    rank = int(np.sum(singular > 1e-10 * singular[0]))
    null = vt[rank:].T  # (k, k − rank)
    if null.shape[1] == 0:
        return np.eye(k)
    d = _spectral_difference_matrix(k)
    dn = d @ null
    gram = dn.T @ dn
    if np.linalg.cond(gram) > METAMER_CONDITION_LIMIT:
        raise DataError(
            "the colour matrix gives a constant spectrum zero colour, so no smoothest metamer "
            "exists; check the camera response over the bands"
        )
    return np.eye(k) - null @ np.linalg.solve(gram, dn.T @ d)


def _spectral_difference_matrix(k: int) -> np.ndarray:
    """D_λ, the forward difference along k bands, as a (k−1, k) matrix."""
    return np.eye(k - 1, k, 1) - np.eye(k - 1, k)


def _spectral_difference_adjoint(z: np.ndarray) -> np.ndarray:
    """D_λᵀ along axis 2: (rows, cols, k−1, …) → (rows, cols, k, …)."""
    zero = np.zeros_like(z[:, :, :1])
    return np.concatenate([zero, z], axis=2) - np.concatenate([z, zero], axis=2)


class Laplacian(_SpatialDifference):
    """Five-point spatial Laplacian ∇²_xy (3.20): (rows, cols, k) → (rows, cols, k).

    ``out = 4u[y, x] − u[y, x+1] − u[y, x−1] − u[y+1, x] − u[y−1, x]`` per channel (the
    thesis's sign: positive semi-definite). It equals ``D_xᵀD_x + D_yᵀD_y`` for the
    forward differences of :class:`Gradient`, so it is self-adjoint.

    Parameters
    ----------
    shape : tuple of int
        Domain shape (rows, cols, k).
    boundary : {"periodic", "neumann"}
        Wrap-around (default), or mirrored edges (``D_xᵀD_x + D_yᵀD_y`` with Neumann
        differences: missing neighbours are replaced by the pixel itself).
    """

    name = "∇²xy"

    def __init__(self, shape: tuple[int, int, int], *, boundary: Boundary = "periodic") -> None:
        shape = _check_shape(shape, "Laplacian")
        self.boundary = _check_boundary(boundary)
        super().__init__(shape, shape)

    def fourier_symbol(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Real per-frequency multiplier (rows, cols): ``4 − 2cos(2πkx/cols) − 2cos(2πky/rows)``.

        ``forward(u)[..., c] = ifft2(symbol · fft2(u[..., c]))`` (periodic only).
        """
        rows, cols = self._spatial_shape(shape)
        sx = 2.0 - 2.0 * np.cos(2.0 * np.pi * np.arange(cols) / cols)
        sy = 2.0 - 2.0 * np.cos(2.0 * np.pi * np.arange(rows) / rows)
        return sy[:, None] + sx[None, :]

    def _forward(self, x: np.ndarray) -> np.ndarray:
        b = self.boundary
        return difference_adjoint(difference(x, 1, b), 1, b) + difference_adjoint(
            difference(x, 0, b), 0, b
        )

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self._forward(y)
