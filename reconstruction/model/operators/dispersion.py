"""The dispersion operator Φ of problem (3.1) and its spectral sampling (thesis §3.2.5).

Φ maps a latent image in the reference geometry (no lateral chromatic aberration) to the
aberrated image the camera sees, one band at a time. Output band k at pixel q (a position
in the band image) is the latent band k sampled by bilinear interpolation at
q + e(q, λ_k), where e is a ``to_reference`` dispersion model's displacement (thesis
§3.2.4, last paragraph: for image estimation, dispersion is expressed in coordinates of
the aberrated image). Each band's map is built once as its weights along each axis
(:class:`AxisTaps`: two source rows and two source columns per output pixel, bilinear):
the image formation folds every band's taps into its own sparse matrix, and Φ applied
alone builds a stencil and a sparse matrix per band when first used, so each iteration of
the solver costs sparse products instead of evaluations of the dispersion model.

Bilinear interpolation is a low-pass filter as well as a shift: at a half-pixel shift it
halves the contrast of a pattern 4 px in period and cancels Nyquist. The camera's bands are
pure shifts of the (pixel-integrated) scene, so with bilinear weights the solver must
over-sharpen the latent image to explain sharp edges, and overshoots next to them.
``interpolation="cubic"`` uses Keys' cubic convolution (a = −½, sixteen weights per output
pixel), which is exact for quadratics and far closer to a pure shift; it costs about four
times the sparse products.

:func:`dispersion_samples` picks the wavelengths at which to sample dispersion for a
patch so that consecutive sampled bands shift by about 0.1 px or less.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse as sp

from calibration.dispersion_model import DispersionModel
from labkit.errors import DataError
from reconstruction.model.operators._base import LinearOperator

#: Colour channels of problem (3.27)'s direct colour estimation, in array order.
COLOUR_CHANNELS = ("R", "G", "B")


class Dispersion(LinearOperator):
    """Φ: latent (reference-geometry) image → dispersed image, (rows, cols, n) → same.

    Parameters
    ----------
    model : DispersionModel
        A ``to_reference`` model: band-image position q (px) → displacement e (px) such
        that the feature imaged at q is at q + e in the reference image. Spectral models
        (``variables="xylambda"``) need `wavelengths_nm`; colour-channel models
        (``variables="xy"``, reference ``"G"``) take ``wavelengths_nm=None`` and act on
        three channels R, G, B, the reference channel being left unshifted.
    wavelengths_nm : ndarray (n,) or None
        Wavelength of each band of the operator's input and output, nm.
    origin : (row0, col0)
        Full-image pixel of the patch's first pixel, px. Model coordinates are
        full-image pixels (x = column, y = row, pixel centres at integers).
    shape : (rows, cols), optional
        Patch size, px; default: from `origin` to the end of the model's image.
    overhang_px : int, optional
        How far the patch may reach beyond the model's image on each side, px (the
        model is extrapolated there); the patch-wise driver pads the image by this much.
    boundary : {"clamp", "periodic"}
        Sample points beyond the patch: moved onto its border, or wrapped around.
    interpolation : {"bilinear", "cubic"}
        Sampling weights: bilinear (the thesis, 4 per pixel) or Keys' cubic convolution
        (16 per pixel; see the module notes).

    Attributes
    ----------
    taps : AxisTaps
        Every band's sampling weights one axis at a time (what the stencils are made of,
        and what the image formation folds).
    stencils : list of (ndarray, ndarray)
        Per band, the flat source pixels (int64) and weights (float64) of every output
        pixel, (rows·cols, 4) bilinear or (rows·cols, 16) cubic; clamped or wrapped sources
        may repeat within a row, and weights may be 0 (built from `taps` when first used).
    matrices : list of scipy.sparse.csr_matrix
        One (rows·cols) × (rows·cols) matrix per band, float64, acting on the band
        flattened in row-major order (the stencils', built when first used).
    max_shift_px : float
        Largest displacement length ‖e‖ over the patch's pixels and the bands, px; a
        value well below 0.1 px means Φ could be skipped.
    mean_displacement_px : ndarray (n, 2)
        Mean displacement (e_x, e_y) of each band over the patch, px: the translation
        that best approximates the band's Φ (the FFT preconditioner uses it).
    wavelengths_nm : ndarray (n,) or None
    channels : tuple of str or None
        ``("R", "G", "B")`` for a colour-channel model.
    origin, patch_shape : tuple of int

    Raises
    ------
    DataError
        The model is ``from_reference``; the patch is not inside the model's image; the
        wavelengths do not suit the model's kind; the model gives NaN or Inf.

    Notes
    -----
    Sample points q + e that fall outside the patch are clamped to its border (nearest
    edge value, "replicate" extension), so every output pixel is a convex combination of
    input pixels. Pixels near the patch border whose sample point leaves the patch are
    therefore approximations: give a patch a margin of at least :attr:`max_shift_px`
    (rounded up) beyond the region whose output is used. Outside the model's calibrated
    region the displacement follows the model's ``extrapolation`` (reconstruction clamps,
    :mod:`calibration.model_domain`).
    """

    name = "Φ"

    def __init__(
        self,
        model: DispersionModel,
        wavelengths_nm: np.ndarray | None,
        *,
        origin: tuple[int, int] = (0, 0),
        shape: tuple[int, int] | None = None,
        overhang_px: int = 0,
        boundary: str = "clamp",
        interpolation: str,
    ) -> None:
        if boundary not in ("clamp", "periodic"):
            raise DataError(f"unknown boundary {boundary!r}; use 'clamp' or 'periodic'")
        check_interpolation(interpolation)
        if model.direction != "to_reference":
            raise DataError(
                "the dispersion operator Φ needs a to_reference dispersion model (band "
                f"position → reference position); this one is {model.direction}: "
                "calibrate with `labkit calibrate dispersion --direction to_reference`"
            )
        row0, col0, rows, cols = _patch(model, origin, shape, overhang_px)
        if model.variables == "xylambda":
            if wavelengths_nm is None:
                raise DataError("a spectral dispersion model needs the bands' wavelengths_nm")
            waves = np.asarray(wavelengths_nm, dtype=np.float64)
            if waves.ndim != 1 or waves.size == 0 or not np.all(np.isfinite(waves)):
                raise DataError(
                    f"wavelengths_nm must be a non-empty 1-D array of finite values (nm), "
                    f"got shape {waves.shape}"
                )
            bands: list[dict[str, Any]] = [{"wavelength_nm": float(w)} for w in waves]
            self.wavelengths_nm: np.ndarray | None = waves
            self.channels: tuple[str, ...] | None = None
        else:
            if wavelengths_nm is not None:
                raise DataError(
                    "a colour-channel dispersion model acts on channels R, G, B: pass "
                    "wavelengths_nm=None"
                )
            known = {str(model.reference), *model.channels}
            missing = [c for c in COLOUR_CHANNELS if c not in known]
            if missing:
                raise DataError(
                    f"the colour-channel dispersion model has no field for channel(s) "
                    f"{', '.join(missing)} (reference {model.reference!r}, fields "
                    f"{', '.join(model.channels)})"
                )
            bands = [{"channel": c} for c in COLOUR_CHANNELS]
            self.wavelengths_nm = None
            self.channels = COLOUR_CHANNELS
        super().__init__((rows, cols, len(bands)), (rows, cols, len(bands)))
        self.model = model
        self.origin = (row0, col0)
        self.patch_shape = (rows, cols)
        self.interpolation = interpolation
        sampling = _SAMPLING[interpolation]

        yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
        if self.wavelengths_nm is not None:  # every band in one evaluation
            all_x, all_y = model.displacement_grid(xx + col0, yy + row0, self.wavelengths_nm)
            ex, ey = np.moveaxis(all_x, -1, 0), np.moveaxis(all_y, -1, 0)  # (J, rows, cols)
        else:
            fields = [model.displacement(xx + col0, yy + row0, **band) for band in bands]
            ex, ey = (np.stack(v) for v in zip(*fields, strict=True))
        finite = np.isfinite(ex).all(axis=(1, 2)) & np.isfinite(ey).all(axis=(1, 2))
        if not finite.all():
            band = bands[int(np.flatnonzero(~finite)[0])]
            raise DataError(f"the dispersion model gives NaN or Inf displacements at {band}")
        samples = len(bands)
        max_shift = float(np.sqrt(np.max(ex * ex + ey * ey)))
        means = np.column_stack([ex.mean(axis=(1, 2)), ey.mean(axis=(1, 2))])
        # every band's taps at once, (J, taps, rows·cols)
        offsets_y, weights_y = sampling((yy + ey).reshape(samples, -1), rows, boundary)
        offsets_x, weights_x = sampling((xx + ex).reshape(samples, -1), cols, boundary)
        # the taps' sources relative to their output pixel's row and column
        offsets_y -= yy.ravel().astype(np.int64)
        offsets_x -= xx.ravel().astype(np.int64)
        self.taps = AxisTaps(offsets_y, weights_y, offsets_x, weights_x, boundary)
        self.max_shift_px = max_shift
        self.mean_displacement_px = means

    @functools.cached_property
    def stencils(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per band, the source pixels and weights (rows·cols, taps²) (see the class)."""
        return [self._stencil(j) for j in range(len(self.taps.offsets_y))]

    @functools.cached_property
    def matrices(self) -> list[sp.csr_matrix]:
        """One CSR matrix per band (built from the taps when first asked for, one band's
        stencil at a time, so that the stencils are not kept beside the matrices)."""
        npx = int(np.prod(self.patch_shape))
        return [_sparse_rows(*self._stencil(j), npx) for j in range(len(self.taps.offsets_y))]

    def _stencil(self, band: int) -> tuple[np.ndarray, np.ndarray]:
        """Band `band`'s source pixels (int64) and weights, (rows·cols, taps²)."""
        rows, cols = self.patch_shape
        t = self.taps
        pixel_rows, pixel_cols = np.divmod(np.arange(rows * cols), cols)
        source_rows = ((pixel_rows + t.offsets_y[band]) % rows).T
        source_cols = ((pixel_cols + t.offsets_x[band]) % cols).T
        taps = source_rows.shape[1]
        indices = source_rows[:, :, None] * cols + source_cols[:, None, :]
        weights = t.weights_y[band].T[:, :, None] * t.weights_x[band].T[:, None, :]
        return indices.reshape(-1, taps * taps), weights.reshape(-1, taps * taps)

    def _forward(self, x: np.ndarray) -> np.ndarray:
        return self._apply(x, transpose=False)

    def _adjoint(self, y: np.ndarray) -> np.ndarray:
        return self._apply(y, transpose=True)

    def _apply(self, array: np.ndarray, *, transpose: bool) -> np.ndarray:
        dtype = np.result_type(array.dtype, np.float32)
        out = np.empty(self.range_shape, dtype=dtype)
        for k, matrix in enumerate(self.matrices):
            band = np.ascontiguousarray(array[:, :, k]).ravel()
            result = matrix.T @ band if transpose else matrix @ band
            out[:, :, k] = result.reshape(self.patch_shape)
        return out


