"""Exact FFT solver of the quadratic step: (α AᵀA + Σ c_t D_tᵀD_t + β I) x = b.

Without dispersion, A = M·C with a constant (3 × n) colour matrix C, and every prior
operator D_t is circulant (periodic boundary), so the normal matrix is periodic with the
2×2 period of the Bayer mosaic. The mosaic's channel masks have four Fourier components,
at frequency offsets s ∈ {0, ½}² of the image size, so in the Fourier domain the matrix
couples each frequency k only with k + s·(rows, cols)/2: the system splits into
rows·cols/4 independent Hermitian systems of size 4n, one per frequency *quadruple*.
They are inverted once (batched) and every solve is two FFTs and a batched product;
with dispersion, whose blocks differ from patch to patch, the inverse is kept in the
Woodbury factors it is computed from and applied as such (:class:`_FactoredInverse`).
The image being real, its spectrum and K are conjugate-symmetric, so only one quadruple
of each conjugate pair is inverted and applied (:func:`conjugate_quadruples`): half the
inversion time and memory, and fewer products per solve; the FFTs are real-to-complex,
gathering the kept quadruples from half the spectrum and filling half the spectrum back
from them (:func:`_half_spectrum_maps`; figures in docs/notes/solver.md).

Derivation. A channel mask is ``m_c(y, x) = Σ_s a_{c,s} exp(iπ(s_y y + s_x x))`` with
``a_{c,s} = ¼ Σ_{phases (p, q) of c} (−1)^{s_y p + s_x q}``; multiplying by
``exp(iπ s·p)`` shifts the DFT by ``s·N/2``. Hence for k' = k₀ + s'N/2, k'' = k₀ + s''N/2,
``(AᵀA)[k', k''] = Σ_c a_{c, s'⊕s''} C_c(k')ᴴ C_c(k'')``. With a per-frequency colour matrix
``C(k)`` (dispersion approximated by one translation per wavelength sample, see
:meth:`~reconstruction.model.image_formation.ImageFormation.fourier_colour`) the same holds, so
the solver doubles as the preconditioner of the conjugate-gradient solve with the true Φ.
"""

from __future__ import annotations

import functools
import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.fft

from labkit.cfa import channel_index, check_layout
from labkit.errors import DataError
from reconstruction.model.prior_terms import Term

_QUADS = ((0, 0), (0, 1), (1, 0), (1, 1))  # s = (s_y, s_x), index 2 s_y + s_x

BLOCK_CACHE_SIZE = 6
"""Inverted block sets and impulse responses kept for reuse (:class:`_BlockCache`; a few MB
to tens of MB each)."""

SINGULAR_RESIDUAL = 1e-2
"""Largest relative residual ‖K K⁻¹ v − v‖ / ‖v‖ of the inverse on a random vector v before
the matrix is declared singular (well-posed systems: ≲ 1e-7 even with the 1e-9 ridge)."""

REFINE_RESIDUAL = 1e-12
"""That residual above which solves and impulse responses take a step of iterative
refinement; below it the inverse is already accurate to about that, and the step (a third
of a solve) would change nothing that matters."""

WOODBURY_RESIDUAL = REFINE_RESIDUAL
"""Residual above which a block's Woodbury inverse is replaced by a direct one: at most
the residual below which solves take no refinement step, so that the Woodbury identity
never adds one (a direct inverse of a well-conditioned block: ≈ 1e-15)."""


def mask_coefficients(cfa: str) -> np.ndarray:
    """Fourier coefficients a[c, s] (3, 4) of the channel masks of a Bayer layout."""
    index = channel_index(check_layout(cfa), (2, 2))
    a = np.zeros((3, 4))
    for p in range(2):
        for q in range(2):
            for s, (sy, sx) in enumerate(_QUADS):
                a[index[p, q], s] += 0.25 * (-1.0) ** (sy * p + sx * q)
    return a


