"""Relative sensitivity of the colour channels per filter band (thesis §4.2.4, Algorithm 12).

Under narrowband light of band b every channel sees the same scene radiance, so in
textureless regions neighbouring pixels of different colours are proportional:
``R ≈ r_b G`` and ``B ≈ b_b G``. Algorithm 12 estimates ``r_b = R/G`` and ``b_b = B/G``
from HDR images (values: fraction of saturation):

1. per CFA colour plane (the four stride-2 sub-images, so no gradient crosses channels),
   keep pixels whose gradient magnitude is at most the plane's median (a quantile, by
   default 0.5);
2. keep values strictly between 0 and `saturation` (0.95 of saturation);
3. pair every Green pixel with its 4-neighbour Red pixels, and separately its 4-neighbour
   Blue pixels, keeping a pair only if both members passed; pool the pairs of every
   image (scene) of the band;
4. fit the line through the origin along the first principal component of the
   (G, R) and (G, B) point clouds (:func:`labkit.fitting.principal_slope`).

**Signal test.** A band can be dark in one channel (e.g. Red at 400 nm on most sensors):
its ratio is then noise. A channel *has signal* in a band when the median of its kept
pixels is at least `min_signal_ratio` (default 1 %) of the median of the kept Green
pixels; Green has signal when its median is at least `min_signal_ratio` of the brighter
of the Red and Blue medians. A ratio whose channel (or Green) lacks signal, or that rests
on fewer than `min_pairs` pairs, is reported with ``reliable = False`` and a reason; when
nothing can be fitted it is NaN, again with ``reliable = False`` — never a silent NaN.

:func:`nominal_channel_sensitivity` gives the ratios a rig's camera response predicts,
``∫ q_c T L dλ / ∫ q_G T L dλ`` (thesis Figure 4.12, dotted lines); for the simulated rig
they are the ground truth for a spectrally flat scene.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration._hdr_inputs import source_of
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import channel_index
from labkit.errors import ConfigError, DataError
from labkit.fitting import principal_slope
from labkit.io.atomic import write_text_atomic
from labkit.io.exr import RawImage
from labkit.io.plain import to_plain
from labkit.spectra import (
    Spectra,
    camera_response,
    illuminant,
    trapezoid_weights,
    wavelength_grid,
)

FORMAT_VERSION = 1

#: Columns of the CSV form, in order (also the keys of each YAML band entry).
COLUMNS = (
    "wavelength_nm",
    "illumination",
    "r_over_g",
    "b_over_g",
    "green_level",
    "pairs_r",
    "pairs_b",
    "residual_r",
    "residual_b",
    "reliable_r",
    "reliable_b",
    "reason_r",
    "reason_b",
)
_REQUIRED = ("wavelength_nm", "r_over_g", "b_over_g")

#: Two bands closer than this are the same band, nm.
BAND_TOLERANCE_NM = 0.05

_RED, _GREEN, _BLUE = 0, 1, 2
_NAMES = {_RED: "red", _BLUE: "blue"}


@dataclass
class ChannelSensitivity:
    """Red/Green and Blue/Green sensitivity ratios per filter band.

    Attributes
    ----------
    wavelengths_nm : ndarray (n,) float64
        Band centre wavelengths, nm, increasing.
    illuminations : tuple of str
        Illumination (slider position) names of the bands.
    r_over_g, b_over_g : ndarray (n,) float64
        Ratios R/G and B/G (dimensionless); NaN only where the matching
        ``reliable_*`` flag is False.
    pairs_r, pairs_b : ndarray (n,) int64
        Green–Red and Green–Blue pixel pairs used (0 for predicted ratios).
    residual_r, residual_b : ndarray (n,) float64
        RMS distance of the normalised pairs from the fitted line
        (:class:`~labkit.fitting.SlopeFit` ``residual_rms``); NaN when unknown.
    reliable_r, reliable_b : ndarray (n,) bool
        Whether each ratio passed the pair-count and signal tests.
    reason_r, reason_b : tuple of str
        Why a ratio is unreliable ("" when it is reliable).
    green_level : ndarray (n,) float64
        Green signal of each band: the mean Green value of its images per second of
        exposure (fraction of saturation per s) for a measured table, the predicted Green
        integral (relative units) for a nominal one; NaN where unknown. Only the ratios
        between bands matter: they put the bands of a reconstruction on the scale of the
        light the camera saw (:meth:`as_response`).
    source : str
        ``"measured"``, ``"nominal"`` or the file the table was read from.
    labkit : dict
        Provenance (method, options, input files, rig).
    """

    wavelengths_nm: np.ndarray
    illuminations: tuple[str, ...]
    r_over_g: np.ndarray
    b_over_g: np.ndarray
    pairs_r: np.ndarray
    pairs_b: np.ndarray
    residual_r: np.ndarray
    residual_b: np.ndarray
    reliable_r: np.ndarray
    reliable_b: np.ndarray
    reason_r: tuple[str, ...]
    reason_b: tuple[str, ...]
    green_level: np.ndarray | None = None
    source: str = "measured"
    labkit: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.wavelengths_nm = np.asarray(self.wavelengths_nm, dtype=np.float64).ravel()
        n = self.wavelengths_nm.size
        if self.green_level is None:
            self.green_level = np.full(n, np.nan)
        for name in ("r_over_g", "b_over_g", "green_level", "residual_r", "residual_b"):
            setattr(self, name, _column(getattr(self, name), np.float64, n, name))
        for name in ("pairs_r", "pairs_b"):
            setattr(self, name, _column(getattr(self, name), np.int64, n, name))
        for name in ("reliable_r", "reliable_b"):
            setattr(self, name, _column(getattr(self, name), np.bool_, n, name))
        for name in ("illuminations", "reason_r", "reason_b"):
            values = tuple(str(v) for v in getattr(self, name))
            if len(values) != n:
                raise DataError(f"ChannelSensitivity: {name} has {len(values)} entries, not {n}")
            setattr(self, name, values)
        if np.any(np.diff(self.wavelengths_nm) <= BAND_TOLERANCE_NM):
            raise DataError(
                f"ChannelSensitivity: band wavelengths must increase by more than "
                f"{BAND_TOLERANCE_NM} nm, got {self.wavelengths_nm.tolist()}"
            )
        for channel in ("r", "b"):
            ratios = getattr(self, f"{channel}_over_g")
            reliable = getattr(self, f"reliable_{channel}")
            silent = ~np.isfinite(ratios) & reliable
            if silent.any():
                raise DataError(
                    f"ChannelSensitivity: {channel}_over_g is missing at "
                    f"{self.wavelengths_nm[silent].tolist()} nm but marked reliable"
                )

    def __len__(self) -> int:
        return int(self.wavelengths_nm.size)

    @property
    def reliable(self) -> np.ndarray:
        """(n,) bool: both ratios of the band are reliable."""
        return self.reliable_r & self.reliable_b

    def index_of(self, wavelength_nm: float) -> int | None:
        """Index of the band centred at `wavelength_nm` (± 0.05 nm), or None."""
        if len(self) == 0:
            return None
        distance = np.abs(self.wavelengths_nm - float(wavelength_nm))
        best = int(np.argmin(distance))
        return best if distance[best] <= BAND_TOLERANCE_NM else None

    def rows(self) -> list[dict[str, Any]]:
        """One dict per band with the keys of :data:`COLUMNS` (NaN → None)."""
        return [
            {
                "wavelength_nm": float(self.wavelengths_nm[i]),
                "illumination": self.illuminations[i],
                "r_over_g": _finite_or_none(self.r_over_g[i]),
                "b_over_g": _finite_or_none(self.b_over_g[i]),
                "green_level": _finite_or_none(self.green_level[i]),
                "pairs_r": int(self.pairs_r[i]),
                "pairs_b": int(self.pairs_b[i]),
                "residual_r": _finite_or_none(self.residual_r[i]),
                "residual_b": _finite_or_none(self.residual_b[i]),
                "reliable_r": bool(self.reliable_r[i]),
                "reliable_b": bool(self.reliable_b[i]),
                "reason_r": self.reason_r[i],
                "reason_b": self.reason_b[i],
            }
            for i in range(len(self))
        ]

    def to_csv(self, path: str | Path) -> None:
        """Write the table as CSV (header :data:`COLUMNS`; empty cell = not available)."""
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in self.rows():
            writer.writerow({key: _cell(value) for key, value in row.items()})
        write_text_atomic(path, buffer.getvalue())

    def to_yaml(self, path: str | Path) -> None:
        """Write the table with its provenance as YAML (``format``, ``bands``, ``labkit``)."""
        import yaml

        document = {
            "format": FORMAT_VERSION,
            "kind": "channel_sensitivity",
            "source": self.source,
            "bands": self.rows(),
            "labkit": to_plain(self.labkit),
        }
        write_text_atomic(path, yaml.safe_dump(document, sort_keys=False, allow_unicode=True))

    def as_response(self) -> Spectra:
        """The table as a camera response sampled at its bands (the thesis' sensor map).

        R = r/g · ℓ, G = ℓ, B = b/g · ℓ per band, with ℓ the band's Green level relative to
        the brightest band's (:attr:`green_level`), or ℓ = 1 in every band when the table
        has no levels (the thesis' normalisation, Algorithm 12). With levels, a spectral
        image reconstructed with this response is in units of the light the camera saw in
        each band, so its bands are on comparable scales; without, each band is in units
        of its own Green response, and bands the camera barely sees (e.g. 400 and 700 nm)
        are hundreds of times smaller than the brightest. A reconstruction treats a response
        sampled only at its bands as a discrete model
        (:class:`reconstruction.image_formation.LatentSpace`).

        Raises
        ------
        DataError
            A ratio could not be fitted (NaN), or fewer than two bands.
        """
        for channel in ("r", "b"):
            ratios = getattr(self, f"{channel}_over_g")
            missing = ~np.isfinite(ratios)
            if missing.any():
                band = float(self.wavelengths_nm[missing][0])
                raise DataError(
                    f"sensitivity {self.source}: {channel}_over_g at {band:g} nm is unknown, so "
                    "the table cannot serve as a camera response; calibrate with images that "
                    "have signal in that band or leave the band out of the file"
                )
        level = self.relative_green_level if self.has_levels else np.ones(len(self))
        values = (
            np.column_stack([self.r_over_g, np.ones(len(self)), self.b_over_g]) * level[:, None]
        )
        return Spectra(self.wavelengths_nm, np.maximum(values, 0.0), ("R", "G", "B"))

    @property
    def has_levels(self) -> bool:
        """Whether every band has a positive, finite :attr:`green_level`."""
        return bool(np.all(np.isfinite(self.green_level)) and np.all(self.green_level > 0))

    @property
    def relative_green_level(self) -> np.ndarray:
        """(n,) :attr:`green_level` relative to the brightest band's; NaN without levels."""
        if not self.has_levels:
            return np.full(len(self), np.nan)
        return self.green_level / self.green_level.max()

    @classmethod
    def from_file(cls, path: str | Path) -> ChannelSensitivity:
        """Read a table written by :meth:`to_csv` or :meth:`to_yaml` (or by hand).

        Only ``wavelength_nm``, ``r_over_g`` and ``b_over_g`` are required; missing
        optional columns default to 0 pairs, unknown residuals, reliable, no reason.

        Raises
        ------
        DataError
            Unreadable file, unknown suffix, or an invalid value; the message names the
            file and the column (CSV) or key (YAML).
        """
        path = Path(path)
        if not path.is_file():
            raise DataError(f"sensitivity file {path} does not exist")
        suffix = path.suffix.lower()
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise DataError(f"{path}: cannot read the sensitivity file ({error})") from None
        if suffix == ".csv":
            return _from_csv(path, text)
        if suffix in (".yaml", ".yml"):
            return _from_yaml(path, text)
        raise DataError(
            f"{path}: unknown sensitivity file type {suffix!r}; use .csv or .yaml "
            "(as written by `labkit calibrate sensitivity`)"
        )


# -- Algorithm 12 ---------------------------------------------------------------------------


@fixed_blas_threads
def channel_sensitivity(
    images: Sequence[RawImage],
    *,
    saturation: float = 0.95,
    gradient_quantile: float = 0.5,
    min_pairs: int = 200,
    min_signal_ratio: float = 0.01,
) -> ChannelSensitivity:
    """Calibrate R/G and B/G per filter band from HDR raw images (thesis Algorithm 12).

    Parameters
    ----------
    images : sequence of RawImage
        Filtered-light HDR mosaics (values: fraction of saturation, 1.0 = saturated;
        ``wavelength_nm`` set). Images of the same band (e.g. several scenes) are pooled;
        they may differ in shape, CFA layout and exposure.
    saturation : float
        Pixels at or above this value (fraction of saturation) are discarded.
    gradient_quantile : float
        Keep pixels whose gradient magnitude (per CFA colour plane, in value units per
        2 px) is at most this quantile of their plane's magnitudes (0.5: the median).
    min_pairs : int
        Fewest pixel pairs for a ratio to count as reliable.
    min_signal_ratio : float
        Signal test (see the module notes): a channel whose median kept value is below
        this fraction of Green's (or Green below this fraction of the brighter other
        channel) makes the band's ratio unreliable.

    Returns
    -------
    ChannelSensitivity
        One band per distinct ``wavelength_nm``, sorted by wavelength.

    Raises
    ------
    DataError
        No images, an image without ``wavelength_nm``, an image smaller than 4 × 4 px,
        or an option out of range.
    """
    if not images:
        raise DataError("channel_sensitivity needs at least one filtered HDR image")
    if not 0 < saturation <= 1 or not 0 < gradient_quantile <= 1:
        raise DataError(
            f"channel_sensitivity: need 0 < saturation ≤ 1 and 0 < gradient_quantile ≤ 1, "
            f"got {saturation} and {gradient_quantile}"
        )
    if min_pairs < 2 or not 0 < min_signal_ratio < 1:
        raise DataError(
            f"channel_sensitivity: need min_pairs ≥ 2 and 0 < min_signal_ratio < 1, "
            f"got {min_pairs} and {min_signal_ratio}"
        )
    bands: dict[float, list[RawImage]] = {}
    for image in images:
        if image.wavelength_nm is None:
            raise DataError(
                f"{source_of(image)}: illumination {image.illumination!r} is unfiltered "
                "(no wavelength_nm); channel sensitivity needs bandpass-filtered images"
            )
        if min(image.raw.shape) < 4:
            raise DataError(f"{source_of(image)}: image {image.raw.shape} is smaller than 4 × 4")
        bands.setdefault(round(float(image.wavelength_nm), 1), []).append(image)

    results = [
        _calibrate_band(
            group,
            saturation=saturation,
            gradient_quantile=gradient_quantile,
            min_pairs=min_pairs,
            min_signal_ratio=min_signal_ratio,
        )
        for _, group in sorted(bands.items())
    ]
    scenes = sorted({str(image.labkit["scene"]) for image in images if "scene" in image.labkit})
    return ChannelSensitivity(
        wavelengths_nm=np.array(sorted(bands)),
        illuminations=tuple(r["illumination"] for r in results),
        r_over_g=[r["r"].ratio for r in results],
        b_over_g=[r["b"].ratio for r in results],
        pairs_r=[r["r"].pairs for r in results],
        pairs_b=[r["b"].pairs for r in results],
        residual_r=[r["r"].residual for r in results],
        residual_b=[r["b"].residual for r in results],
        reliable_r=[not r["r"].reasons for r in results],
        reliable_b=[not r["b"].reasons for r in results],
        reason_r=tuple("; ".join(r["r"].reasons) for r in results),
        reason_b=tuple("; ".join(r["b"].reasons) for r in results),
        green_level=[r["green_level"] for r in results],
        source="measured",
        labkit={
            "method": "thesis Algorithm 12 (first principal component of neighbour pairs)",
            "saturation": saturation,
            "gradient_quantile": gradient_quantile,
            "min_pairs": min_pairs,
            "min_signal_ratio": min_signal_ratio,
            "scenes": scenes,
            "sources": [source_of(image) for image in images],
        },
    )


@dataclass
class _RatioFit:
    ratio: float = math.nan
    pairs: int = 0
    residual: float = math.nan
    reasons: list[str] = field(default_factory=list)


def _calibrate_band(
    images: Sequence[RawImage],
    *,
    saturation: float,
    gradient_quantile: float,
    min_pairs: int,
    min_signal_ratio: float,
) -> dict[str, Any]:
    """Pooled pairs and fits of one band."""
    pairs: dict[int, tuple[list[np.ndarray], list[np.ndarray]]] = {
        _RED: ([], []),
        _BLUE: ([], []),
    }
    kept_values: dict[int, list[np.ndarray]] = {_RED: [], _GREEN: [], _BLUE: []}
    for image in images:
        raw = np.asarray(image.raw, dtype=np.float64)
        keep = smooth_unsaturated_mask(
            raw, saturation=saturation, gradient_quantile=gradient_quantile
        )
        index = channel_index(image.cfa, raw.shape)
        for channel, values in kept_values.items():
            values.append(raw[keep & (index == channel)])
        for channel, (greens, others) in pairs.items():
            g, x = neighbour_pairs(raw, keep, index, channel)
            greens.append(g)
            others.append(x)
    medians = {
        channel: float(np.median(np.concatenate(values))) if sum(v.size for v in values) else 0.0
        for channel, values in kept_values.items()
    }
    green = medians[_GREEN]
    brightest_other = max(medians[_RED], medians[_BLUE])
    fits = {}
    for channel, (greens, others) in pairs.items():
        name = _NAMES[channel]
        fit = _RatioFit()
        g = np.concatenate(greens)
        x = np.concatenate(others)
        fit.pairs = int(g.size)
        if fit.pairs >= 2:
            try:
                slope = principal_slope(g, x)
                fit.ratio, fit.residual = slope.slope, slope.residual_rms
            except DataError as error:
                fit.reasons.append(f"no fit ({str(error).removeprefix('principal_slope: ')})")
        if fit.pairs < min_pairs:
            fit.reasons.append(f"only {fit.pairs} green–{name} pairs (need {min_pairs})")
        if green <= 0:
            fit.reasons.append("no green pixel passed the gradient and saturation masks")
        else:
            if medians[channel] < min_signal_ratio * green:
                fit.reasons.append(
                    f"{name} has no signal (median {name}/green {medians[channel] / green:.2g} "
                    f"< {min_signal_ratio:g})"
                )
            if green < min_signal_ratio * brightest_other:
                fit.reasons.append(
                    f"green has no signal (median green/brightest {green / brightest_other:.2g} "
                    f"< {min_signal_ratio:g})"
                )
        fits[channel] = fit
    names = sorted({image.illumination for image in images})
    return {
        "illumination": "+".join(names),
        "r": fits[_RED],
        "b": fits[_BLUE],
        "green_level": green_level(images),
    }


def green_level(images: Sequence[RawImage]) -> float:
    """Mean Green value per second of exposure over images of one band (NaN if unknown).

    Each image contributes the mean of its Green pixels divided by its ``exposure_s``
    (fraction of saturation per s); the images of the band (several scenes) are averaged.
    """
    levels = []
    for image in images:
        if image.exposure_s is None or not image.exposure_s > 0:
            return math.nan
        raw = np.asarray(image.raw, dtype=np.float64)
        green = raw[channel_index(image.cfa, raw.shape) == _GREEN]
        levels.append(float(green.mean()) / float(image.exposure_s))
    return float(np.mean(levels))


def smooth_unsaturated_mask(
    raw: np.ndarray, *, saturation: float = 0.95, gradient_quantile: float = 0.5
) -> np.ndarray:
    """Pixels of a mosaic in textureless, unsaturated regions (Algorithm 12 steps 2–3).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, fraction of saturation; at least 4 × 4.
    saturation : float
        Keep values strictly below this (and strictly above 0).
    gradient_quantile : float
        Keep pixels whose gradient magnitude within their CFA colour plane (the
        stride-2 sub-image of their 2 × 2 phase, central differences) is at most this
        quantile of that plane's magnitudes.

    Returns
    -------
    ndarray (rows, cols) bool
    """
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 2 or min(raw.shape) < 4:
        raise DataError(f"a mosaic of at least 4 × 4 pixels is needed, got shape {raw.shape}")
    keep = np.zeros(raw.shape, dtype=bool)
    for dy in (0, 1):
        for dx in (0, 1):
            plane = raw[dy::2, dx::2]
            gy, gx = np.gradient(plane)
            magnitude = np.hypot(gx, gy)
            keep[dy::2, dx::2] = magnitude <= np.quantile(magnitude, gradient_quantile)
    return keep & (raw > 0) & (raw < saturation)


def neighbour_pairs(
    raw: np.ndarray, keep: np.ndarray, index: np.ndarray, channel: int
) -> tuple[np.ndarray, np.ndarray]:
    """Values of every (Green pixel, 4-neighbour `channel` pixel) pair where both are kept.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Mosaic values.
    keep : ndarray (rows, cols) bool
        Pixels allowed in a pair.
    index : ndarray (rows, cols)
        Channel of each pixel (0 R, 1 G, 2 B; :func:`labkit.cfa.channel_index`).
    channel : int
        0 (Red) or 2 (Blue).

    Returns
    -------
    green, other : ndarray (n,)
        Paired values; each Green pixel appears once per kept neighbour of `channel`
        (two in a Bayer mosaic), each `channel` pixel once per kept Green neighbour.
    """
    greens, others = [], []
    horizontal = (np.s_[:, :-1], np.s_[:, 1:])
    vertical = (np.s_[:-1, :], np.s_[1:, :])
    for first, second in (horizontal, vertical):
        both = keep[first] & keep[second]
        a_raw, b_raw = raw[first], raw[second]
        a_index, b_index = index[first], index[second]
        forward = both & (a_index == _GREEN) & (b_index == channel)
        backward = both & (a_index == channel) & (b_index == _GREEN)
        greens += [a_raw[forward], b_raw[backward]]
        others += [b_raw[forward], a_raw[backward]]
    return np.concatenate(greens), np.concatenate(others)


# -- the rig's prediction -------------------------------------------------------------------


def nominal_channel_sensitivity(
    rig, illuminations: Iterable[str] | None = None
) -> ChannelSensitivity:
    """R/G and B/G that a rig's camera response predicts for its filter bands.

    ``ratio_c = ∫ q_c T L dλ / ∫ q_G T L dλ`` over 380–780 nm (trapezoid rule on a
    1 nm grid, or the simulator's grid if finer), with camera response q (zero outside
    its data), filter transmission T and light source L. For a simulated rig this is
    what a spectrally flat (grey) scene gives.

    Parameters
    ----------
    rig : labkit.rig.Rig
        The rig (camera response, slider filters, light source).
    illuminations : iterable of str, optional
        Filtered illuminations to predict (default: every filtered slider position).

    Returns
    -------
    ChannelSensitivity
        ``source = "nominal"``, 0 pairs, unknown residuals; a band where the Green
        integral vanishes is NaN and unreliable.

    Raises
    ------
    ConfigError
        An illumination is unknown or unfiltered.
    """
    names = list(rig.slider.illumination_names() if illuminations is None else illuminations)
    filters = {}
    for name in names:
        filt = rig.filter_for(name)
        if filt is not None:
            filters[name] = filt
        elif illuminations is not None:
            raise ConfigError(
                f"rig {rig.source or rig.name}: illumination {name!r} has no filter, so it "
                "has no channel sensitivity; name a filtered slider position"
            )
    if not filters:
        raise ConfigError(f"rig {rig.source or rig.name} has no filtered slider position")
    step = 1.0 if rig.sim is None else min(1.0, float(rig.sim.spectral_step_nm))
    w = wavelength_grid(380.0, 780.0, step)
    response = load_response(rig.response_source()).select(["R", "G", "B"])
    q = response.resample(w, extrapolate="zero").values
    light = illuminant(rig.light.source, w).values[:, 0] * trapezoid_weights(w)
    order = sorted(filters, key=lambda name: filters[name].centre_nm)
    totals = np.stack([(q * (light * filters[name].transmission(w))[:, None]).sum(0)
                       for name in order])  # fmt: skip
    green = totals[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        r, b = totals[:, 0] / green, totals[:, 2] / green
    ok = green > 0
    reason = tuple("" if good else "green response is zero in this band" for good in ok)
    n = len(order)
    return ChannelSensitivity(
        wavelengths_nm=[filters[name].centre_nm for name in order],
        illuminations=tuple(order),
        r_over_g=np.where(ok, r, np.nan),
        b_over_g=np.where(ok, b, np.nan),
        pairs_r=np.zeros(n),
        pairs_b=np.zeros(n),
        residual_r=np.full(n, np.nan),
        residual_b=np.full(n, np.nan),
        reliable_r=ok,
        reliable_b=ok,
        reason_r=reason,
        reason_b=reason,
        green_level=np.where(ok, green, np.nan),
        source="nominal",
        labkit={
            "method": "∫ q_c T L dλ / ∫ q_G T L dλ, trapezoid rule",
            "rig": rig.source or rig.name,
            "response": rig.camera.response,
            "light": rig.light.source,
            "grid_nm": [float(w[0]), float(w[-1]), step],
        },
    )


# -- plot ------------------------------------------------------------------------------------


def plot_channel_sensitivity(
    measured: ChannelSensitivity, nominal: ChannelSensitivity | None, path: str | Path
) -> None:
    """Measured (solid, markers) vs nominal (dotted) R/G and B/G against wavelength.

    The thesis' Figure 4.12. Ratios span decades, so the y axis is logarithmic;
    unreliable measured ratios are drawn as open markers. Written as PNG, atomically.
    """
    import matplotlib.pyplot as plt

    from labkit.plots import save_figure

    figure, axis = plt.subplots(figsize=(7, 4.5))
    for key, colour, label in (("r", "tab:red", "R/G"), ("b", "tab:blue", "B/G")):
        w = measured.wavelengths_nm
        ratio = getattr(measured, f"{key}_over_g")
        reliable = getattr(measured, f"reliable_{key}")
        shown = np.isfinite(ratio) & (ratio > 0)
        axis.plot(w[shown], ratio[shown], "-o", color=colour, label=f"{label} measured",
                  markevery=reliable[shown].tolist())  # fmt: skip
        bad = shown & ~reliable
        if bad.any():
            axis.plot(w[bad], ratio[bad], "o", mfc="none", color=colour,
                      label=f"{label} unreliable")  # fmt: skip
        if nominal is not None:
            ratio = getattr(nominal, f"{key}_over_g")
            shown = np.isfinite(ratio) & (ratio > 0)
            axis.plot(nominal.wavelengths_nm[shown], ratio[shown], ":", color=colour,
                      label=f"{label} nominal")  # fmt: skip
    axis.set_yscale("log")
    axis.set_xlabel("filter centre wavelength (nm)")
    axis.set_ylabel("sensitivity relative to Green")
    axis.set_title("relative channel sensitivity per filter band")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=8)
    save_figure(figure, path)


# -- file parsing ---------------------------------------------------------------------------


def _column(values: Any, dtype: type, n: int, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=dtype).ravel()
    if array.size != n:
        raise DataError(f"ChannelSensitivity: {name} has {array.size} entries, not {n}")
    return array


def _finite_or_none(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _cell(value: Any) -> str:
    """A CSV cell: None → empty, bools lower-case, floats exact (shortest repr)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)


def _from_csv(path: Path, text: str) -> ChannelSensitivity:
    reader = csv.DictReader(io.StringIO(text))
    header = reader.fieldnames or []
    unknown = [name for name in header if name not in COLUMNS]
    if unknown:
        raise DataError(
            f"{path}: column {unknown[0]!r} is not a known column; "
            f"expected columns {', '.join(COLUMNS)}"
        )
    missing = [name for name in _REQUIRED if name not in header]
    if missing:
        raise DataError(
            f"{path}: column {missing[0]!r} is missing; a sensitivity CSV needs at least "
            f"{', '.join(_REQUIRED)}"
        )
    rows = []
    for number, row in enumerate(reader, start=2):
        if None in row:
            raise DataError(f"{path}: line {number} has more cells than the header has columns")
        rows.append((f"line {number}", {k: v for k, v in row.items() if v is not None}))
    return _build(path, rows, lambda where, key: f"{where}, column {key!r}", source=str(path))


def _from_yaml(path: Path, text: str) -> ChannelSensitivity:
    import yaml

    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise DataError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(document, dict):
        raise DataError(f"{path}: a sensitivity YAML file must be a mapping with `bands`")
    if document.get("format", FORMAT_VERSION) != FORMAT_VERSION:
        raise DataError(
            f"{path}: format is {document['format']!r}; this labkit reads format {FORMAT_VERSION}"
        )
    kind = document.get("kind", "channel_sensitivity")
    if kind != "channel_sensitivity":
        raise DataError(f"{path}: kind is {kind!r}; expected 'channel_sensitivity'")
    bands = document.get("bands")
    if not isinstance(bands, list):
        raise DataError(f"{path}: bands is missing or not a list; expected one entry per band")
    rows = []
    for number, band in enumerate(bands):
        if not isinstance(band, dict):
            raise DataError(f"{path}: bands[{number}] must be a mapping of {', '.join(COLUMNS)}")
        unknown = [key for key in band if key not in COLUMNS]
        if unknown:
            raise DataError(
                f"{path}: bands[{number}].{unknown[0]} is not a known key; "
                f"expected keys {', '.join(COLUMNS)}"
            )
        rows.append((f"bands[{number}]", band))
    provenance = document.get("labkit") or {}
    return _build(
        path,
        rows,
        lambda where, key: f"{where}.{key}",
        source=str(document.get("source", path)),
        provenance=provenance if isinstance(provenance, dict) else {},
    )


def _build(
    path: Path,
    rows: list[tuple[str, Mapping[str, Any]]],
    locate: Callable[[str, str], str],
    *,
    source: str,
    provenance: dict[str, Any] | None = None,
) -> ChannelSensitivity:
    if not rows:
        raise DataError(f"{path}: no bands; the file must list at least one band")

    def fail(where: str, key: str, problem: str) -> DataError:
        return DataError(f"{path}: {locate(where, key)} {problem}")

    def number(where: str, row: Mapping[str, Any], key: str, *, required: bool) -> float:
        value = row.get(key)
        if value is None or (isinstance(value, str) and value.strip() == ""):
            if required:
                raise fail(where, key, "is missing; give a number")
            return math.nan
        if isinstance(value, bool):
            raise fail(where, key, f"is {value!r}; expected a number")
        try:
            result = float(value)
        except (TypeError, ValueError):
            raise fail(where, key, f"is {value!r}; expected a number") from None
        if not math.isfinite(result):
            if required:
                raise fail(where, key, f"is {value!r}; expected a finite number")
            return math.nan
        return result

    def flag(where: str, row: Mapping[str, Any], key: str) -> bool:
        value = row.get(key)
        if value is None or value == "":
            return True
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in ("true", "yes", "1"):
            return True
        if text in ("false", "no", "0"):
            return False
        raise fail(where, key, f"is {value!r}; expected true or false")

    columns: dict[str, list[Any]] = {key: [] for key in COLUMNS}
    for where, row in rows:
        wavelength = number(where, row, "wavelength_nm", required=True)
        if not 200 <= wavelength <= 2000:
            raise fail(where, "wavelength_nm", f"is {wavelength:g}; expected 200–2000 nm")
        columns["wavelength_nm"].append(wavelength)
        illumination = row.get("illumination")
        columns["illumination"].append(
            f"{wavelength:g}" if illumination in (None, "") else str(illumination)
        )
        for key in ("pairs_r", "pairs_b"):
            count = number(where, row, key, required=False)
            if math.isnan(count):
                count = 0
            if count < 0 or count != int(count):
                raise fail(where, key, f"is {row.get(key)!r}; expected a whole number ≥ 0")
            columns[key].append(int(count))
        for key in ("residual_r", "residual_b"):
            columns[key].append(number(where, row, key, required=False))
        level = number(where, row, "green_level", required=False)
        if level <= 0:
            raise fail(where, "green_level", f"is {level:g}; a Green level must be positive")
        columns["green_level"].append(level)
        for channel in ("r", "b"):
            reliable = flag(where, row, f"reliable_{channel}")
            key = f"{channel}_over_g"
            ratio = number(where, row, key, required=reliable)
            if ratio < 0:
                raise fail(where, key, f"is {ratio:g}; a sensitivity ratio cannot be negative")
            columns[key].append(ratio)
            columns[f"reliable_{channel}"].append(reliable)
            reason = row.get(f"reason_{channel}")
            columns[f"reason_{channel}"].append("" if reason is None else str(reason))
    order = np.argsort(columns["wavelength_nm"], kind="stable")
    sorted_w = np.asarray(columns["wavelength_nm"])[order]
    close = np.flatnonzero(np.diff(sorted_w) <= BAND_TOLERANCE_NM)
    if close.size:
        duplicate = rows[order[close[0] + 1]][0]
        raise fail(duplicate, "wavelength_nm", f"repeats the band at {sorted_w[close[0]]:g} nm")
    picked = {key: [values[i] for i in order] for key, values in columns.items()}
    return ChannelSensitivity(
        wavelengths_nm=picked["wavelength_nm"],
        illuminations=tuple(picked["illumination"]),
        r_over_g=picked["r_over_g"],
        b_over_g=picked["b_over_g"],
        pairs_r=picked["pairs_r"],
        pairs_b=picked["pairs_b"],
        residual_r=picked["residual_r"],
        residual_b=picked["residual_b"],
        reliable_r=picked["reliable_r"],
        reliable_b=picked["reliable_b"],
        reason_r=tuple(picked["reason_r"]),
        reason_b=tuple(picked["reason_b"]),
        green_level=picked["green_level"],
        source=source,
        labkit={**(provenance or {}), "file": str(path)},
    )


def is_sensitivity_file(source: str | Path) -> bool:
    """Whether `source` names a table written by ``labkit calibrate sensitivity``."""
    path = Path(str(source))
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return True
    if suffix != ".csv" or not path.is_file():
        return False
    with path.open(newline="", encoding="utf-8", errors="replace") as handle:
        header = next(csv.reader(handle), [])
    return "r_over_g" in [cell.strip() for cell in header]


def load_response(source: str | Path) -> Spectra:
    """A camera response from a dataset name, a response CSV, or a measured sensitivity.

    Parameters
    ----------
    source : str or Path
        A colour-science camera dataset name, a CSV ``wavelength_nm,R,G,B``, or the
        ``sensitivity.yaml``/``.csv`` of ``labkit calibrate sensitivity`` (then
        :meth:`ChannelSensitivity.as_response`: sampled at its bands).
    """
    if is_sensitivity_file(source):
        return ChannelSensitivity.from_file(source).as_response()
    return camera_response(source)