def _patch(
    model: DispersionModel,
    origin: tuple[int, int],
    shape: tuple[int, int] | None,
    overhang_px: int = 0,
) -> tuple[int, int, int, int]:
    """(row0, col0, rows, cols) of a patch checked to lie inside the model's image.

    The image is widened by `overhang_px` on every side before the check.
    """
    image_rows, image_cols = (int(n) for n in model.image_shape)
    m = int(overhang_px)
    row0, col0 = (int(v) for v in origin)
    if shape is None:
        rows, cols = image_rows - row0, image_cols - col0
    else:
        rows, cols = (int(n) for n in shape)
    if (
        row0 < -m
        or col0 < -m
        or rows < 1
        or cols < 1
        or row0 + rows > image_rows + m
        or col0 + cols > image_cols + m
    ):
        raise DataError(
            f"patch at origin (row, col) = ({row0}, {col0}) with shape ({rows}, {cols}) is not "
            f"inside the dispersion model's image of shape ({image_rows}, {image_cols}); was "
            "the model calibrated for this camera and image size?"
        )
    return row0, col0, rows, cols


#: Sampling weights Φ can use.
INTERPOLATIONS = ("bilinear", "cubic")


def check_interpolation(interpolation: str) -> str:
    """`interpolation` if it is one of :data:`INTERPOLATIONS`, else a DataError."""
    if interpolation not in INTERPOLATIONS:
        raise DataError(
            f"unknown interpolation {interpolation!r} for the dispersion operator; use "
            f"{' or '.join(repr(i) for i in INTERPOLATIONS)}"
        )
    return interpolation


