"""Where a dispersion model is backed by data, and what happens outside it.

A model is fitted to keypoints: positions in the image and, for a spectral model, the
effective wavelengths of the bands they were found in. :class:`CalibratedRegion` records
that domain — the keypoints' convex hull, how far apart they lie, and the wavelength
range. A polynomial's tail beyond its data is not evidence: a degree-4 fit in λ over
450–687 nm can double the 450 nm shift by 400 nm. So a model used for correction is
evaluated **inside** its domain only (:meth:`CalibratedRegion.clamp`):

* a wavelength outside the calibrated range is moved to the range's nearest end;
* a position farther from the hull than one keypoint spacing is moved to that distance
  (a smooth field is trusted over one sampling interval beyond its last sample, as any
  interpolation is; beyond it, not).

:func:`domain_use` says, for one use of a model (an image size and the wavelengths it is
evaluated at), what lies outside and what the policy does there; commands put its
:meth:`DomainUse.message` in their output and log, and ``refuse`` turns it into an error.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from calibration._model_files import float_array
from labkit.errors import ConfigError, DataError

#: What a use of a model does outside its domain: move inputs to its edge, stop with an
#: error, or evaluate the fitted function there all the same (said in the output).
Extrapolation = Literal["clamp", "refuse", "allow"]
EXTRAPOLATIONS: tuple[str, ...] = ("clamp", "refuse", "allow")

#: Wavelengths within this of the calibrated range count as inside it, nm (effective
#: wavelengths are printed to 0.1 nm; a band set typed from them must not trip it).
WAVELENGTH_SLACK_NM = 0.5

#: Points projected per chunk by :meth:`CalibratedRegion.clamp` (bounds memory).
_CHUNK = 1 << 16


@dataclass(frozen=True)
class CalibratedRegion:
    """Where a model is backed by keypoints: their convex hull, spacing and wavelength range.

    Attributes
    ----------
    hull_xy : ndarray (k, 2)
        Convex hull vertices (x, y) of the model's input positions, counter-clockwise, px.
    wavelength_nm : (min, max) or None
        Band wavelengths covered (spectral models), nm.
    spacing_px : float or None
        Typical distance between neighbouring keypoints of one band, px (the median
        distance of a keypoint to its nearest neighbour). Positions up to this far outside
        the hull are inside the domain. None (fewer than two keypoints, or model files
        written before it was recorded): the hull alone.
    """

    hull_xy: np.ndarray
    wavelength_nm: tuple[float, float] | None = None
    spacing_px: float | None = None

    @classmethod
    def from_points(
        cls, x: np.ndarray, y: np.ndarray, wavelength_nm: np.ndarray | None = None
    ) -> CalibratedRegion:
        """The region spanned by keypoint positions (and wavelengths, one per point or
        just the range)."""
        points = np.column_stack([np.ravel(x), np.ravel(y)]).astype(np.float64)
        hull = _convex_hull(points)
        span = None
        band = points
        if wavelength_nm is not None and np.size(wavelength_nm):
            waves = np.ravel(wavelength_nm)
            span = (float(np.min(waves)), float(np.max(waves)))
            if waves.size == len(points):
                values, counts = np.unique(waves, return_counts=True)
                band = points[waves == values[np.argmax(counts)]]
        return cls(hull, span, _spacing(band))

    @property
    def margin_px(self) -> float:
        """How far outside the hull positions still count as inside the domain, px."""
        return 0.0 if self.spacing_px is None else float(self.spacing_px)

    def contains(
        self, x: np.ndarray, y: np.ndarray, wavelength_nm: np.ndarray | float | None = None
    ) -> np.ndarray:
        """Boolean mask: positions inside the hull (and wavelengths inside the range)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        inside = np.ones(np.broadcast_shapes(x.shape, y.shape), dtype=bool)
        hull = self.hull_xy
        if len(hull) >= 3:
            for (x0, y0), (x1, y1) in zip(hull, np.roll(hull, -1, axis=0), strict=True):
                inside &= (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) >= -1e-9
        if wavelength_nm is not None and self.wavelength_nm is not None:
            lo, hi = self.wavelength_nm
            w = np.asarray(wavelength_nm, dtype=np.float64)
            inside = inside & (w >= lo - 1e-9) & (w <= hi + 1e-9)
        return inside

    def distance_outside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance (px) of each position from the hull; 0 inside it."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        out = np.zeros(x.shape)
        outside = ~self.contains(x, y)
        if outside.any():
            points = np.column_stack([x[outside], y[outside]])
            nearest = self._nearest_on_hull(points)
            out[outside] = np.hypot(*(points - nearest).T)
        return out

    def clamp(
        self,
        x: np.ndarray,
        y: np.ndarray,
        wavelength_nm: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Inputs moved into the domain (see the module notes); same shapes, float64."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        x, y = x.copy(), y.copy()
        if x.size > 4 and self._box_inside(x, y):
            outside = np.zeros(x.shape, dtype=bool)  # the hull is convex: nothing to move
        else:
            outside = ~self.contains(x, y)
        if outside.any() and len(self.hull_xy) >= 1:
            points = np.column_stack([x[outside], y[outside]])
            nearest = self._nearest_on_hull(points)
            away = points - nearest
            distance = np.hypot(*away.T)
            # beyond the margin: moved back to it, along the way to the hull
            scale = np.minimum(1.0, self.margin_px / np.maximum(distance, 1e-300))
            moved = nearest + away * scale[:, None]
            x[outside], y[outside] = moved[:, 0], moved[:, 1]
        if wavelength_nm is not None and self.wavelength_nm is not None:
            wavelength_nm = np.clip(np.asarray(wavelength_nm, np.float64), *self.wavelength_nm)
        return x, y, wavelength_nm

    def _box_inside(self, x: np.ndarray, y: np.ndarray) -> bool:
        """Whether the bounding box of the positions lies inside the (convex) hull."""
        if len(self.hull_xy) < 3:
            return False
        (x0, x1), (y0, y1) = (float(x.min()), float(x.max())), (float(y.min()), float(y.max()))
        return bool(np.all(self.contains(np.array([x0, x1, x0, x1]), np.array([y0, y0, y1, y1]))))

    def _nearest_on_hull(self, points: np.ndarray) -> np.ndarray:
        """The hull's nearest point to each of `points` (n, 2), px."""
        hull = self.hull_xy
        if len(hull) == 1:
            return np.broadcast_to(hull[0], points.shape).copy()
        starts = hull
        ends = np.roll(hull, -1, axis=0)
        if len(hull) == 2:  # a segment, not a closed polygon
            starts, ends = hull[:1], hull[1:]
        edge = ends - starts  # (k, 2)
        length2 = np.maximum(np.sum(edge * edge, axis=1), 1e-300)
        out = np.empty_like(points)
        for start in range(0, len(points), _CHUNK):
            p = points[start : start + _CHUNK, None, :]  # (m, 1, 2)
            t = np.clip(np.sum((p - starts) * edge, axis=2) / length2, 0.0, 1.0)  # (m, k)
            foot = starts + t[..., None] * edge  # (m, k, 2)
            best = np.argmin(np.sum((p - foot) ** 2, axis=2), axis=1)
            out[start : start + _CHUNK] = foot[np.arange(len(best)), best]
        return out

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"hull_xy": self.hull_xy.tolist()}
        if self.wavelength_nm is not None:
            out["wavelength_nm"] = list(self.wavelength_nm)
        if self.spacing_px is not None:
            out["spacing_px"] = float(self.spacing_px)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str) -> CalibratedRegion:
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where} must be a mapping with hull_xy")
        hull = float_array(data.get("hull_xy"), f"{where}.hull_xy")
        if hull.ndim != 2 or hull.shape[1] != 2:
            raise ConfigError(f"{where}.hull_xy must be a list of [x, y] pairs")
        span = data.get("wavelength_nm")
        if span is not None:
            span_arr = float_array(span, f"{where}.wavelength_nm")
            if span_arr.shape != (2,) or span_arr[0] > span_arr[1]:
                raise ConfigError(f"{where}.wavelength_nm must be [min, max]")
            span = (float(span_arr[0]), float(span_arr[1]))
        spacing = data.get("spacing_px")
        if spacing is not None:
            value = float_array([spacing], f"{where}.spacing_px")[0]
            if value < 0:
                raise ConfigError(f"{where}.spacing_px must be ≥ 0 px, got {value:g}")
            spacing = float(value)
        return cls(hull, span, spacing)


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (Andrew's monotone chain) of (n, 2) points."""
    unique = np.unique(points, axis=0)
    if len(unique) < 3:
        return unique

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def chain(pts: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for p in pts:
            while len(out) >= 2 and cross(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = chain(unique), chain(unique[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _spacing(points: np.ndarray) -> float | None:
    """Median distance from each of `points` (n, 2) to its nearest neighbour, px."""
    unique = np.unique(points, axis=0)
    if len(unique) < 2:
        return None
    distance, _ = cKDTree(unique).query(unique, k=2)
    return float(np.median(distance[:, 1]))


#: Below this, a difference in displacement does not matter, px (the reconstruction drops
#: Φ of patches that shift less, :class:`reconstruction.solve.patches.PatchOptions`).
NEGLIGIBLE_PX = 0.05


@dataclass(frozen=True)
class DomainUse:
    """What one use of a model asks of it beyond its domain (:func:`domain_use`).

    Attributes
    ----------
    policy : {"clamp", "refuse", "allow"}
    wavelength_nm : (min, max) or None
        The calibrated range, nm.
    requested_nm : list of float
        Wavelengths the use evaluates the model at (the band set, or the ends of a
        sampled range), nm.
    outside_nm : list of float
        Those of `requested_nm` outside the calibrated range (beyond the slack), nm.
    area_outside : float
        Fraction of the image farther than the margin from the keypoints' hull.
    max_outside_px : float
        Largest distance of an image pixel from the hull, px.
    margin_px : float
        Distance from the hull still inside the domain, px.
    spectral_effect_px, spatial_effect_px : float
        Largest difference between the fitted function and its clamped value over the
        image: at the wavelengths outside the range, and at the positions beyond the
        margin, px. How much the result depends on a choice the data cannot make.
    validated : list of dict
        For each end of the calibrated range that a requested wavelength lies beyond, the
        model's own record of its error one band step beyond its data (``band_nm``,
        ``from_nm``, ``step_nm``, ``rms_px``; :func:`calibration.fit_polynomial_model`),
        when the model has one.
    """

    policy: str
    wavelength_nm: tuple[float, float] | None
    requested_nm: list[float]
    outside_nm: list[float]
    area_outside: float
    max_outside_px: float
    margin_px: float
    spectral_effect_px: float = 0.0
    spatial_effect_px: float = 0.0
    validated: list[dict[str, Any]] = field(default_factory=list)

    @property
    def outside(self) -> bool:
        """Does this use reach beyond the domain where it matters? Every wavelength outside
        the range does; positions beyond the margin do when clamping them changes the
        displacement by :data:`NEGLIGIBLE_PX` or more."""
        return bool(self.outside_nm) or (
            self.area_outside > 0 and self.spatial_effect_px >= NEGLIGIBLE_PX
        )

    def message(self, *, what: str = "the dispersion model") -> str | None:
        """One sentence for output and log (None when :attr:`outside` is false)."""
        if not self.outside:
            return None
        clamp = self.policy == "clamp"
        parts = []
        if self.outside_nm:
            lo, hi = self.wavelength_nm
            listed = ", ".join(
                f"{w:.1f} → {min(max(w, lo), hi):.1f}" if clamp else f"{w:.1f}"
                for w in self.outside_nm
            )
            parts.append(
                f"wavelengths {listed} nm (calibrated {lo:.1f}–{hi:.1f} nm; the fitted "
                f"function differs by up to {self.spectral_effect_px:.2f} px there"
                + _validated_text(self.validated)
                + ")"
            )
        if self.area_outside > 0 and self.spatial_effect_px >= NEGLIGIBLE_PX:
            parts.append(
                f"{100 * self.area_outside:.1f} % of the image lies more than "
                f"{self.margin_px:.0f} px (one keypoint spacing) from the keypoints, up to "
                f"{self.max_outside_px:.0f} px"
                + (", and takes the displacement there" if clamp else "")
                + f" (the fitted function differs by up to {self.spatial_effect_px:.2f} px)"
            )
        action = {"clamp": "clamped", "refuse": "refused", "allow": "extrapolated"}[self.policy]
        return f"{what} is used outside the domain it was calibrated on ({action}): " + "; ".join(
            parts
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "policy": self.policy,
            "calibrated_nm": None if self.wavelength_nm is None else list(self.wavelength_nm),
            "requested_nm": [float(w) for w in self.requested_nm],
            "outside_nm": [float(w) for w in self.outside_nm],
            "area_outside": float(self.area_outside),
            "max_outside_px": float(self.max_outside_px),
            "margin_px": float(self.margin_px),
            "spectral_effect_px": float(self.spectral_effect_px),
            "spatial_effect_px": float(self.spatial_effect_px),
            "validated": [dict(v) for v in self.validated],
        }


def _validated_text(records: Sequence[Mapping[str, Any]]) -> str:
    steps = [
        f"{r['from_nm']:.1f} → {r['band_nm']:.1f} nm {r['rms_px']:.2f} px RMS"
        for r in records
        if isinstance(r.get("rms_px"), (int, float))
    ]
    if not steps:
        return ""
    return "; calibration measured its error extrapolating one band step: " + ", ".join(steps)


def domain_use(
    model: Any,
    *,
    shape: tuple[int, int] | None = None,
    wavelengths_nm: Sequence[float] | np.ndarray | None = None,
    policy: str = "clamp",
    fix: str = "extrapolation='clamp'",
) -> DomainUse:
    """How far a use of `model` reaches beyond its domain, and how much that matters.

    Parameters
    ----------
    model : calibration.DispersionModel
        (typed ``Any`` here: the model module imports this one)
    shape : (rows, cols), optional
        Image evaluated, px (default: the model's image).
    wavelengths_nm : sequence of float, optional
        Wavelengths the use evaluates the model at, nm (spectral models).
    policy : {"clamp", "refuse", "allow"}
    fix : str
        How the caller spells clamping, for the refusal's message.

    Raises
    ------
    DataError
        `policy` is ``"refuse"`` and the use reaches beyond the domain (the message says
        where, and the fixes).
    """
    check_extrapolation(policy)
    region = model.region
    fitted, clamped = model.within_domain("allow"), model.within_domain("clamp")
    rows, cols = (int(v) for v in (shape or model.image_shape))
    # pixel centres of a coarse grid (the area), and the corners: the distance from a convex
    # hull is convex, so its largest value over the image is at a corner
    step = max(1, min(rows, cols) // 128)
    gx, gy = (
        v.ravel()
        for v in np.meshgrid(np.arange(step / 2, cols, step), np.arange(step / 2, rows, step))
    )
    beyond = region.distance_outside(gx, gy) > region.margin_px + 1e-9
    cx, cy = (
        np.array([0.0, cols - 1.0, 0.0, cols - 1.0]),
        np.array([0.0, 0.0, rows - 1.0, rows - 1.0]),
    )
    corners = region.distance_outside(cx, cy)
    far = corners > region.margin_px + 1e-9
    gx, gy = np.append(gx, cx[far]), np.append(gy, cy[far])
    beyond = np.append(beyond, far[far])
    requested = [] if wavelengths_nm is None else [float(w) for w in np.ravel(wavelengths_nm)]
    outside_nm: list[float] = []
    if region.wavelength_nm is not None:
        lo, hi = region.wavelength_nm
        outside_nm = [
            w for w in requested if w < lo - WAVELENGTH_SLACK_NM or w > hi + WAVELENGTH_SLACK_NM
        ]

    def effect(x: np.ndarray, y: np.ndarray, waves: list[float]) -> float:
        """Largest |fitted − clamped| displacement at positions × wavelengths, px."""
        if x.size == 0 or (model.variables == "xylambda" and not waves):
            return 0.0
        if model.variables == "xylambda":
            args = (x[:, None], y[:, None], np.array(waves)[None, :])
            pairs = [(fitted.displacement(*args), clamped.displacement(*args))]
        else:
            pairs = [
                (fitted.displacement(x, y, channel=c), clamped.displacement(x, y, channel=c))
                for c in model.channels
            ]
        return max(float(np.max(np.hypot(a[0] - b[0], a[1] - b[1]))) for a, b in pairs)

    spectral = effect(gx[~beyond], gy[~beyond], outside_nm)
    in_range = [min(max(w, lo), hi) for w in requested] if region.wavelength_nm else requested
    if model.variables == "xylambda" and not in_range and region.wavelength_nm is not None:
        in_range = list(region.wavelength_nm)
    spatial = effect(gx[beyond], gy[beyond], in_range)
    validated = []
    if outside_nm:
        lo, hi = region.wavelength_nm
        records = model.selection.get("extrapolation") or []
        ends = (min(outside_nm) < lo, max(outside_nm) > hi)
        for record, beyond_end in zip(records, ends, strict=False):
            if beyond_end and isinstance(record, Mapping):
                validated.append(dict(record))
    use = DomainUse(
        policy,
        region.wavelength_nm,
        requested,
        outside_nm,
        float(np.mean(beyond[: beyond.size - int(far.sum())])),
        float(corners.max()),
        region.margin_px,
        spectral,
        spatial,
        validated,
    )
    if policy == "refuse" and use.outside:
        raise DataError(
            f"{use.message()}. Give a model calibrated over these bands and this image "
            f"(e.g. a disk chart that fills the frame, under every filter), or clamp it to "
            f"its domain with {fix}"
        )
    return use


def check_extrapolation(policy: str) -> str:
    """`policy` if it is one of :data:`EXTRAPOLATIONS`, else a DataError."""
    if policy not in EXTRAPOLATIONS:
        raise DataError(
            f"unknown extrapolation {policy!r}; use {', '.join(repr(p) for p in EXTRAPOLATIONS)}"
        )
    return policy
