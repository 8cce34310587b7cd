"""Score colour and spectral estimates of one raw image against baselines and truth (§4.4, §4.6).

:func:`baseline_images` runs the demosaicing baselines of :mod:`reconstruction.baselines`
(each also followed by colour-channel warping when a colour dispersion model is given);
:func:`evaluate` scores any set of named colour images of one raw image by

- the residual chromatic aberration of §4.4.3 (edge strips and centres of the patches of a
  ColorChecker-like chart, against an ideal image synthesised from the raw patch centres),
  when the chart geometry (`boxes` or `labels`) is given;
- the colour errors (4.10)–(4.12) against a known raw-colour truth (simulation);
- the spectral errors (4.3)–(4.7) of spectral estimates against a known spectral truth.

Estimates are divided by the raw image's mean and truths by their own mean, so error
figures are fractions of the mean signal and comparable between images. Against a truth,
each estimate is registered first (per band/channel scale (4.9), (4.13)), since the
truth's units (e.g. a simulator's irradiance) differ from the camera's by unknown factors.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.dispersion_model import DispersionModel
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.baselines import BASELINES, baseline
from reconstruction.evaluate.metrics import (
    ColourErrors,
    SpectralErrors,
    colour_errors,
    spectral_errors,
)
from reconstruction.evaluate.residual_aberration import ResidualAberration, residual_aberration

BORDER_PX = 8
"""Border left out of the comparisons with a truth, px (interpolation borders)."""

#: A spectral truth: ``truth(wavelengths_nm) → (rows, cols, n)``, or a fixed cube.
SpectralTruth = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Score:
    """The figures of one method (None where the input to compute them was not given)."""

    name: str
    seconds: float | None = None
    residual: ResidualAberration | None = None
    colour: ColourErrors | None = None
    spectral: SpectralErrors | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types."""
        return {
            "seconds": self.seconds,
            "residual_aberration": None if self.residual is None else self.residual.as_dict(),
            "colour": None if self.colour is None else self.colour.as_dict(),
            "spectral": None if self.spectral is None else self.spectral.as_dict(),
        }


@dataclass(frozen=True)
class Evaluation:
    """Scores of every method, in the order given (:func:`evaluate`)."""

    scores: dict[str, Score]
    normalisation: float
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON types: every method's figures, the normalisation and notes."""
        return {
            "units": "fraction of the raw image's mean (of the truth's mean against a truth)",
            "normalisation": self.normalisation,
            "methods": {name: score.as_dict() for name, score in self.scores.items()},
            "notes": list(self.notes),
        }

    def table(self) -> tuple[list[str], list[list[str]]]:
        """(header, rows) of a summary table: time, residual aberration, colour, spectral."""
        header = ["method", "time (s)"]
        have = {
            "residual": any(s.residual is not None for s in self.scores.values()),
            "colour": any(s.colour is not None for s in self.scores.values()),
            "spectral": any(s.spectral is not None for s in self.scores.values()),
        }
        if have["residual"]:
            header += ["edge RMSE R/G/B", "centre RMSE R/G/B"]
        if have["colour"]:
            header += ["colour RMSE R/G/B"]
        if have["spectral"]:
            header += ["spectral RMSE", "MRAE", "GOF"]
        rows = []
        for name, score in self.scores.items():
            row = [name, "—" if score.seconds is None else f"{score.seconds:.3g}"]
            if have["residual"]:
                r = score.residual
                row += _triples(None if r is None else (r.edge, r.centre), 2)
            if have["colour"]:
                row += _triples(None if score.colour is None else (score.colour,), 1)
            if have["spectral"]:
                s = score.spectral
                row += (
                    ["—"] * 3
                    if s is None
                    else [f"{s.rmse_global:.4f}", f"{s.mrae:.4f}", f"{s.gof:.4f}"]
                )
            rows.append(row)
        return header, rows


