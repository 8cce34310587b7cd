"""The image formation operator A = M·Ω·Φ·B of problem (3.1), and its direct-colour form (3.27).

:class:`LatentSpace` says what the unknown image holds and how it becomes raw colour:

* ``kind="spectral"`` — coefficients of the spectral basis B at band centres (3.1). Ω
  integrates the spectrum ``B(I)`` against the camera response on the response's own
  (fine) wavelength grid by the trapezoid rule (3.6), extrapolating B as the thesis does.
* ``kind="colour"`` — the raw colour channels R, G, B themselves (3.27).

A response tabulated only at the band centres — a sensor map (thesis Algorithm 12: each
band's R/G and B/G, Green = 1) — is a discrete model and gets ``kernel="discrete"``: the
latent image holds the band images themselves, their colours are the tabulated values
(no integral; bands do not overlap), and each band is warped by the dispersion at its own
centre. This is the image formation of the thesis' synthetic raw images (Algorithm 13).
Interpolating such a table as a continuous response would mix the ratios of neighbouring
bands, which can differ widely (R/G at 550 and 600 nm on the thesis' real frames; figures
in docs/notes/real-frames.md, "The sensor map as a camera response").

Either may carry a per-channel scale ``r`` (thesis §6.3, (6.1)): the unknown is then
``J = I / r`` and the priors act on J, which equalises how strongly bright and dark bands
are smoothed.

Dispersion is sampled at a few wavelengths λ_j (thesis §3.2.5; see
:func:`~reconstruction.model.operators.dispersion_samples`) and interpolated linearly in λ between
them: the band operator at a response wavelength f is ``Σ_j h_j(f) Φ_j`` with hat
functions h_j (constant beyond the ends). The colour integral therefore splits into one
(3 × n) matrix per sample, ``C_j = Σ_f Ω(f) h_j(f) B(f, ·)``, with ``Σ_j C_j`` equal to the
dispersion-free colour matrix, and

    raw = M Σ_j Φ_j (I C_jᵀ).

Compared with the thesis, which integrates the spectrum over the Φ samples themselves,
this keeps the colour integral as accurate as the response's sampling whatever the number
of Φ samples, and makes a patch whose Φ is dropped see exactly the same colours. M and all
Φ_j and the C_j are folded into one sparse matrix over the latent image (its few distinct
source pixels per raw pixel, times n).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import scipy.fft
import scipy.sparse as sp

from calibration.dispersion_model import DispersionModel
from labkit.cfa import CHANNELS
from labkit.errors import DataError
from labkit.spectra import Spectra, hat_weights, trapezoid_weights
from reconstruction.model.operators import (
    Dispersion,
    LinearOperator,
    Mosaic,
    SpectralBasis,
    dispersion_samples,
)
from reconstruction.model.operators.basis import choose_bands, sensitive_range
from reconstruction.model.operators.dispersion import keys_kernel

DISCRETE = "discrete"
"""Kernel of a spectral space whose response is a sensor map sampled at the band centres."""


@dataclass(frozen=True, eq=False)
class LatentSpace:
    """What the latent image holds, and its map to raw colour.

    Attributes
    ----------
    kind : {"spectral", "colour"}
    centres_nm : ndarray (n,) or None
        Band centres of a spectral latent image, nm.
    response : Spectra or None
        Camera response R, G, B (spectral kind).
    kernel : {"gaussian", "sinc", "discrete"}
        Kernel of the spectral basis B; ``"discrete"`` for a sensor map (see the module
        docstring).
    scale : ndarray (n,)
        Per-channel scale r of the §6.3 variant (ones for the plain problem).
    support_nm : (float, float) or None
        Where the camera is sensitive (≥ 5 % of a channel's peak), nm: the range over
        which dispersion is sampled.
    band_light_nm : ndarray (n,) or None
        Discrete spaces: the wavelength of the light each band holds, where its dispersion
        is evaluated — its centre, unless the bands are filters whose effective
        wavelengths a dispersion model recorded (:meth:`with_band_light`). None: the
        centres.
    """

    kind: Literal["spectral", "colour"]
    centres_nm: np.ndarray | None = None
    response: Spectra | None = None
    kernel: str = "gaussian"
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))
    support_nm: tuple[float, float] | None = None
    band_light_nm: np.ndarray | None = None

    @classmethod
    def spectral(
        cls, response: Spectra, centres_nm: np.ndarray | None = None, *, kernel: str = "gaussian"
    ) -> LatentSpace:
        """Spectral latent space: bands from :func:`choose_bands` unless `centres_nm` given.

        With `centres_nm`, the response needs no bandlimit. A response sampled at exactly
        the band centres (a sensor map) makes the space discrete, whatever `kernel` says.
        """
        response = _rgb(response)
        if centres_nm is not None and _samples_centres(response, centres_nm):
            centres = np.asarray(centres_nm, dtype=float)
            support = (float(centres[0]), float(centres[-1]))
            return cls("spectral", centres, response, DISCRETE, np.ones(centres.size), support)
        if centres_nm is None:
            selection = choose_bands(response)
            centres, sensitive = selection.centres_nm, selection.support_nm
        else:
            centres, sensitive = np.asarray(centres_nm, float), sensitive_range(response)
        if centres.ndim != 1 or centres.size < 2:
            raise DataError(f"need ≥ 2 band centres (nm), got {centres!r}")
        lo, hi = response.domain
        if centres[0] < lo or centres[-1] > hi:
            raise DataError(
                f"the bands {centres[0]:g}–{centres[-1]:g} nm are not covered by the camera "
                f"response ({lo:g}–{hi:g} nm); choose bands inside the response or supply a "
                "response measured over them"
            )
        SpectralBasis((1, 1), centres, centres, kernel=kernel)  # validates spacing etc.
        support = (min(sensitive[0], centres[0]), max(sensitive[1], centres[-1]))
        return cls("spectral", centres, response, kernel, np.ones(centres.size), support)

    @classmethod
    def colour(cls) -> LatentSpace:
        """Direct colour estimation (3.27): the latent image is raw R, G, B."""
        return cls("colour")

    @property
    def channels(self) -> int:
        return 3 if self.kind == "colour" else int(self.centres_nm.size)

    def with_scale(self, scale: np.ndarray) -> LatentSpace:
        """The same space with per-channel scale r (§6.3): unknown J = I / r."""
        scale = np.asarray(scale, dtype=np.float64)
        if scale.shape != (self.channels,) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
            raise DataError(f"scale must be {self.channels} positive finite values, got {scale!r}")
        return replace(self, scale=scale)

    @property
    def phi_nm(self) -> np.ndarray | None:
        """Wavelengths at which each band's dispersion is evaluated, nm (discrete spaces:
        :attr:`band_light_nm` or the centres; spectral: the centres; colour: None)."""
        if self.band_light_nm is not None:
            return self.band_light_nm
        return self.centres_nm

    def with_band_light(self, light_nm: np.ndarray) -> LatentSpace:
        """The same discrete space with its bands' light at `light_nm` (n,), nm."""
        if self.kernel != DISCRETE:
            raise DataError("only a discrete (sensor-map) space has bands of filtered light")
        light = np.asarray(light_nm, dtype=np.float64)
        if light.shape != self.centres_nm.shape or not np.all(np.isfinite(light)):
            raise DataError(f"need {self.centres_nm.size} finite wavelengths, got {light!r}")
        support = (float(light.min()), float(light.max()))
        return replace(self, band_light_nm=light, support_nm=support)

    def colour_matrix(self) -> np.ndarray:
        """Ω·B (3 × n): latent image → raw colour without dispersion (scale included)."""
        return self.colour_matrices(None)[0]

    def colour_matrices(self, samples_nm: np.ndarray | None) -> np.ndarray:
        """Per-sample colour matrices C_j (J, 3, n); J = 1 without dispersion samples."""
        if self.kind == "colour":
            if samples_nm is not None:
                raise DataError("direct colour estimation has no wavelength samples")
            return (np.eye(3) * self.scale[None, :])[None]
        if self.kernel == DISCRETE:
            matrix = self.response.values.T * self.scale[None, :]  # (3, n)
            if samples_nm is None:
                return matrix[None]
            if not np.array_equal(np.asarray(samples_nm, dtype=float), self.centres_nm):
                raise DataError("a discrete (sensor-map) space samples Φ at its band centres")
            return np.einsum("cn,jn->jcn", matrix, np.eye(self.centres_nm.size))
        fine = self.response.wavelengths
        weights = self.response.values * trapezoid_weights(fine)[:, None]  # (f, 3)
        basis = SpectralBasis((1, 1), self.centres_nm, fine, kernel=self.kernel).matrix  # (f, n)
        basis = basis * self.scale[None, :]
        if samples_nm is None:
            return (weights.T @ basis)[None]
        hats = hat_weights(fine, samples_nm)  # (J, f)
        return np.einsum("fc,jf,fn->jcn", weights, hats, basis)

    def spectral_values(self, latent: np.ndarray) -> np.ndarray:
        """The spectrum at the band centres, ``B(r ⊙ J)`` at ``centres_nm`` (…, n)."""
        if self.kind == "colour" or self.kernel == DISCRETE:
            return latent * self.scale
        at_centres = SpectralBasis((1, 1), self.centres_nm, self.centres_nm, kernel=self.kernel)
        return latent @ (at_centres.matrix * self.scale[None, :]).T  # one image-sized array

    def raw_colour(self, latent: np.ndarray) -> np.ndarray:
        """The latent image in raw colour (…, 3), without dispersion."""
        return latent @ self.colour_matrix().T


