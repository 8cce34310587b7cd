"""Correction of lateral chromatic aberration by warping (the Rudakova–Monasse baseline).

A ``from_reference`` dispersion model says that the feature imaged at p in the reference
image (the Green channel, or the reference band) is imaged at p + d(p) in another channel
or band (thesis §3.2.4, last paragraph). Resampling that channel at p + d(p) therefore
moves every feature back onto its reference position::

    corrected(p) = image(p + d(p))

This is how Rudakova and Monasse correct colour images, and the baseline the thesis
compares its reconstruction against. Images are warped one 2-D plane at a time, in
blocks of rows, so a (rows, cols, bands) cube needs little more memory than itself and
its result.

The model is evaluated on a grid every `field_step_px` pixels and interpolated to every
pixel with cubic splines (dispersion fields are smooth; at the default 8 px the
interpolation error of a smooth field is far below 0.001 px), which makes thin-plate
spline models affordable on full-size images. ``field_step_px=1`` evaluates every pixel.

A ``to_reference`` model (the direction image formation uses) is inverted on the fly:
the band position q of reference position p solves ``q + d_to(q) = p``, found by the
fixed-point iteration ``q ← p − d_to(q)`` (a contraction, as dispersion fields change by
far less than a pixel per pixel) to :data:`INVERSION_TOLERANCE_PX`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage
from scipy.interpolate import BSpline, make_interp_spline

from calibration.dispersion_model import DispersionModel
from labkit.cfa import CHANNELS
from labkit.errors import DataError

#: Pixels resampled per block (bounds the per-block temporaries: ~40 B per pixel).
_BLOCK_PIXELS = 1 << 18
#: Accuracy of the inversion of a ``to_reference`` model, px.
INVERSION_TOLERANCE_PX = 1e-6
#: Fixed-point iterations allowed for that inversion.
_INVERSION_ITERATIONS = 50
#: Boundary modes of :func:`scipy.ndimage.map_coordinates` that never produce NaN.
_MODES = ("nearest", "reflect", "mirror", "grid-mirror", "wrap", "grid-wrap", "constant")

#: (r0, r1) → (dx, dy) of rows r0:r1, px.
FieldRows = Callable[[int, int], tuple[np.ndarray, np.ndarray]]


def warp(
    image: np.ndarray,
    dx: np.ndarray | float,
    dy: np.ndarray | float,
    *,
    order: int = 1,
    mode: str = "nearest",
) -> np.ndarray:
    """Resample a 2-D image at displaced positions: ``out(p) = image(p + d(p))``.

    Parameters
    ----------
    image : ndarray (rows, cols)
        The image; float32 stays float32, anything else becomes float64.
    dx, dy : ndarray (rows, cols) or float
        Displacement along columns (x) and rows (y) at every output pixel, px.
    order : int
        Spline order of the interpolation, 0–5 (1 = bilinear).
    mode : str
        How positions outside the image are filled (:func:`scipy.ndimage.map_coordinates`
        modes; default: the nearest border pixel).

    Returns
    -------
    ndarray (rows, cols)

    Raises
    ------
    DataError
        Not a 2-D image, displacements of another shape, or NaN/Inf in either.
    """
    plane = np.asarray(image)
    if plane.ndim != 2:
        raise DataError(f"warp needs a 2-D image, got shape {plane.shape}")
    _check_options(order, mode)
    _check_finite(plane, "the image to warp")
    try:
        fdx = np.broadcast_to(np.asarray(dx, dtype=np.float64), plane.shape)
        fdy = np.broadcast_to(np.asarray(dy, dtype=np.float64), plane.shape)
    except ValueError:
        raise DataError(
            f"displacements of shape {np.shape(dx)} / {np.shape(dy)} do not match the "
            f"image {plane.shape}"
        ) from None
    _check_finite(fdx, "dx")
    _check_finite(fdy, "dy")
    out = np.empty(plane.shape, dtype=_out_dtype(plane.dtype))
    _warp_plane(plane, lambda r0, r1: (fdx[r0:r1], fdy[r0:r1]), out, order=order, mode=mode)
    return out


def correct_channels(
    rgb: np.ndarray,
    model: DispersionModel,
    *,
    order: int = 1,
    field_step_px: int = 8,
) -> np.ndarray:
    """Warp the Red and Blue channels of a colour image onto Green.

    Parameters
    ----------
    rgb : ndarray (rows, cols, 3)
        A demosaiced colour image (channels R, G, B).
    model : DispersionModel
        A colour-channel (``variables="xy"``) model calibrated on images of this size
        (``from_reference``, or ``to_reference`` inverted on the fly); every channel it
        has a field for is warped onto its reference channel.
    order : int
        Interpolation spline order (1 = bilinear).
    field_step_px : int
        Spacing of the grid the model is evaluated on, px (1 = every pixel).

    Returns
    -------
    ndarray (rows, cols, 3)
        The corrected image; float32 stays float32. Channels without a field are copied.

    Raises
    ------
    DataError
        A spectral model, a model for another image size, or an image that is not
        (rows, cols, 3) or holds NaN/Inf.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise DataError(f"correct_channels needs a (rows, cols, 3) image, got shape {rgb.shape}")
    _check_model(model, rgb.shape[:2], "xy")
    _check_options(order, "nearest")
    _check_finite(rgb, "the colour image")
    out = np.empty(rgb.shape, dtype=_out_dtype(rgb.dtype))
    out[...] = rgb
    for channel in model.channels:
        if channel not in CHANNELS:
            raise DataError(
                f"dispersion model has a field for channel {channel!r}; expected R or B"
            )
        index = CHANNELS.index(channel)
        field = _model_field(model, rgb.shape[:2], field_step_px, channel=channel)
        plane = np.ascontiguousarray(rgb[..., index])
        _warp_plane(plane, field, out[..., index], order=order, mode="nearest")
    return out