class AxisTaps(NamedTuple):
    """Φ's sampling weights, one axis at a time, of every band and output pixel.

    Output pixel p = (i, k) (flat index i·cols + k) of band j takes
    ``weights_y[j, a, p] · weights_x[j, b, p]`` of the source pixel
    ``(i + offsets_y[j, a, p], k + offsets_x[j, b, p])``, wrapped round the patch (periodic
    boundary; with ``"clamp"`` the offsets already stay inside it). Offsets are int64 px,
    (bands, taps, rows·cols) with 2 taps per axis bilinear and 4 cubic; weights float64,
    the same shape.
    """

    offsets_y: np.ndarray
    weights_y: np.ndarray
    offsets_x: np.ndarray
    weights_x: np.ndarray
    boundary: str


def _bilinear_taps(
    position: np.ndarray, size: int, boundary: str = "clamp"
) -> tuple[np.ndarray, np.ndarray]:
    """Source pixels and weights (…, 2, n) sampling an axis of `size` px linearly at
    `position` (…, n).

    With ``boundary="clamp"`` positions outside [0, size − 1] are moved to the nearest end
    (and both taps stay inside the axis); with ``"periodic"`` the sources are not wrapped
    here (:class:`AxisTaps` wraps them).
    """
    if boundary == "clamp":
        position = np.clip(position, 0.0, size - 1.0)
        first = np.clip(np.floor(position).astype(np.int64), 0, max(size - 2, 0))
        second = np.minimum(first + 1, size - 1)
    else:
        first = np.floor(position).astype(np.int64)
        second = first + 1
    fraction = position - first  # in [0, 1]; 0 when size == 1
    return np.stack([first, second], axis=-2), np.stack([1 - fraction, fraction], axis=-2)