def to_quadruples(spectrum: np.ndarray) -> np.ndarray:
    """(rows, cols, …) Fourier array → (rows/2 · cols/2, 4, …) grouped by quadruple."""
    rows, cols = spectrum.shape[:2]
    rest = spectrum.shape[2:]
    grouped = spectrum.reshape(2, rows // 2, 2, cols // 2, *rest)
    grouped = np.moveaxis(grouped, (0, 2), (2, 3))  # (rows/2, cols/2, s_y, s_x, …)
    return grouped.reshape(rows // 2 * (cols // 2), 4, *rest)


def conjugate_quadruples(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which quadruples hold the conjugates of which, for real images of `shape`.

    The DFT of a real image has ``X(−k) = conj X(k)``. The quadruple with base frequency
    (a, b) therefore holds the conjugates of base ((−a) mod rows/2, (−b) mod cols/2), its
    member s at member ``s ^ m``, where m flips s_y unless a = 0 and s_x unless b = 0.

    Returns
    -------
    kept : ndarray (H,) int
        Quadruples that are computed: one of each conjugate pair (and the self-conjugate).
    filled_rows, source_rows : ndarray int
        Rows ``4 q + s`` of the other quadruples, and the rows of the kept quadruples'
        compact (H · 4) array whose conjugates they are.
    """
    half_rows, half_cols = shape[0] // 2, shape[1] // 2
    a, b = np.divmod(np.arange(half_rows * half_cols), half_cols)
    partner = ((-a) % half_rows) * half_cols + (-b) % half_cols
    mask = np.where(a > 0, 2, 0) | np.where(b > 0, 1, 0)
    index = np.arange(a.size)
    kept = index[index <= partner]
    filled = index[index > partner]
    position = np.full(a.size, -1)
    position[kept] = np.arange(kept.size)
    members = np.arange(4)
    filled_rows = (4 * filled[:, None] + members).ravel()
    source_rows = (4 * position[partner[filled]][:, None] + (members ^ mask[filled, None])).ravel()
    return kept, filled_rows, source_rows


@functools.lru_cache(maxsize=16)
def _half_spectrum_maps(
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the kept quadruples' members sit in a real image's half spectrum (rfft2).

    Returns the kept quadruples (:func:`conjugate_quadruples`); for each of their members
    in order, its row of the (rows · (cols/2 + 1)) half spectrum and whether it is that
    row's conjugate; and for each row of the half spectrum, the member (a row of the kept
    quadruples' compact (H · 4) array) that holds it and whether as its conjugate. One
    gather each way per solve, on half the spectrum the full FFT would transform.
    """
    rows, cols = shape
    width = cols // 2 + 1
    kept, filled_rows, source_rows = conjugate_quadruples(shape)
    natural = to_quadruples(np.arange(rows * cols).reshape(rows, cols))
    members = natural[kept].ravel()
    # a frequency (k, l) right of the half spectrum is the conjugate of (−k, −l)
    row, col = np.divmod(members, cols)
    right = col >= width
    gather = np.where(right, (-row) % rows, row) * width + np.where(right, cols - col, col)
    holder = np.empty(rows * cols, dtype=np.int64)
    conjugated = np.zeros(rows * cols, dtype=bool)
    filled = natural.ravel()[filled_rows]
    holder[members] = np.arange(members.size)
    holder[filled] = source_rows
    conjugated[filled] = True
    row, col = np.divmod(np.arange(rows * width), width)
    half = holder[row * cols + col]
    half_conjugated = conjugated[row * cols + col]
    maps = (kept, gather, right, half, half_conjugated)
    for array in maps:
        array.flags.writeable = False
    return maps


class _BlockCache:
    """The inverted blocks (and impulse responses) of recent solvers, by their matrix.

    Without dispersion every patch of an image has the same matrix (same size, Bayer phase,
    colour matrix, priors and weights): the patches of one image then invert it once,
    not once per patch and penalty. The arrays are shared read-only; at most
    :data:`BLOCK_CACHE_SIZE` sets are kept, the least recently used dropped first.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self._entries: OrderedDict[tuple[Any, ...], tuple[np.ndarray, ...]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[Any, ...]) -> tuple[np.ndarray, ...] | None:
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
            return entry

    def put(self, key: tuple[Any, ...], *arrays: np.ndarray) -> None:
        for array in arrays:
            array.flags.writeable = False
        with self._lock:
            self._entries[key] = arrays
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


_BLOCKS = _BlockCache(BLOCK_CACHE_SIZE)


def _add_block_diagonal(dense: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """`dense` (H, 4n, 4n) with the 4 (n × n) `blocks` (H, 4, n, n) added on its diagonal,
    in place; returns `dense`."""
    nq, _, n, _ = blocks.shape
    view = dense.reshape(nq, 4, n, 4, n)
    for s in range(4):
        view[:, s, :, s, :] += blocks[:, s]
    return dense


def _woodbury_factors(mosaic: np.ndarray, local_inverse: np.ndarray) -> tuple[np.ndarray, ...]:
    """V = R⁻¹Uᴴ (H, 4n, 4) and W = V C⁻¹ with the capacitance C = I + U R⁻¹ Uᴴ (4 × 4), so
    that ``(UᴴU + R)⁻¹ = R⁻¹ − W Vᴴ`` per quadruple.

    ``mosaic`` is U, (H or 1, 4, 4n); ``local_inverse`` R⁻¹ of the block-diagonal R,
    (H, 4, n, n): the priors and β at the quadruple's 4 frequencies, the same for every
    patch of a size (:func:`_local_inverse`). Raises ``LinAlgError`` for a singular C.
    """
    nq, _, n, _ = local_inverse.shape
    u = np.broadcast_to(mosaic, (nq, 4, 4 * n))
    # V = R⁻¹ Uᴴ, (H, 4 members, n, 4 raw frequencies)
    v = np.matmul(local_inverse, np.conj(np.swapaxes(u.reshape(nq, 4, 4, n), 1, 3)).swapaxes(1, 2))
    v = v.reshape(nq, 4 * n, 4)
    return v, v @ np.linalg.inv(np.eye(4) + u @ v)


def _woodbury_inverse(mosaic: np.ndarray, local_inverse: np.ndarray) -> np.ndarray | None:
    """``(UᴴU + R)⁻¹`` per quadruple by the Woodbury identity (:func:`_woodbury_factors`),
    or None if it fails. A 4 × 4 capacitance replaces the 4n × 4n inverse (a third of its
    time). Where R is ill-conditioned (the mean at small β) the subtraction loses digits:
    :func:`_accurate_inverse` checks each block.
    """
    try:
        v, w = _woodbury_factors(mosaic, local_inverse)
    except np.linalg.LinAlgError:
        return None
    inverse = -(w @ np.conj(np.swapaxes(v, 1, 2))).astype(np.complex128, copy=False)
    return _add_block_diagonal(inverse, local_inverse)


def _relative_residuals(product: np.ndarray, probe: np.ndarray) -> np.ndarray:
    """Each block's ``‖K K⁻¹ p − p‖ / ‖p‖`` from the products K K⁻¹ p (·, 4n, 1) and the
    probe p, the same vector in every block ((1 or ·), 4n, 1)."""
    error = np.linalg.norm(product - probe, axis=(1, 2))
    return error / float(np.linalg.norm(probe[0]))


def _accurate_inverse(
    matrix: np.ndarray, inverse: np.ndarray | None, probe: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray]:
    """`inverse`, with the blocks it gets wrong (or all, if None) inverted directly.

    Returns the inverse (None if the matrix is singular) and each block's relative residual
    ``‖K K⁻¹ p − p‖ / ‖p‖`` on the probe p.
    """

    def residuals(k: np.ndarray, k_inverse: np.ndarray) -> np.ndarray:
        return _relative_residuals(k @ (k_inverse @ probe), probe)

    if inverse is None:  # every block directly
        inverse, result = np.empty_like(matrix), np.full(matrix.shape[0], math.inf)
    else:
        result = residuals(matrix, inverse)
    redo = np.flatnonzero(~(result <= WOODBURY_RESIDUAL))
    if redo.size:
        try:
            direct = np.linalg.inv(matrix[redo])
        except np.linalg.LinAlgError:
            return None, np.full(matrix.shape[0], math.inf)
        inverse[redo] = direct
        result[redo] = residuals(matrix[redo], direct)
    return inverse, result


class _FactoredInverse:
    """K⁻¹ = R⁻¹ − V C⁻¹ Vᴴ per quadruple, applied without forming it (a dispersive solver).

    K = UᴴU + R with U the (4 × 4n) mosaic rows and R block-diagonal (the priors and β at
    the quadruple's 4 frequencies); V = R⁻¹Uᴴ and C = I + UV (4 × 4). A solve then reads
    R⁻¹ (4 blocks of n × n) and two 4n × 4 factors instead of a dense 4n × 4n inverse:
    about half the products and a third of the memory traffic, and no inverse to form per
    patch. Blocks where the identity loses digits (:func:`_accurate_inverse`'s test on the
    same probe) are inverted directly and applied as such.
    """

    def __init__(
        self,
        mosaic: np.ndarray,
        local: np.ndarray,
        local_inverse: np.ndarray,
        probe: np.ndarray,
    ) -> None:
        nq, _, n, _ = local.shape
        self.n = n
        self.mosaic = np.broadcast_to(mosaic, (nq, 4, 4 * n))
        self.local, self.local_inverse = local, local_inverse
        v, self.w = _woodbury_factors(mosaic, local_inverse)
        self.vh = np.conj(np.swapaxes(v, 1, 2))
        self.redo = np.zeros(0, dtype=np.intp)
        self.direct = np.zeros((0, 4 * n, 4 * n), dtype=np.complex128)
        probes = np.broadcast_to(probe.astype(np.complex128), (nq, 4 * n, 1))
        self.residuals = _relative_residuals(self.multiply(self.solve(probes)), probe)
        redo = np.flatnonzero(~(self.residuals <= WOODBURY_RESIDUAL))
        if redo.size:
            matrix = self.dense_matrix(redo)
            self.direct = np.linalg.inv(matrix)
            self.redo = redo
            self.residuals[redo] = _relative_residuals(matrix @ (self.direct @ probe), probe)

    def solve(self, spectrum: np.ndarray) -> np.ndarray:
        """K⁻¹ s for the kept quadruples' spectra s (H, 4n, m)."""
        nq, size, m = spectrum.shape
        out = (self.local_inverse @ spectrum.reshape(nq, 4, self.n, m)).reshape(nq, size, m)
        out -= self.w @ (self.vh @ spectrum)
        if self.redo.size:
            out[self.redo] = self.direct @ spectrum[self.redo]
        return out

    def multiply(self, x: np.ndarray) -> np.ndarray:
        """K x for the kept quadruples' spectra x (H, 4n, m)."""
        nq, size, m = x.shape
        out = (self.local @ x.reshape(nq, 4, self.n, m)).reshape(nq, size, m)
        out += np.conj(np.swapaxes(self.mosaic, 1, 2)) @ (self.mosaic @ x)
        return out

    def dense_matrix(self, blocks: np.ndarray | slice = slice(None)) -> np.ndarray:
        """K's blocks (all, or those indexed by `blocks`) as dense (·, 4n, 4n) matrices."""
        u = self.mosaic[blocks]
        return _add_block_diagonal(np.conj(np.swapaxes(u, 1, 2)) @ u, self.local[blocks])

    def dense_inverse(self) -> np.ndarray:
        """K⁻¹ as dense (H, 4n, 4n) blocks (for single-precision solves and impulses)."""
        inverse = _add_block_diagonal(-(self.w @ self.vh), self.local_inverse)
        inverse[self.redo] = self.direct
        return inverse


_LOCAL = _BlockCache(4)
"""The priors' blocks R (and R⁻¹ per β) of recent patch sizes (:func:`_local_inverse`)."""


def _local_inverse(key: tuple[Any, ...], local: np.ndarray) -> np.ndarray | None:
    """R⁻¹ of the (H, 4, n, n) blocks `local`, shared by the solvers with the same `key`
    (patch size, priors and β; not the colour matrix, so the patches of an image with Φ
    share it); None if a block is singular."""
    cached = _LOCAL.get(key)
    if cached is not None:
        return cached[0]
    try:
        inverse = np.linalg.inv(local)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(inverse)):
        return None
    _LOCAL.put(key, inverse)
    return inverse


def _terms_digest(terms: Sequence[tuple[float, Term]]) -> str:
    """Hex digest of what the prior matrices of `terms` depend on."""
    digest = hashlib.blake2b()
    for coefficient, term in terms:
        if coefficient:
            digest.update(f"{float(coefficient)!r} {type(term).__name__} {term!r}".encode())
            extra = getattr(term, "colour", None)  # the smoothness term's colour matrix
            if extra is not None:
                digest.update(np.ascontiguousarray(extra, dtype=np.float64).tobytes())
    return digest.hexdigest()


def _matrix_key(
    shape: tuple[int, int],
    cfa: str,
    colour: np.ndarray,
    data_weight: float,
    terms_digest: str,
) -> tuple[Any, ...]:
    """What the matrix of a solver without dispersion depends on (identity aside);
    `terms_digest` is :func:`_terms_digest` of its prior terms."""
    colour_digest = hashlib.blake2b(np.ascontiguousarray(colour, dtype=np.float64).tobytes())
    return (
        shape,
        check_layout(cfa),
        colour.shape,
        float(data_weight),
        colour_digest.hexdigest(),
        terms_digest,
    )


class FourierSolver:
    """Solve ``(α AᵀA + Σ_t c_t D_tᵀD_t + β I) x = b`` exactly (periodic boundary).

    Parameters
    ----------
    shape : (rows, cols)
        Patch size, px; both even.
    cfa : str
        Bayer layout at the patch's top-left pixel.
    colour : ndarray
        (3, n) real colour matrix, or (rows, cols, 3, n) complex per-frequency matrices.
    data_weight : float
        α (2 for the objective ‖Ax − y‖²).
    terms : sequence of (coefficient, PriorTerm or SmoothnessTerm)
        c_t ≥ 0 and the term whose DᵀD enters.
    identity : float
        β ≥ 0 (ADMM penalty on x, and any ridge).

    Attributes
    ----------
    dispersive : bool
        Whether `colour` is per frequency (Φ by mean translations): K̃ then only
        approximates the matrix of the problem with the true Φ.

    Notes
    -----
    Memory: two sets of (rows·cols/4) complex (4n × 4n) matrices (the matrix and its
    inverse), e.g. 210 MB for 160 × 160 px and 8 bands; with dispersion about a third of
    that (the Woodbury factors, :class:`_FactoredInverse`), until a dense form is asked
    for (single-precision solves, impulse responses). Without dispersion (a real colour
    matrix) both are shared with every solver of the same matrix (:class:`_BlockCache`).
    The matrix must be positive definite: give β > 0 unless the data and priors already
    determine every component.
    """

    def __init__(
        self,
        shape: tuple[int, ...],
        cfa: str,
        colour: np.ndarray,
        *,
        data_weight: float = 2.0,
        terms: Sequence[tuple[float, Term]] = (),
        identity: float = 0.0,
    ) -> None:
        rows, cols = (int(v) for v in shape)
        if rows % 2 or cols % 2 or rows < 2 or cols < 2:
            raise DataError(
                f"the FFT solver needs an even patch size (the Bayer period is 2×2), got "
                f"{rows}×{cols}"
            )
        colour = np.asarray(colour)
        self.shape = (rows, cols)
        self.dispersive = colour.ndim != 2
        self.channels = n = colour.shape[-1]
        a = mask_coefficients(cfa)
        xor = np.array([[s ^ t for t in range(4)] for s in range(4)])
        a_xor = a[:, xor]  # (3, 4, 4)
        # a real image's spectrum is conjugate-symmetric, and so is K: only about half the
        # quadruples are solved, the rest are their conjugates (about half the time)
        self._kept, self._gather, self._gather_conj, self._half, self._half_conj = (
            _half_spectrum_maps(self.shape)
        )
        # the data term of a quadruple is U^H U with U (4 × 4n): its 4 raw frequencies from
        # its 4n latent ones, U[u, (t, j)] = √α Σ_c a[c, u ⊕ t] C_c(k_t)[j] (the channel
        # masks are disjoint, so the cross-channel products vanish)
        if colour.ndim == 2:
            mosaic = np.einsum("cut,cj->utj", a_xor, colour)[None]
        else:
            quads = to_quadruples(colour)[self._kept]  # (H, 4, 3, n)
            mosaic = np.einsum("cut,htcj->hutj", a_xor, quads, optimize=True)
        self._mosaic = math.sqrt(data_weight) * mosaic.reshape(mosaic.shape[0], 4, 4 * n)
        self._data: np.ndarray | None = None  # UᴴU (H or 1, 4n, 4n), once a dense K is needed
        self._factored: _FactoredInverse | None = None
        self._dense: tuple[np.ndarray, np.ndarray] | None = None  # (K, K⁻¹) of _factored
        for coefficient, _ in terms:
            if coefficient < 0:
                raise DataError(f"prior coefficient must be ≥ 0, got {coefficient}")
        terms_digest = _terms_digest(terms)
        self._prior_key = ("prior", self.shape, n, terms_digest)
        cached = _LOCAL.get(self._prior_key)
        if cached is None:
            prior = np.zeros((rows, cols, n, n))
            for coefficient, term in terms:
                if coefficient:
                    for symbol, matrix in term.fourier_pieces(self.shape, n):
                        prior += coefficient * symbol[..., None, None] * matrix
            cached = (to_quadruples(prior)[self._kept],)
            _LOCAL.put(self._prior_key, *cached)
        self._prior = cached[0]  # (H, 4, n, n), read-only
        self._key: tuple[Any, ...] | None = None
        if colour.ndim == 2:  # per-frequency colour (dispersion) makes every patch differ
            self._key = _matrix_key(self.shape, cfa, colour, data_weight, terms_digest)
        self.identity = math.nan  # none yet: set_identity inverts
        self._inverse32: np.ndarray | None = None  # made on the first solve_single
        self.set_identity(identity)

    def set_identity(self, identity: float) -> None:
        """Change β and re-invert (ADMM's penalty update)."""
        if identity == self.identity:
            return
        if identity < 0:
            raise DataError(f"identity coefficient must be ≥ 0, got {identity}")
        cached = None if self._key is None else _BLOCKS.get((*self._key, identity))
        if cached is not None:
            self._matrix, self._inverse, residual = cached
            self._inverse_residual = float(residual)
            self.identity = identity
            self._inverse32 = None
            return
        n = self.channels
        nq = self._prior.shape[0]
        local = self._prior + identity * np.eye(n)  # (H, 4, n, n): priors and β per member
        # a (numerically) singular block inverts to garbage without an error: check the
        # inverse on one random vector per block (O(n²) per block, the inversion is O(n³))
        probe = np.random.default_rng(0).standard_normal((1, 4 * n, 1))
        local_inverse = _local_inverse((*self._prior_key, float(identity)), local)
        self._factored = self._dense = None
        if self.dispersive and local_inverse is not None:
            # every patch has its own K̃: applied in factored form, never formed (a singular
            # capacitance or block falls through to the dense path, which reports it)
            try:
                factored = _FactoredInverse(self._mosaic, local, local_inverse, probe)
                worst = float(np.max(factored.residuals))
            except np.linalg.LinAlgError:
                worst = math.inf
            if worst <= SINGULAR_RESIDUAL:
                self._factored = factored
                self._matrix = self._inverse = None  # type: ignore[assignment]
                self._inverse_residual = worst
                self.identity = identity
                self._inverse32 = None
                return
        if self._data is None:
            self._data = np.conj(np.swapaxes(self._mosaic, 1, 2)) @ self._mosaic
        matrix = np.broadcast_to(self._data, (nq, 4 * n, 4 * n)).astype(np.complex128)
        self._matrix = _add_block_diagonal(matrix, local)
        inverse = None if local_inverse is None else _woodbury_inverse(self._mosaic, local_inverse)
        inverse, residuals = _accurate_inverse(self._matrix, inverse, probe)
        worst = float(np.max(residuals)) if inverse is not None else math.inf
        if inverse is None or not worst <= SINGULAR_RESIDUAL:
            raise DataError(
                "the quadratic step's matrix is singular: with identity coefficient "
                f"{identity:g}, the data and prior terms leave some frequency components "
                "undetermined (a Bayer mosaic observes 4 of the 4n per frequency quadruple); "
                "give identity > 0 (e.g. a ridge of 1e-9 × the data term's scale)"
            )
        self._inverse = inverse
        self._inverse_residual = worst
        self.identity = identity
        self._inverse32 = None
        if self._key is not None:
            _BLOCKS.put((*self._key, identity), self._matrix, self._inverse, np.array(worst))

    def _dense_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """K and K⁻¹ as dense (H, 4n, 4n) blocks (formed once from the factors if need be)."""
        if self._factored is None:
            return self._matrix, self._inverse
        if self._dense is None:
            self._dense = (self._factored.dense_matrix(), self._factored.dense_inverse())
        return self._dense

    @property
    def _refine(self) -> bool:
        """Whether solves take a step of iterative refinement (:data:`REFINE_RESIDUAL`)."""
        return self._inverse_residual > REFINE_RESIDUAL

    def _apply_quadruples(
        self, x: np.ndarray, inverse: bool, refine: bool = True, blocks: np.ndarray | None = None
    ) -> np.ndarray:
        """K x or K⁻¹ x through the per-quadruple blocks; `blocks` replaces K⁻¹'s (no
        refinement then), and x's precision carries through the FFTs."""
        n = self.channels
        spectrum = scipy.fft.rfft2(x, axes=(0, 1)).reshape(-1, n)[self._gather]
        np.conjugate(spectrum, out=spectrum, where=self._gather_conj[:, None])
        spectrum = spectrum.reshape(-1, 4 * n, 1)
        factored = self._factored
        if blocks is not None:
            out = blocks @ spectrum
        elif inverse and factored is not None:
            out = factored.solve(spectrum)
            if refine and self._refine:
                out += factored.solve(spectrum - factored.multiply(out))
        elif inverse:
            out = self._inverse @ spectrum
            if refine and self._refine:  # the ridge alone can leave cond ≈ 1e9
                out += self._inverse @ (spectrum - self._matrix @ out)
        elif factored is not None:
            out = factored.multiply(spectrum)
        else:
            out = self._matrix @ spectrum
        return self._to_image(out.reshape(-1, 4, n))

    def _to_image(self, kept: np.ndarray) -> np.ndarray:
        """Real image (rows, cols, …) from the kept quadruples' spectrum (H, 4, …)."""
        rest = kept.shape[2:]
        half = kept.reshape(-1, *rest)[self._half]
        where = self._half_conj.reshape(-1, *(1,) * len(rest))
        np.conjugate(half, out=half, where=where)
        rows, cols = self.shape
        half = half.reshape(rows, cols // 2 + 1, *rest)
        return scipy.fft.irfft2(half, s=self.shape, axes=(0, 1), overwrite_x=True)

    def impulse_responses(self, *, refine: bool = True) -> np.ndarray:
        """Columns of K⁻¹ at the 4n impulses of one Bayer period, (2, 2, n, rows, cols, n).

        ``g[p, q, j]`` is K⁻¹ applied to a unit impulse at pixel (p, q), band j. K is
        periodic with the 2×2 mosaic period, so the column of any impulse at (r, c) is
        ``g[r % 2, c % 2, j]`` rolled by (r − r % 2, c − c % 2). (A read-only view of one
        array, shared by the solvers of the same matrix without dispersion.)
        Refined as :meth:`solve` refines; ``refine=False`` never, for a preconditioner built
        from ``solve(…, refine=False)``.
        """
        refine = refine and self._refine
        tag = "impulses" if refine else "impulses, unrefined"
        key = None if self._key is None else (*self._key, self.identity, tag)
        cached = None if key is None else _BLOCKS.get(key)
        if cached is not None:
            return cached[0]
        rows, cols = self.shape
        n = self.channels
        # the impulses' spectra are known: exp(−2πi (k p / rows + l q / cols)) in band j
        k = np.arange(rows)[:, None, None]
        m = np.arange(cols)[None, :, None]
        p, q = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])  # impulse pixel 2p + q
        phase = np.exp(-2j * np.pi * (k * p / rows + m * q / cols))  # (rows, cols, 4)
        phase = to_quadruples(phase)[self._kept]  # (H, 4 members, 4 impulse pixels)
        matrix, dense_inverse = self._dense_blocks()
        inverse = dense_inverse.reshape(-1, 4, n, 4, n)
        out = np.einsum("hsitj,htp->hsipj", inverse, phase, optimize=True)
        out = out.reshape(-1, 4 * n, 4 * n)
        if refine:  # one step of iterative refinement against the impulses' spectra phase ⊗ I
            spectrum = np.einsum("htp,ij->htipj", phase, np.eye(n)).reshape(-1, 4 * n, 4 * n)
            out += dense_inverse @ (spectrum - matrix @ out)
        columns = self._to_image(out.reshape(-1, 4, n, 4 * n))  # (rows, cols, n, 4n)
        impulses = np.moveaxis(columns.reshape(rows, cols, n, 2, 2, n), (3, 4, 5), (0, 1, 2))
        if key is not None:
            _BLOCKS.put(key, impulses)
        return impulses

    def solve(self, b: np.ndarray, *, refine: bool = True) -> np.ndarray:
        """x with K x = b; `b` and x are (rows, cols, n) real.

        A step of iterative refinement follows where the inverse is not accurate to
        :data:`REFINE_RESIDUAL`; ``refine=False`` skips it always (a third of the cost),
        for use as a preconditioner, where the solve is approximate anyway.
        """
        return self._apply_quadruples(np.asarray(b, dtype=np.float64), inverse=True, refine=refine)

    def solve_single(self, b: np.ndarray) -> np.ndarray:
        """x with K x ≈ b in single precision (float64 result), for preconditioning.

        FFTs and the block products in float32/complex64: relative error from 1e-7 up to
        ≈ 3e-5 as the blocks' condition grows, at about half the time of
        ``solve(b, refine=False)``. The ADMM step's CG (to 1e-5) uses it; the active-set
        finish, which needs CG to 1e-7, keeps float64.
        """
        if self._inverse32 is None:
            self._inverse32 = self._dense_blocks()[1].astype(np.complex64)
        single = self._apply_quadruples(
            np.asarray(b, dtype=np.float32), inverse=True, blocks=self._inverse32
        )
        return single.astype(np.float64)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """K x computed in the Fourier domain (for checks)."""
        return self._apply_quadruples(np.asarray(x, dtype=np.float64), inverse=False)