def correct_spectral(
    cube: np.ndarray,
    wavelengths_nm: np.ndarray,
    model: DispersionModel,
    *,
    order: int = 1,
    field_step_px: int = 8,
) -> np.ndarray:
    """Warp every band of a spectral image onto the reference band's geometry.

    Parameters
    ----------
    cube : ndarray (rows, cols, bands)
        Spectral or multispectral image.
    wavelengths_nm : ndarray (bands,)
        Band wavelengths, nm; band b is resampled at p + d(p, λ_b).
    model : DispersionModel
        A spectral (``variables="xylambda"``) model calibrated on images of this size
        (``from_reference``, or ``to_reference`` inverted on the fly). Bands outside its
        calibrated wavelength range use the model's extrapolation.
    order : int
        Interpolation spline order (1 = bilinear).
    field_step_px : int
        Spacing of the grid the model is evaluated on, px (1 = every pixel).

    Returns
    -------
    ndarray (rows, cols, bands)
        The corrected cube; float32 stays float32. Peak memory: the input, the result
        and a few single-band temporaries.

    Raises
    ------
    DataError
        A colour-channel model, a model for another image size, a
        wavelength count that does not match the bands, or NaN/Inf in the cube.
    """
    cube = np.asarray(cube)
    if cube.ndim != 3:
        raise DataError(f"correct_spectral needs a (rows, cols, bands) cube, got {cube.shape}")
    wavelengths = np.asarray(wavelengths_nm, dtype=np.float64).ravel()
    if wavelengths.size != cube.shape[2] or not np.all(np.isfinite(wavelengths)):
        raise DataError(
            f"the cube has {cube.shape[2]} bands but {wavelengths.size} wavelengths were "
            "given (all finite, nm); pass one wavelength per band"
        )
    _check_model(model, cube.shape[:2], "xylambda")
    _check_options(order, "nearest")
    out = np.empty(cube.shape, dtype=_out_dtype(cube.dtype))
    for band, wavelength in enumerate(wavelengths):
        plane = np.ascontiguousarray(cube[..., band])
        _check_finite(plane, f"band {band} ({wavelength:g} nm) of the cube")
        field = _model_field(model, cube.shape[:2], field_step_px, wavelength_nm=wavelength)
        _warp_plane(plane, field, out[..., band], order=order, mode="nearest")
    return out


# -- helpers --------------------------------------------------------------------------


