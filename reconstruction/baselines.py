"""Comparison methods: demosaicing, optionally followed by colour-channel warping (§4.6).

The thesis compares its reconstruction with plain demosaicing (bilinear interpolation
and adaptive residual interpolation, §4.6.3) and with the lateral chromatic aberration
correction of Rudakova and Monasse: demosaic, then warp the Red and Blue channels onto
Green with a calibrated colour-channel dispersion model (§4.6.4). Adaptive residual
interpolation has no maintained Python implementation; the gradient-corrected linear
filters of Malvar et al. (2004) and the directional filtering of Menon et al. (2007),
both from ``colour-demosaicing``, stand in as the stronger demosaicers.

:data:`BASELINES` names the demosaicers (``demosaic(raw, layout) → rgb``);
:func:`baseline` runs one, and with a ``from_reference`` colour-channel dispersion model
adds the warping step (:func:`calibration.warp.correct_channels`). The thesis notes
that bilinear demosaicing followed by bilinear warping is what Rudakova and Monasse most
likely intended (one bilinear interpolation of the mosaic).

Borders: for Malvar and Menon the mosaic is mirrored by :data:`PAD_PX` pixels (an even
number, so the Bayer phase is kept) before demosaicing, so that every filter sees real
neighbours of the right colour, and cropped after (colour-demosaicing's own convolution
boundary would mirror about the edge pixel and mix colours); bilinear is
:func:`labkit.io.demosaic_bilinear`, which does the same with 2 px.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calibration.dispersion_model import DispersionModel
from calibration.warp import correct_channels
from labkit.cfa import check_layout
from labkit.errors import DataError
from labkit.io import demosaic_bilinear

#: Mirror padding of the mosaic before demosaicing, px (even: keeps the Bayer phase).
PAD_PX = 8

#: ``demosaic(raw (rows, cols), layout) → (rows, cols, 3)``.
Demosaicer = Callable[[np.ndarray, str], np.ndarray]


def _mirrored(method: Callable[..., np.ndarray], raw: np.ndarray, layout: str) -> np.ndarray:
    """`method` (a colour-demosaicing function) on a mosaic mirrored by PAD_PX, cropped."""
    padded = np.pad(np.asarray(raw, dtype=np.float64), PAD_PX, mode="reflect")
    rgb = method(padded, check_layout(layout))[PAD_PX:-PAD_PX, PAD_PX:-PAD_PX]
    return rgb.astype(np.float32)


def demosaic_malvar(raw: np.ndarray, layout: str) -> np.ndarray:
    """Malvar–He–Cutler (2004) gradient-corrected bilinear demosaic, (rows, cols, 3) float32."""
    from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004

    return _mirrored(demosaicing_CFA_Bayer_Malvar2004, raw, layout)


def demosaic_menon(raw: np.ndarray, layout: str) -> np.ndarray:
    """Menon–Andriani–Calvagno (2007) directional demosaic with refining, float32."""
    from colour_demosaicing import demosaicing_CFA_Bayer_Menon2007

    return _mirrored(demosaicing_CFA_Bayer_Menon2007, raw, layout)


#: Demosaicing methods by name: ``demosaic(raw (rows, cols), layout) → (rows, cols, 3)``.
BASELINES: dict[str, Demosaicer] = {
    "bilinear": demosaic_bilinear,
    "malvar": demosaic_malvar,
    "menon": demosaic_menon,
}


def baseline(
    raw: np.ndarray,
    method: str,
    *,
    cfa: str,
    dispersion: DispersionModel | None = None,
    order: int = 1,
    field_step_px: int = 8,
) -> np.ndarray:
    """Demosaic a raw mosaic with a named baseline; optionally correct it by warping.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, any linear units (e.g. HDR e⁻/s), at least 2 × 2 px.
    method : str
        A key of :data:`BASELINES`: ``"bilinear"``, ``"malvar"`` or ``"menon"``.
    cfa : str
        Bayer layout of `raw`, e.g. ``"GBRG"``.
    dispersion : DispersionModel, optional
        A colour-channel (``variables="xy"``) dispersion model calibrated on images of
        this size (either direction; see :mod:`calibration.warp`): the Red and Blue
        channels are then warped onto Green (Rudakova–Monasse correction).
    order : int
        Spline order of the warping interpolation (1 = bilinear).
    field_step_px : int
        Grid spacing on which the model is evaluated before interpolation, px.

    Returns
    -------
    ndarray (rows, cols, 3), float32
        R, G, B in the units of `raw`. Malvar's and Menon's filters have negative taps,
        so values may overshoot (or fall below 0) at sharp edges; nothing is clipped.

    Raises
    ------
    DataError
        An unknown method (the message lists the known ones), an unknown layout, a
        mosaic that is not 2-D, smaller than 2 × 2 or holds NaN/Inf, or a dispersion
        model of the wrong kind, direction or image size.
    """
    if method not in BASELINES:
        raise DataError(
            f"unknown baseline method {method!r}; use one of {', '.join(sorted(BASELINES))}"
        )
    layout = check_layout(cfa)
    mosaic = np.asarray(raw)
    if mosaic.ndim != 2 or min(mosaic.shape) < 2:
        raise DataError(
            f"baseline needs a (rows, cols) Bayer mosaic of at least 2 × 2 px, got shape "
            f"{mosaic.shape}"
        )
    if not np.all(np.isfinite(mosaic)):
        raise DataError("the raw mosaic holds NaN or Inf; fix or inpaint those pixels first")
    rgb = np.asarray(BASELINES[method](mosaic, layout), dtype=np.float32)
    if dispersion is not None:
        rgb = correct_channels(rgb, dispersion, order=order, field_step_px=field_step_px)
    return rgb
