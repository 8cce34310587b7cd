"""Scores of a reconstruction of a labelled ColorChecker chart (thesis §4.4, Table 5.7).

Given the chart's label image (0: background, 1–24: the patches in chart order),
:class:`ChartScorer` scores a :class:`~reconstruction.Reconstruction` of it three ways:

- its patch-centre spectra against the patches' measured reflectances
  (:func:`patch_spectral_errors`; the thesis' Table 5.7);
- its per-pixel spectra against a spectral truth of the same geometry, over the chart and
  in the patches' edge strips, centres and surround
  (:func:`~reconstruction.spectral_strip_errors`);
- the residual chromatic aberration of its raw colour image in the patches' edge strips
  (:func:`~reconstruction.evaluate`, as ``labkit evaluate`` reports it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy import ndimage

from labkit.errors import DataError
from labkit.spectra import Spectra
from reconstruction.evaluate.evaluation import evaluate
from reconstruction.evaluate.metrics import spectral_errors
from reconstruction.evaluate.residual_aberration import patch_regions, spectral_strip_errors
from reconstruction.result import Reconstruction

CENTRE_FRACTION = 0.5
"""Patch centre: the pixels at least this fraction of the patch's largest distance to its
edge away from the edge (the inner half, by the distance transform of each label)."""
CHART_BORDER_PX = 8
"""Border of the frame left out of the per-pixel errors, px (interpolation borders)."""


def patch_centres(labels: np.ndarray, *, fraction: float = CENTRE_FRACTION) -> list[np.ndarray]:
    """Boolean masks of the centres of patches 1…24 of a label image.

    A patch's centre is the set of its pixels whose distance to the patch's edge is at
    least ``1 − fraction`` of the largest such distance (``fraction = 0.5``: the inner half).

    Raises
    ------
    DataError
        A patch label 1…24 is missing.
    """
    masks = []
    missing = []
    for label in range(1, 25):
        patch = labels == label
        if not patch.any():
            missing.append(label)
            continue
        distance = ndimage.distance_transform_edt(patch)
        masks.append(distance >= (1.0 - fraction) * distance.max())
    if missing:
        raise DataError(
            f"the label image has no pixels for patch(es) {missing}; it needs labels 1–24 "
            "(ColorChecker order, row by row from the top left) and 0 for the background"
        )
    return masks


def patch_spectral_errors(
    cube: np.ndarray,
    wavelengths_nm: Sequence[float],
    centres: list[np.ndarray],
    reflectances: Spectra,
) -> dict[str, Any]:
    """Patch-centre spectra of `cube` against measured reflectances (thesis Table 5.7).

    Each patch's mean spectrum over its centre is compared with its reflectance sampled at
    the cube's band wavelengths, after scaling each band by least squares over the 24
    patches (eq. 4.9: the cube's units are not reflectance).

    Returns
    -------
    dict
        ``"mrae"``, ``"rmse"`` (means over the patches), ``"per_patch_mrae"`` (24,),
        ``"estimate"`` (24, bands) in reflectance units after the registration, and
        ``"truth"`` (24, bands).
    """
    wavelengths = np.asarray(wavelengths_nm, dtype=float)
    estimate = np.stack([cube[mask].mean(axis=0) for mask in centres]).astype(float)
    truth = reflectances.resample(wavelengths).values.T.astype(float)
    errors = spectral_errors(
        truth[:, None, :], estimate[:, None, :], ssim=False, register=True, floor=0.0
    )
    return {
        "mrae": float(errors.mrae),
        "rmse": float(errors.rmse_pixel),
        "per_patch_mrae": errors.mrae_map[:, 0].filled(np.nan),
        "estimate": estimate * np.asarray(errors.scale),
        "truth": truth,
    }


@dataclass
class ChartScorer:
    """What scores reconstructions of one raw image of a labelled chart.

    Attributes
    ----------
    labels : ndarray (rows, cols) int
        Patch labels 1–24 (0: background).
    raw : ndarray (rows, cols)
        The raw image reconstructed.
    cfa : str
        Its Bayer layout.
    reflectances : Spectra
        The 24 patches' measured reflectances.
    truth : ndarray (rows, cols, bands) or callable, optional
        A per-pixel spectral truth in the reconstructions' geometry, or what makes it
        (called once, when a per-pixel error first needs it).
    truth_wavelengths_nm : sequence of float, optional
        Its bands' wavelengths, nm.
    """

    labels: np.ndarray
    raw: np.ndarray
    cfa: str
    reflectances: Spectra
    truth: np.ndarray | Callable[[], np.ndarray] | None = None
    truth_wavelengths_nm: Sequence[float] | None = None

    @cached_property
    def truth_cube(self) -> np.ndarray | None:
        """:attr:`truth`, made if it was given as a callable."""
        return self.truth() if callable(self.truth) else self.truth

    @cached_property
    def centres(self) -> list[np.ndarray]:
        """Masks of the 24 patch centres (:func:`patch_centres` of :attr:`labels`)."""
        return patch_centres(self.labels)

    def patch_errors(self, cube: np.ndarray, wavelengths_nm: Sequence[float]) -> dict[str, Any]:
        """:func:`patch_spectral_errors` of `cube` on this chart."""
        return patch_spectral_errors(cube, wavelengths_nm, self.centres, self.reflectances)

    def pixel_errors(self, result: Reconstruction) -> dict[str, float]:
        """A reconstruction's spectral RMSE per pixel against :attr:`truth`: over the chart
        (its patches and the strip width around them, the :data:`CHART_BORDER_PX` border
        left out) and in the patches' edge strips, centres and surround (relative to the
        chart's mean truth).

        Returns
        -------
        dict
            ``chart``, ``strips``, ``centres``, ``surround``.

        Raises
        ------
        DataError
            No truth, or the reconstruction's bands are not among the truth's.
        """
        truth = self.truth_cube
        if truth is None or self.truth_wavelengths_nm is None:
            raise DataError("per-pixel errors need a spectral truth of the chart; none given")
        bands = np.asarray(self.truth_wavelengths_nm, dtype=float)
        wanted = np.asarray(result.wavelengths_nm, dtype=float)
        index = np.abs(bands[None, :] - wanted[:, None]).argmin(axis=1)
        if not np.allclose(bands[index], wanted, atol=1.0):
            raise DataError(
                f"the reconstruction's bands {wanted.tolist()} nm are not among the "
                f"truth's {bands.tolist()} nm; reconstruct at its bands"
            )
        # the chart: its patches and their surround (the rest of the frame holds the lab,
        # whose truth is dark and noisy)
        regions = patch_regions(self.labels.shape, labels=self.labels)
        keep = (regions.labels > 0) | regions.surround
        b = CHART_BORDER_PX
        keep[:b] = keep[-b:] = keep[:, :b] = keep[:, -b:] = False
        split = spectral_strip_errors(
            truth[..., index], result.spectral, labels=self.labels, mask=keep
        )
        return {
            "chart": split.whole,
            "strips": split.strips,
            "centres": split.centres,
            "surround": split.surround,
        }

    def edge_rmse(self, images: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
        """Edge-strip RMSE per channel (fractions of the raw mean, as ``labkit evaluate``
        reports them) of each raw colour image of the chart, by name:
        {name: {"R": …, "G": …, "B": …}}."""
        methods = evaluate(self.raw, images, cfa=self.cfa, labels=self.labels).as_dict()
        return {
            name: {
                c: float(methods["methods"][name]["residual_aberration"]["edge"]["rmse"][c])
                for c in "RGB"
            }
            for name in images
        }

    def score(self, result: Reconstruction) -> dict[str, float]:
        """A reconstruction's patch-centre MRAE and RMSE against the reflectances, the
        edge-strip RMSE R/G/B of its raw colour image, and, with a truth, its per-pixel
        spectral RMSE (``spectral_rmse`` over the chart, ``spectral_rmse_strips``,
        ``…_centres``, ``…_surround``)."""
        patch = self.patch_errors(result.spectral, result.wavelengths_nm)
        edge = self.edge_rmse({"x": result.raw_colour})["x"]
        scores = {
            "mrae": patch["mrae"],
            "rmse": patch["rmse"],
            **{f"edge_rmse_{c}": edge[c] for c in "RGB"},
        }
        if self.truth is not None:
            pixels = self.pixel_errors(result)
            scores["spectral_rmse"] = pixels["chart"]
            scores.update(
                {f"spectral_rmse_{k}": pixels[k] for k in ("strips", "centres", "surround")}
            )
        return scores