def keys_kernel(t: np.ndarray, a: float = -0.5) -> np.ndarray:
    """Keys' cubic convolution kernel at offsets `t` (px): 1 at 0, 0 at other integers."""
    t = np.abs(t)
    return np.where(t <= 1.0, _keys_near(t, a), np.where(t < 2.0, _keys_far(t, a), 0.0))


def _keys_near(t: np.ndarray, a: float) -> np.ndarray:
    """Keys' kernel for |offsets| t in [0, 1]."""
    return ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0


def _keys_far(t: np.ndarray, a: float) -> np.ndarray:
    """Keys' kernel for |offsets| t in [1, 2]."""
    return ((a * t - 5.0 * a) * t + 8.0 * a) * t - 4.0 * a


def _keys_taps(fraction: np.ndarray, a: float = -0.5) -> np.ndarray:
    """:func:`keys_kernel` at offsets ``fraction - (-1, 0, 1, 2)`` (…, 4, n) for fractions
    (…, n) in [0, 1) (a 0-d or 1-d `fraction` gives (4, n)): the outer taps on the kernel's
    far piece, the inner on its near piece, the same values without evaluating both pieces
    at every tap."""
    f = np.asarray(fraction)
    if f.ndim < 2:
        f = f.ravel()
    return np.stack(
        [_keys_far(1.0 + f, a), _keys_near(f, a), _keys_near(1.0 - f, a), _keys_far(2.0 - f, a)],
        axis=-2,
    )


def _cubic_taps(
    position: np.ndarray, size: int, boundary: str = "clamp"
) -> tuple[np.ndarray, np.ndarray]:
    """Source pixels and weights (…, 4, n) sampling an axis of `size` px at `position`
    (…, n) by Keys' cubic convolution.

    With ``boundary="clamp"`` positions are first moved into the axis and sources beyond
    it repeat its end pixel; with ``"periodic"`` the sources are not wrapped here
    (:class:`AxisTaps` wraps them).
    """
    if boundary == "clamp":
        position = np.clip(position, 0.0, size - 1.0)
    first = np.floor(position).astype(np.int64)
    sources = first[..., None, :] + np.arange(-1, 3)[:, None]
    if boundary == "clamp":
        sources = np.clip(sources, 0, size - 1)
    return sources, _keys_taps(position - first)


def _sparse_rows(indices: np.ndarray, weights: np.ndarray, n: int) -> sp.csr_matrix:
    """An n × n CSR matrix with a fixed number of (index, weight) entries per row."""
    taps = indices.shape[1]
    index_dtype = np.int32 if taps * n < np.iinfo(np.int32).max else np.int64
    matrix = sp.csr_matrix(
        (
            weights.ravel(),
            indices.ravel().astype(index_dtype),
            np.arange(0, taps * n + 1, taps, dtype=index_dtype),
        ),
        shape=(n, n),
    )
    matrix.sum_duplicates()  # clamped or wrapped neighbours repeat an index
    matrix.eliminate_zeros()  # integer sample points need one weight, not all
    return matrix


_SAMPLING = {"bilinear": _bilinear_taps, "cubic": _cubic_taps}