def _samples_centres(response: Spectra, centres_nm) -> bool:
    """Is the response tabulated at exactly the band centres (a sensor map)?"""
    centres = np.asarray(centres_nm, dtype=float)
    wavelengths = np.asarray(response.wavelengths, dtype=float)
    return wavelengths.shape == centres.shape and np.allclose(wavelengths, centres, atol=1e-6)


def _rgb(response: Spectra) -> Spectra:
    if set(CHANNELS) <= set(response.labels):
        return response.select(list(CHANNELS))
    if response.values.shape[1] != 3:
        raise DataError(
            "camera response needs channels R, G, B (or exactly three); got "
            f"{list(response.labels)}"
        )
    return response


class ImageFormation(LinearOperator):
    """A: latent image (rows, cols, n) → raw mosaic (rows, cols).

    Parameters
    ----------
    shape : (rows, cols)
        Patch size, px.
    cfa : str
        Bayer layout of the patch's top-left pixel.
    colour_matrices : ndarray (J, 3, n)
        Per-dispersion-sample colour matrices C_j (J = 1 without dispersion).
    dispersion : Dispersion, optional
        Φ sampled at J wavelengths (or on the 3 colour channels); None for no dispersion.

    Attributes
    ----------
    mosaic : Mosaic
        M of the patch.
    """

    name = "A"

    def __init__(
        self,
        shape: tuple[int, int],
        cfa: str,
        colour_matrices: np.ndarray,
        dispersion: Dispersion | None = None,
    ) -> None:
        rows, cols = (int(n) for n in shape)
        colour_matrices = np.asarray(colour_matrices, dtype=np.float64)
        if colour_matrices.ndim != 3 or colour_matrices.shape[1] != 3:
            raise DataError(f"colour matrices must be (J, 3, n), got {colour_matrices.shape}")
        n = colour_matrices.shape[2]
        super().__init__((rows, cols, n), (rows, cols))
        self.mosaic = Mosaic((rows, cols), cfa)
        self.cfa = self.mosaic.cfa
        self.channel_index = self.mosaic.index
        self.colour_matrices = colour_matrices
        self.dispersion = dispersion
        self._matrix = self._matrix_t = None
        if dispersion is not None:
            if dispersion.patch_shape != (rows, cols):
                raise DataError("Φ's patch shape differs from the image formation's")
            if len(dispersion.taps.offsets_y) != colour_matrices.shape[0]:
                raise DataError(
                    f"{len(dispersion.taps.offsets_y)} dispersion samples but "
                    f"{colour_matrices.shape[0]} colour matrices"
                )
            self._matrix = self._combined(dispersion)
            self._matrix_t = self._matrix.T.tocsr()
        elif colour_matrices.shape[0] != 1:
            raise DataError("without dispersion there must be exactly one colour matrix")

    @property
    def mean_shifts_px(self) -> np.ndarray | None:
        """Mean displacement (J, 2) of each Φ sample over the patch (the FFT preconditioner's)."""
        return None if self.dispersion is None else self.dispersion.mean_displacement_px

    @property
    def colour_matrix(self) -> np.ndarray:
        """Σ_j C_j (3 × n): the colour matrix of the same patch without dispersion."""
        return self.colour_matrices.sum(axis=0)

    def without_dispersion(self) -> ImageFormation:
        """The same A with Φ = identity."""
        return ImageFormation(self.domain_shape[:2], self.cfa, self.colour_matrix[None])

    def _combined(self, dispersion: Dispersion) -> sp.csr_matrix:
        """``M Σ_j Φ_j (· C_jᵀ)`` as one (rows·cols) × (rows·cols·n) matrix on the latent image.

        Consecutive samples' stencils overlap almost entirely (they are ≤ 0.1 px apart), so
        folding the colour matrices in leaves only the few distinct source pixels of each
        raw pixel times n bands: far fewer products than mixing every sample's colour image
        and then interpolating it. The fold reads Φ's taps per axis
        (:class:`~reconstruction.model.operators.dispersion.AxisTaps`), finds
        the distinct (raw pixel, source pixel) pairs with a table over each raw pixel's
        window of source offsets, and sums each pair's weights times its channel's colours
        over the samples in order.
        """
        bands = _own_bands(self.colour_matrices)
        if bands is not None:
            return self._combined_per_band(dispersion, bands)
        rows, cols = self.domain_shape[:2]
        npx, n = rows * cols, self.domain_shape[2]
        taps = dispersion.taps
        samples, width, _ = taps.offsets_y.shape
        reach = int(max(np.abs(taps.offsets_y).max(), np.abs(taps.offsets_x).max()))
        window = 2 * reach + 1
        wraps = taps.boundary == "periodic" and (window > rows or window > cols)
        if wraps or window * window > 16 * samples * width * width:
            # a window larger than the patch would key one source by two offsets, and a
            # far-reaching one would make the table larger than the pairs
            return self._combined_by_sort(dispersion)
        # each (raw pixel, source pixel) pair is keyed by the raw pixel and the source's
        # offset in the window; the entries are taken in (sample, tap, channel, pixel)
        # order, so that the gather below has one row per (sample, tap, channel) in order
        channel = self.channel_index.ravel()
        order = np.argsort(channel, kind="stable")
        entries = samples * width * width * npx
        small = max(npx * window * window, entries) < np.iinfo(np.int32).max
        index = np.int32 if small else np.int64
        offsets_y = np.take(taps.offsets_y, order, axis=2).astype(index, copy=False)
        offsets_x = np.take(taps.offsets_x, order, axis=2).astype(index, copy=False)
        base = ((order * window + reach) * window + reach).astype(index)
        keys = ((offsets_y * window + base)[:, :, None, :] + offsets_x[:, None, :, :]).ravel()
        seen = np.zeros(npx * window * window, dtype=bool)
        seen[keys] = True
        which = (np.cumsum(seen, dtype=index) - 1)[keys]
        distinct = np.flatnonzero(seen)
        del seen, keys
        weights_y = np.take(taps.weights_y, order, axis=2)
        weights_x = np.take(taps.weights_x, order, axis=2)
        weights = weights_y[:, :, None, :] * weights_x[:, None, :, :]
        # per distinct pair: Σ_j w_j C_j[channel, :], the sum running over the samples in
        # order (as a product by a matrix sorted by pair would add them)
        per_row = np.tile(np.bincount(channel, minlength=3), samples * width * width)
        indptr = np.concatenate([[0], np.cumsum(per_row)]).astype(index)
        gather = sp.csr_matrix(
            (weights.ravel(), which, indptr), shape=(per_row.size, distinct.size)
        )
        colour = np.repeat(self.colour_matrices[:, None], width * width, axis=1)
        values = gather.T @ colour.reshape(-1, n)
        raw, offset = np.divmod(distinct, window * window)
        dy, dx = np.divmod(offset, window)
        sources = ((raw // cols + dy - reach) % rows) * cols + (raw % cols + dx - reach) % cols
        if np.any((raw[1:] == raw[:-1]) & (sources[1:] <= sources[:-1])):
            # wrapped sources, out of order within their row: a stable sort of nearly
            # sorted pairs, in about linear time
            resort = np.argsort(raw * npx + sources, kind="stable")
            raw, sources, values = raw[resort], sources[resort], values[resort]
        return self._assemble(raw, sources, values)

    def _combined_by_sort(self, dispersion: Dispersion) -> sp.csr_matrix:
        """:meth:`_combined` by a sort of every (raw pixel, source pixel) pair (stencils
        that reach across the whole patch, where a table of offsets does not serve)."""
        npx = int(np.prod(self.domain_shape[:2]))
        n = self.domain_shape[2]
        stencils = dispersion.stencils
        taps = stencils[0][0].shape[1]
        rows_all = np.tile(np.repeat(np.arange(npx, dtype=np.int64), taps), len(stencils))
        cols_all = np.concatenate([indices.ravel() for indices, _ in stencils])
        weights = np.concatenate([w.ravel() for _, w in stencils])
        channel = np.repeat(self.channel_index.ravel(), taps)
        columns = np.concatenate([3 * j + channel for j in range(len(stencils))])
        pairs, which = np.unique(rows_all * npx + cols_all, return_inverse=True)
        gather = sp.csr_matrix((weights, (which, columns)), shape=(pairs.size, 3 * len(stencils)))
        values = gather @ self.colour_matrices.reshape(-1, n)
        raw, sources = np.divmod(pairs, npx)
        return self._assemble(raw, sources, values)

    def _assemble(self, raw: np.ndarray, sources: np.ndarray, values: np.ndarray) -> sp.csr_matrix:
        """A from its distinct (raw pixel, source pixel) pairs, in order, and their (pairs, n)
        values over the bands."""
        npx = int(np.prod(self.domain_shape[:2]))
        n = self.domain_shape[2]
        per_row = np.bincount(raw, minlength=npx) * n
        indptr = np.concatenate([[0], np.cumsum(per_row)])
        indices = (sources[:, None] * n + np.arange(n)).ravel()
        matrix = sp.csr_matrix((values.ravel(), indices, indptr), shape=(npx, npx * n))
        # colour matrices with zero entries (samples that see some bands only, where the
        # per-band route does not apply) and taps at whole-pixel positions leave stored
        # zeros that every product would read
        matrix.eliminate_zeros()
        return matrix

    def _combined_per_band(self, dispersion: Dispersion, bands: np.ndarray) -> sp.csr_matrix:
        """:meth:`_combined` where sample j sees band ``bands[j]`` alone (a band-centre
        response): no two samples share a column, so nothing is added up and each raw
        pixel's row is its samples' stencils side by side, read straight from Φ's taps.

        The row is in the order (row tap, sample, column tap), not the columns' (a product
        does not need sorted columns); a source that two taps of one stencil
        reach (a patch narrower than the stencil) stays two entries, which a product adds.
        """
        rows, cols = self.domain_shape[:2]
        npx, n = rows * cols, self.domain_shape[2]
        taps = dispersion.taps
        samples, width, _ = taps.offsets_y.shape
        pixel_rows, pixel_cols = np.divmod(np.arange(npx), cols)
        channel = self.channel_index.ravel()
        colour = self.colour_matrices[np.arange(samples), :, bands][:, channel]  # (J, px)
        entries = samples * width * width
        index = np.int32 if npx * n < np.iinfo(np.int32).max else np.int64
        # each row in the order (row tap, sample, column tap): its sources then run nearly
        # in order, as a product reads the latent image best
        source_rows = ((pixel_rows + taps.offsets_y) % rows * (cols * n)).astype(index)
        source_cols = ((pixel_cols + taps.offsets_x) % cols * n + bands[:, None, None]).astype(
            index
        )  # both (J, taps, px), in units of the latent image's flat index
        shape = (npx, width, samples, width)  # written in this order (ravel copies nothing)
        columns = np.add(
            source_rows.transpose(2, 1, 0)[:, :, :, None],
            source_cols.transpose(2, 0, 1)[:, None],
            out=np.empty(shape, dtype=index),
        )
        row_weights = (taps.weights_y * colour[:, None, :]).transpose(2, 1, 0)
        values = np.multiply(
            row_weights[:, :, :, None],
            taps.weights_x.transpose(2, 0, 1)[:, None],
            out=np.empty(shape),
        )
        indptr = np.arange(0, npx * entries + 1, entries, dtype=index)
        matrix = sp.csr_matrix((values.ravel(), columns.ravel(), indptr), shape=(npx, npx * n))
        matrix.eliminate_zeros()  # integer sample points need one weight, not all
        return matrix

    def _forward(self, x: np.ndarray) -> np.ndarray:
        x = x.astype(np.float64, copy=False)
        if self._matrix is None:
            return self.mosaic.forward(x @ self.colour_matrices[0].T)
        return (self._matrix @ x.ravel()).reshape(self.range_shape)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        y = y.astype(np.float64, copy=False)
        if self._matrix is None:
            return self.mosaic.adjoint(y) @ self.colour_matrices[0]
        return (self._matrix_t @ y.ravel()).reshape(self.domain_shape)

    def fourier_colour(self) -> np.ndarray:
        """Colour matrix per spatial frequency for the FFT solver.

        Without Φ: the constant (3, n) matrix. With Φ: (rows, cols, 3, n) complex,
        ``Σ_j φ_j(k) C_j`` where φ_j is the DFT symbol of a translation by sample j's mean
        displacement, interpolated as Φ interpolates (bilinear or cubic) — exact when Φ_j
        is that translation (with wrap-around).
        """
        if self.mean_shifts_px is None:
            return self.colour_matrices[0]
        rows, cols = self.range_shape
        symbols = np.stack(
            [
                _translation_symbol(dx, dy, rows, cols, self.dispersion.interpolation)
                for dx, dy in self.mean_shifts_px
            ]
        )  # (J, rows, cols)
        return np.einsum("jyx,jcn->yxcn", symbols, self.colour_matrices, optimize=True)

    def translation_forward(self, x: np.ndarray) -> np.ndarray:
        """Ãx: A with each Φ sample replaced by its mean translation (periodic), by FFT.

        The operator whose normal matrix the FFT solver inverts with :meth:`fourier_colour`;
        without Φ it is A itself.
        """
        if self.dispersion is None:
            return self.forward(x)
        spectrum = scipy.fft.fft2(x, axes=(0, 1))
        colour = np.einsum("yxcn,yxn->yxc", self.fourier_colour(), spectrum, optimize=True)
        return self.mosaic.forward(scipy.fft.ifft2(colour, axes=(0, 1)).real)

    def translation_adjoint(self, y: np.ndarray) -> np.ndarray:
        """Ãᵀy, the adjoint of :meth:`translation_forward`."""
        if self.dispersion is None:
            return self.adjoint(y)
        spectrum = scipy.fft.fft2(self.mosaic.adjoint(y), axes=(0, 1))
        latent = np.einsum("yxcn,yxc->yxn", self.fourier_colour().conj(), spectrum, optimize=True)
        return scipy.fft.ifft2(latent, axes=(0, 1)).real


def _translation_symbol(
    dx: float, dy: float, rows: int, cols: int, interpolation: str
) -> np.ndarray:
    """DFT multiplier of ``out(q) = x sampled at q + (dx, dy)`` (periodic) with the weights
    of `interpolation` (bilinear, or Keys' cubic convolution), as Φ samples."""

    def axis(shift: float, n: int) -> np.ndarray:
        whole = np.floor(shift)
        frac = shift - whole
        if interpolation == "cubic":
            offsets = np.arange(-1.0, 3.0)
            weights = keys_kernel(frac - offsets)
        else:
            offsets, weights = np.array([0.0, 1.0]), np.array([1.0 - frac, frac])
        phase = np.exp(2j * np.pi * np.arange(n) / n)
        return sum(w * phase ** (whole + o) for o, w in zip(offsets, weights, strict=True))

    return axis(dy, rows)[:, None] * axis(dx, cols)[None, :]


def _own_bands(colour_matrices: np.ndarray) -> np.ndarray | None:
    """The one band each sample's colour matrix (J, 3, n) sees, when every sample sees
    exactly one and no two the same band; else None."""
    seen = np.any(colour_matrices != 0, axis=1)  # (J, n)
    if not np.all(seen.sum(axis=1) == 1) or np.any(seen.sum(axis=0) > 1):
        return None
    return np.argmax(seen, axis=1)


def build_formation(
    latent: LatentSpace,
    shape: tuple[int, int],
    cfa: str,
    *,
    model: DispersionModel | None = None,
    origin: tuple[int, int] = (0, 0),
    overhang_px: int = 0,
    step_px: float = 0.1,
    colour_gain: float = 1.0,
    interpolation: str | None = None,
) -> ImageFormation:
    """A for one patch: colour matrices of `latent`, and Φ from `model` if given.

    Parameters
    ----------
    latent : LatentSpace
    shape : (rows, cols)
        Patch size, px.
    cfa : str
        Bayer layout at the patch's top-left pixel.
    model : DispersionModel, optional
        A ``to_reference`` model: spectral (``xylambda``) for a spectral latent space,
        colour-channel (``xy``, reference G) for a colour one.
    origin : (row0, col0)
        Full-image pixel of the patch's top-left pixel, px.
    overhang_px : int
        How far a padded patch may reach beyond the model's image, px.
    step_px : float
        Largest shift between consecutive dispersion samples, px (§3.2.5: 0.1).
    colour_gain : float
        Factor on every colour matrix (the driver's normalisation, 1 / q_max).
    interpolation : {"bilinear", "cubic"}
        Sampling weights of Φ (:class:`~reconstruction.model.operators.Dispersion`); required
        with a `model` (this layer has no default of its own: the options resolve it).
    """
    if model is None:
        return ImageFormation(shape, cfa, colour_gain * latent.colour_matrices(None))
    if interpolation is None:
        raise DataError(
            "build_formation with a dispersion model needs interpolation= ('cubic' or "
            "'bilinear'; ReconstructOptions resolves it)"
        )
    if latent.kind == "colour":
        if model.variables != "xy":
            raise DataError(
                "direct colour estimation needs a colour-channel dispersion model "
                "(`labkit calibrate dispersion --reference G`), not a spectral one"
            )
        phi = Dispersion(
            model,
            None,
            origin=origin,
            shape=shape,
            overhang_px=overhang_px,
            boundary="periodic",
            interpolation=interpolation,
        )
        selectors = np.zeros((3, 3, 3))
        for c in range(3):
            selectors[c, c, c] = colour_gain * latent.scale[c]
        return ImageFormation(shape, cfa, selectors, phi)
    if model.variables != "xylambda":
        raise DataError(
            "spectral reconstruction needs a spectral (xylambda) dispersion model; a "
            "colour-channel model suits direct colour estimation (--latent colour)"
        )
    if latent.kernel == DISCRETE:
        samples = latent.centres_nm
        phi_nm = latent.phi_nm
    else:
        samples = phi_nm = dispersion_samples(
            model,
            latent.support_nm,
            origin=origin,
            shape=shape,
            min_count=2,
            step_px=step_px,
            overhang_px=overhang_px,
        )
    phi = Dispersion(
        model,
        phi_nm,
        origin=origin,
        shape=shape,
        overhang_px=overhang_px,
        boundary="periodic",
        interpolation=interpolation,
    )
    return ImageFormation(shape, cfa, colour_gain * latent.colour_matrices(samples), phi)