@fixed_blas_threads
def baseline_images(
    raw: np.ndarray,
    *,
    cfa: str,
    methods: Sequence[str] = tuple(BASELINES),
    colour_dispersion: DispersionModel | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Demosaic `raw` with each baseline, and each followed by warping given a colour model.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, any linear units.
    cfa : str
        Bayer layout, e.g. ``"GBRG"``.
    methods : sequence of str
        Keys of :data:`reconstruction.baselines.BASELINES`.
    colour_dispersion : DispersionModel, optional
        A colour-channel model (reference G, either direction) of this image size; adds
        ``"<method> + warp"`` images (Rudakova–Monasse correction, §4.6.4).

    Returns
    -------
    images : dict of str to ndarray (rows, cols, 3) float32
    seconds : dict of str to float
        Run time of each image, s.
    """
    unknown = [m for m in methods if m not in BASELINES]
    if unknown:
        raise DataError(
            f"unknown baseline method(s) {unknown}; use some of {', '.join(sorted(BASELINES))}"
        )
    images: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}
    for method in methods:
        for model in (None, colour_dispersion) if colour_dispersion is not None else (None,):
            name = method if model is None else f"{method} + warp"
            start = time.perf_counter()
            images[name] = baseline(raw, method, cfa=cfa, dispersion=model)
            seconds[name] = time.perf_counter() - start
    return images, seconds


@fixed_blas_threads
def evaluate(
    raw: np.ndarray,
    images: Mapping[str, np.ndarray],
    *,
    cfa: str,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    truth_colour: np.ndarray | None = None,
    spectral: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
    truth_spectral: SpectralTruth | None = None,
    seconds: Mapping[str, float] | None = None,
    border_px: int = BORDER_PX,
) -> Evaluation:
    """Score named colour (and spectral) estimates of one raw image.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        The raw mosaic the estimates were made from, any linear units.
    images : mapping of str to ndarray (rows, cols, 3)
        Colour estimates in the raw image's colour space and units (demosaiced, warped,
        or a reconstruction's raw colour).
    cfa : str
        Bayer layout of `raw`.
    boxes, labels : ndarray, optional
        ColorChecker patch geometry (see :func:`residual_aberration`); without either,
        no residual aberration is measured.
    truth_colour : ndarray (rows, cols, 3), optional
        The aberration-free raw-colour truth, any units (each estimate is registered).
    spectral : mapping of str to (cube (rows, cols, n), wavelengths_nm (n,)), optional
        Spectral estimates (e.g. reconstructions), scored against `truth_spectral`.
    truth_spectral : callable, optional
        ``truth(wavelengths_nm) → (rows, cols, n)``: the true spectral image at the
        estimate's band centres, any units (each band is registered).
    seconds : mapping of str to float, optional
        Run time of each method, s (reported as given).
    border_px : int
        Border left out of comparisons with a truth, px.

    Returns
    -------
    Evaluation

    Raises
    ------
    DataError
        A raw image that is not 2-D, finite and positive on average; an image of another
        size than `raw` or with NaN/Inf; a spectral estimate without `truth_spectral`.
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or not np.all(np.isfinite(raw)):
        raise DataError(f"raw image must be a finite 2-D mosaic, got shape {raw.shape}")
    scale = float(raw.mean())
    if not scale > 0:
        raise DataError("raw image has no signal (mean ≤ 0); nothing to evaluate")
    spectral = dict(spectral or {})
    if spectral and truth_spectral is None:
        raise DataError("spectral estimates need truth_spectral to be scored against")
    seconds = dict(seconds or {})
    inner = (slice(border_px, -border_px or None), slice(border_px, -border_px or None))
    raw_n = raw / scale
    scores: dict[str, Score] = {}
    for name in [*images, *(n for n in spectral if n not in images)]:
        image = _checked(images[name], raw.shape, name) / scale if name in images else None
        residual = colour = spectral_score = None
        if image is not None and (boxes is not None or labels is not None):
            residual = residual_aberration(image, raw_n, cfa=cfa, boxes=boxes, labels=labels)
        if image is not None and truth_colour is not None:
            truth = _normalised(_checked(truth_colour, raw.shape, "truth_colour"))[inner]
            colour = colour_errors(truth, image[inner], ssim=True, register=True)
        if name in spectral:
            cube, wavelengths = spectral[name]
            cube = _checked(cube, raw.shape, name, channels=None)[inner]
            truth = _checked(truth_spectral(np.asarray(wavelengths)), raw.shape, "truth_spectral",
                             channels=cube.shape[-1])  # fmt: skip
            truth = _normalised(truth)[inner]
            spectral_score = spectral_errors(truth, cube, ssim=True, register=True)
        scores[name] = Score(name, seconds.get(name), residual, colour, spectral_score)
    notes = [
        "Errors are fractions of the raw image's mean; against a truth, of the truth's mean, "
        f"after registering each channel/band, leaving out a {border_px}-px border.",
    ]
    return Evaluation(scores, scale, notes)


def _checked(
    image: np.ndarray, shape: tuple[int, ...], name: str, *, channels: int | None = 3
) -> np.ndarray:
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 3 or image.shape[:2] != shape or (channels and image.shape[2] != channels):
        want = f"{shape[0]}×{shape[1]}×{channels or 'n'}"
        raise DataError(f"{name}: expected an image of {want}, got shape {image.shape}")
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad:
        raise DataError(f"{name}: {bad} NaN/Inf values; cannot evaluate it")
    return image


def _normalised(truth: np.ndarray) -> np.ndarray:
    mean = float(truth.mean())
    if not mean > 0:
        raise DataError("the truth has no signal (mean ≤ 0); cannot compare with it")
    return truth / mean


def _triples(errors: tuple[ColourErrors, ...] | None, count: int) -> list[str]:
    if errors is None:
        return ["—"] * count
    return ["/".join(f"{v:.4f}" for v in e.rmse) for e in errors]