def dispersion_samples(
    model: DispersionModel,
    bounds_nm: tuple[float, float],
    *,
    origin: tuple[int, int] = (0, 0),
    shape: tuple[int, int] | None = None,
    min_count: int,
    step_px: float = 0.1,
    overhang_px: int = 0,
) -> np.ndarray:
    """Wavelengths at which to sample dispersion for a patch (thesis §3.2.5).

    The model is evaluated at the centres of the patch's four quadrants for λ_min and
    λ_max (not at the centre, where dispersion is minute, nor at the edges, where models
    are least accurate). The dispersion scale l of the patch is the larger of

    * the thesis' mean length of these eight displacement vectors, and
    * the mean over the quadrants of the spread ‖e(λ_max) − e(λ_min)‖.

    The number of samples is n = max(`min_count`, ⌈l / `step_px`⌉ + 1), so consecutive
    sampled wavelengths shift the image by about `step_px` or less on average.

    Parameters
    ----------
    model : DispersionModel
        A spectral (``xylambda``) model, either direction.
    bounds_nm : (λ_min, λ_max)
        Wavelengths where the camera is non-negligibly sensitive, nm; λ_min < λ_max.
    origin : (row0, col0)
        Full-image pixel of the patch's first pixel.
    shape : (rows, cols), optional
        Patch size, px; default: from `origin` to the end of the model's image.
    min_count : int
        Least number of samples (thesis: the number of spectral basis vectors of B).
    step_px : float
        Largest shift between consecutive samples aimed for, px (thesis: 0.1, the
        perceptibility limit of Rudakova and Monasse).
    overhang_px : int
        How far the patch may reach beyond the model's image, px (as for
        :class:`Dispersion`).

    Returns
    -------
    ndarray (n,) float64
        n equally spaced wavelengths from λ_min to λ_max inclusive, nm; for a model
        clamped to its domain (:meth:`~calibration.DispersionModel.within_domain`), from
        λ_min to λ_max narrowed to the calibrated range.

    Notes
    -----
    Departure from the thesis: its mean vector length alone equals the spread only when
    the reference wavelength lies at one end of [λ_min, λ_max]. With the reference inside
    (e.g. 600 nm in 400–700 nm) the two end vectors point in opposite directions and the
    image moves by up to twice that length across the range, so the thesis' n would leave
    ≈ 0.2 px between samples; taking the larger of the two scales keeps its stated aim.
    Because dispersion is not linear in λ, the shift between consecutive samples varies
    along the range: the bound holds on average, exactly only for dispersion linear in λ.
    """
    if model.variables != "xylambda":
        raise DataError(
            "spectral sampling of dispersion needs a spectral (xylambda) dispersion model; "
            "a colour-channel model has one displacement per channel"
        )
    lo, hi = (float(v) for v in bounds_nm)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise DataError(f"bounds_nm must be finite with λ_min < λ_max, got ({lo}, {hi})")
    if int(min_count) < 1:
        raise DataError(f"min_count must be at least 1, got {min_count}")
    if not (np.isfinite(step_px) and step_px > 0):
        raise DataError(f"step_px must be positive, got {step_px}")
    span = model.region.wavelength_nm
    if model.extrapolation == "clamp" and span is not None:
        # a clamped model is constant beyond its range, as the samples' hats are: sampling
        # inside the range only loses nothing
        inner = (max(lo, span[0]), min(hi, span[1]))
        if inner[0] < inner[1]:
            lo, hi = inner
    row0, col0, rows, cols = _patch(model, origin, shape, overhang_px)
    # quadrant centres of the patch's pixel area [−0.5, n − 0.5], full-image px
    qx = col0 - 0.5 + cols * np.array([0.25, 0.75, 0.25, 0.75])
    qy = row0 - 0.5 + rows * np.array([0.25, 0.25, 0.75, 0.75])
    ex, ey = model.displacement(qx[:, None], qy[:, None], np.array([[lo, hi]]))
    if not (np.all(np.isfinite(ex)) and np.all(np.isfinite(ey))):
        raise DataError("the dispersion model gives NaN or Inf displacements in this patch")
    mean_length = float(np.mean(np.hypot(ex, ey)))
    mean_spread = float(np.mean(np.hypot(ex[:, 1] - ex[:, 0], ey[:, 1] - ey[:, 0])))
    scale = max(mean_length, mean_spread)
    # the 1e-9 keeps rounding (1.1 / 0.1 = 11.000000000000002) from adding a sample
    count = max(int(min_count), math.ceil(scale / step_px - 1e-9) + 1)
    return np.linspace(lo, hi, count)