def _warp_plane(
    plane: np.ndarray, field: FieldRows, out: np.ndarray, *, order: int, mode: str
) -> None:
    """Write ``plane(p + d(p))`` into `out` (a (rows, cols) array or view), block by block."""
    rows, cols = plane.shape
    if order > 1:
        source = ndimage.spline_filter(plane, order=order, mode=mode, output=np.float64)
    else:
        source = plane
    block = max(1, _BLOCK_PIXELS // cols)
    columns = np.arange(cols, dtype=np.float64)[None, :]
    for r0 in range(0, rows, block):
        r1 = min(r0 + block, rows)
        dx, dy = field(r0, r1)
        coordinates = np.empty((2, r1 - r0, cols))
        np.add(np.arange(r0, r1, dtype=np.float64)[:, None], dy, out=coordinates[0])
        np.add(columns, dx, out=coordinates[1])
        del dx, dy
        if not np.all(np.isfinite(coordinates)):
            raise DataError(
                f"the displacement field holds NaN or Inf in rows {r0}–{r1 - 1}; check the "
                "dispersion model (or the dx, dy given to warp)"
            )
        out[r0:r1] = ndimage.map_coordinates(
            source, coordinates, output=out.dtype, order=order, mode=mode, prefilter=False
        )


def _model_field(
    model: DispersionModel,
    shape: tuple[int, int],
    step: int,
    *,
    wavelength_nm: float | None = None,
    channel: str | None = None,
) -> FieldRows:
    """Displacement rows of `model` over an image of `shape`: exact or spline-interpolated."""
    if int(step) != step or step < 1:
        raise DataError(f"field_step_px must be a positive integer, got {step}")
    rows, cols = shape
    nodes_y, nodes_x = _nodes(rows, int(step)), _nodes(cols, int(step))
    if nodes_y is None or nodes_x is None:
        x = np.arange(cols, dtype=np.float64)[None, :]

        def exact(r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
            y = np.arange(r0, r1, dtype=np.float64)[:, None]
            return from_reference_displacement(model, x, y, wavelength_nm, channel=channel)

        return exact
    node_dx, node_dy = from_reference_displacement(
        model, nodes_x[None, :], nodes_y[:, None], wavelength_nm, channel=channel
    )
    # not-a-knot cubic splines through the nodes: along x to every column (a dense
    # (cols, nx) matrix), then along y as B-spline coefficients evaluated per block
    knots_x, to_coef_x = _spline_operator(nodes_x)
    across = BSpline(knots_x, to_coef_x, 3)(np.arange(cols, dtype=np.float64))  # (cols, nx)
    knots_y, to_coef_y = _spline_operator(nodes_y)
    rows_coef = to_coef_y @ np.concatenate([node_dx @ across.T, node_dy @ across.T], axis=1)
    down = BSpline(knots_y, rows_coef, 3)

    def interpolated(r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
        both = down(np.arange(r0, r1, dtype=np.float64))  # (r1 - r0, 2 cols)
        return both[:, :cols], both[:, cols:]

    return interpolated


def from_reference_displacement(
    model: DispersionModel,
    x: np.ndarray,
    y: np.ndarray,
    wavelength_nm: float | None = None,
    *,
    channel: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Displacement (dx, dy) px from reference positions (x, y) px to where a band images them.

    A ``from_reference`` model gives it directly; a ``to_reference`` model is inverted by
    fixed-point iteration to :data:`INVERSION_TOLERANCE_PX`.

    Raises
    ------
    DataError
        The inversion does not converge (a field that folds the image onto itself).
    """
    kwargs = {"channel": channel} if channel is not None else {}
    extra = () if wavelength_nm is None else (wavelength_nm,)
    if model.direction == "from_reference":
        return model.displacement(x, y, *extra, **kwargs)
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    dx, dy = model.displacement(x, y, *extra, **kwargs)
    qx, qy = x - dx, y - dy
    for _ in range(_INVERSION_ITERATIONS):
        dx, dy = model.displacement(qx, qy, *extra, **kwargs)
        new_x, new_y = x - dx, y - dy
        change = float(np.max(np.hypot(new_x - qx, new_y - qy), initial=0.0))
        qx, qy = new_x, new_y
        if not np.isfinite(change):
            break
        if change <= INVERSION_TOLERANCE_PX:
            return qx - x, qy - y
    where = f" at {wavelength_nm:g} nm" if wavelength_nm is not None else ""
    where += f" for channel {channel}" if channel is not None else ""
    raise DataError(
        f"could not invert the to_reference dispersion model{where} (fixed-point iteration "
        "did not converge); check the model, or calibrate a from_reference one for warping"
    )


def _nodes(size: int, step: int) -> np.ndarray | None:
    """Grid nodes 0, step, … covering 0…size−1, or None where too few for cubic splines."""
    if step == 1:
        return None
    count = -(-(size - 1) // step) + 1
    if count < 4:
        return None
    return step * np.arange(count, dtype=np.float64)


def _spline_operator(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Knots and the (n_coef, n_nodes) matrix from node values to the B-spline
    coefficients of the not-a-knot cubic spline through them."""
    spline = make_interp_spline(nodes, np.eye(nodes.size), k=3)
    return spline.t, spline.c


def _check_model(model: DispersionModel, shape: tuple[int, int], variables: str) -> None:
    if model.variables != variables:
        if variables == "xy":
            raise DataError(
                "this is a spectral (x, y, λ) dispersion model; warp spectral images with it "
                "(correct_spectral; on the command line `labkit correct warp SPECTRAL.exr "
                "--model MODEL.yaml`), or calibrate a colour-channel model (`labkit calibrate "
                "dispersion HDR --reference G`) for colour images"
            )
        raise DataError(
            "this is a colour-channel dispersion model (R/B relative to G); warp colour "
            "images with it (correct_channels; on the command line `labkit correct warp "
            "RAW --model MODEL.yaml`), or calibrate a spectral model between filter bands "
            "(`labkit calibrate dispersion HDR --reference 600`) for spectral images"
        )
    model_shape = tuple(int(v) for v in model.image_shape)
    if model_shape != tuple(shape):
        raise DataError(
            f"the dispersion model was calibrated on {model_shape[1]}×{model_shape[0]} px "
            f"images but this image is {shape[1]}×{shape[0]} px; use a model calibrated "
            "with the same camera mode (sensor size, binning, region of interest)"
        )


def _check_options(order: int, mode: str) -> None:
    if order not in range(6):
        raise DataError(f"interpolation order must be 0–5, got {order}")
    if mode not in _MODES:
        raise DataError(f"boundary mode {mode!r} is not supported; use one of {_MODES}")


def _check_finite(array: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(array)):
        raise DataError(f"{what} holds NaN or Inf; fix or mask those pixels before warping")


def _out_dtype(dtype: np.dtype) -> np.dtype:
    return np.dtype(np.float32) if dtype == np.float32 else np.dtype(np.float64)
