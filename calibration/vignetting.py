"""Vignetting and illumination non-uniformity correction (thesis §3.2.2, (3.2)–(3.4)).

:func:`fit_vignetting` takes a raw (mosaiced) image of a scene that should be uniform
inside a user-marked region, and fits a bivariate polynomial model of intensity in image
(x, y) to the pixels of one colour channel (Green by default) inside the region:

1. coordinates are centred and whitened (zero mean, unit variance along each principal
   direction: the thesis' affine homography T_xy), intensities z-scored (T_I);
2. the model is a polynomial of **total degree** ≤ p in the whitened coordinates. The
   thesis' (3.2) sums aᵢⱼ xⁱ yʲ over i, j ≤ p (a tensor-product degree); we use total
   degree i + j ≤ p, as for the dispersion polynomials: vignetting is close to a
   function of r² = x² + y², which total degree captures with fewer terms. The basis is
   Legendre in the whitened coordinates mapped to [−1, 1] (:mod:`calibration._polybasis`);
   it spans the same polynomials as monomials, better conditioned;
3. p ∈ {0, …, `max_degree`} (thesis: 0…5) is chosen by 10-fold cross-validation with the
   one-standard-error rule of thesis Algorithm 1: the smallest degree whose mean
   validation error is within one sample standard deviation (of the fold errors) of the
   minimum. (The minimum alone tends to pick a spurious higher degree on a flat image.)

The model is stored as a *relative* intensity: :meth:`VignettingModel.image` is the
fitted surface divided by its mean over the fitted pixels, and
:meth:`VignettingModel.correct` divides a raw image by it (thesis (3.4); the same map
for every colour channel), which flattens the image while keeping its overall level.

For speed, at most :data:`MAX_PIXELS` pixels (a seeded random subsample) are fitted.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration import _polybasis as pb
from calibration._model_files import float_array, read_model_document
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS, channel_index, check_layout
from labkit.errors import ConfigError, DataError
from labkit.io.atomic import write_text_atomic
from labkit.io.plain import to_plain

KIND = "labkit.vignetting_model"
FORMAT = 1
#: Largest number of pixels fitted (a random subsample beyond that).
MAX_PIXELS = 200_000
#: Fewest channel pixels inside the mask.
MIN_PIXELS = 100
#: Rows of the image evaluated at a time.
_ROW_CHUNK_PIXELS = 1 << 18


@dataclass(frozen=True, eq=False)
class VignettingModel:
    """A fitted polynomial model of relative intensity over the image.

    Attributes
    ----------
    degree : int
        Total polynomial degree in (x, y).
    xy_offset, xy_matrix : ndarray (2,), (2, 2)
        Whitening of pixel coordinates (x = column, y = row): ``u = M (p − offset)``.
    domain : Domain
        Affine map of whitened coordinates onto [−1, 1] over the fitted pixels.
    intensity_offset, intensity_scale : float
        Mean and standard deviation of the fitted intensities (raw units).
    coefficients : ndarray (m,)
        Legendre coefficients of the normalised intensity, terms in
        :func:`calibration._polybasis.exponent_table` order.
    mean_intensity : float
        Mean of the fitted surface over the fitted pixels, raw units (``image()`` divides
        by it).
    image_shape : (rows, cols)
    cfa : str
        Bayer layout of the image fitted.
    channel : str
        Colour channel whose pixels were fitted.
    selection : dict
        Cross-validation report: errors and standard deviations per degree (squared
        normalised intensity), skipped degrees, condition number, pixel counts.
    name : str
        What was fitted (file name), for messages.
    """

    degree: int
    xy_offset: np.ndarray
    xy_matrix: np.ndarray
    domain: pb.Domain
    intensity_offset: float
    intensity_scale: float
    coefficients: np.ndarray
    mean_intensity: float
    image_shape: tuple[int, int]
    cfa: str
    channel: str = "G"
    selection: dict[str, Any] = field(default_factory=dict)
    name: str = "image"

    def __post_init__(self) -> None:
        m = pb.n_terms_xy(self.degree)
        coef = np.asarray(self.coefficients, dtype=np.float64).ravel()
        if coef.size != m:
            raise DataError(
                f"vignetting model of degree {self.degree} needs {m} coefficients, got {coef.size}"
            )
        object.__setattr__(self, "coefficients", coef)
        object.__setattr__(
            self, "image_shape", (int(self.image_shape[0]), int(self.image_shape[1]))
        )
        object.__setattr__(self, "_image", None)

    @property
    def condition_number(self) -> float:
        """2-norm condition number of the final design matrix."""
        return float(self.selection.get("condition_number", float("nan")))

    def surface(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Fitted intensity (raw units) at pixel positions x (column), y (row); float64."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape)
        xy = np.column_stack([np.broadcast_to(x, shape).ravel(), np.broadcast_to(y, shape).ravel()])
        exps = pb.exponent_table(self.degree)
        out = np.empty(len(xy))
        for start in range(0, len(xy), _ROW_CHUNK_PIXELS):
            u = (xy[start : start + _ROW_CHUNK_PIXELS] - self.xy_offset) @ self.xy_matrix.T
            out[start : start + _ROW_CHUNK_PIXELS] = (
                pb.design_matrix(self.domain(u), exps) @ self.coefficients
            )
        return (out * self.intensity_scale + self.intensity_offset).reshape(shape)

    def image(self) -> np.ndarray:
        """Relative intensity (rows, cols) float32, mean 1 over the fitted pixels (cached).

        The whitened coordinates are affine in (column, row), so the model is also a
        polynomial of the same total degree in the image's own coordinates scaled to
        [−1, 1]. Its coefficients there are found by least squares from the model at a
        few hundred points (exact: the two bases span the same space), after which the
        image is one separable product ``P(rows)ᵀ D P(cols)``.
        """
        cached = self._image  # type: ignore[attr-defined]
        if cached is None:
            cached = self._grid_image()
            if cached is None:  # not representable to rounding: evaluate every pixel
                cached = np.empty(self.image_shape, dtype=np.float32)
                rows, cols = self.image_shape
                step = max(1, _ROW_CHUNK_PIXELS // cols)
                x = np.arange(cols, dtype=np.float64)[None, :]
                for r0 in range(0, rows, step):
                    y = np.arange(r0, min(rows, r0 + step), dtype=np.float64)[:, None]
                    cached[r0 : r0 + step] = self.surface(x, y) / self.mean_intensity
            cached.flags.writeable = False
            object.__setattr__(self, "_image", cached)
        return cached

    def _grid_image(self) -> np.ndarray | None:
        """:meth:`image` by the separable re-expansion (None if it does not reproduce)."""
        rows, cols = self.image_shape
        exps = pb.exponent_table(self.degree)
        centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
        half = np.maximum(centre, 0.5)
        k = self.degree + 4
        grid = np.cos(np.pi * (np.arange(k) + 0.5) / k)  # Chebyshev nodes in (−1, 1)
        gx, gy = np.meshgrid(grid, grid)
        nodes = np.column_stack([np.concatenate([gx.ravel(), [-1, 1, -1, 1]]),
                                 np.concatenate([gy.ravel(), [-1, -1, 1, 1]])])  # fmt: skip
        pixels = nodes * half + centre
        values = self.surface(pixels[:, 0], pixels[:, 1]) / self.mean_intensity
        design = pb.design_matrix(nodes, exps)
        coef, *_ = np.linalg.lstsq(design, values, rcond=None)
        scale = float(np.abs(values).max())
        if not np.abs(design @ coef - values).max() <= 1e-9 * max(scale, 1e-300):
            return None
        table = np.zeros((self.degree + 1, self.degree + 1))
        table[exps[:, 1], exps[:, 0]] = coef  # [row degree, column degree]
        p_cols = pb.legendre_table((np.arange(cols) - centre[0]) / half[0], self.degree)
        p_rows = pb.legendre_table((np.arange(rows) - centre[1]) / half[1], self.degree)
        return (p_rows.T @ (table @ p_cols)).astype(np.float32)

    def correct(self, raw: np.ndarray) -> np.ndarray:
        """`raw` divided by :meth:`image` (thesis (3.4)); the same map for every channel.

        `raw` is a (rows, cols) mosaic or a (rows, cols, k) image of this model's size.
        Returns float32 for integer or float32 input, else the input's float type.
        """
        raw = np.asarray(raw)
        if raw.shape[:2] != self.image_shape or raw.ndim not in (2, 3):
            raise DataError(
                f"vignetting correction: image of shape {raw.shape} does not match the model's "
                f"{self.image_shape} (fitted to {self.name})"
            )
        dtype = np.result_type(raw.dtype, np.float32) if raw.dtype.kind in "biuf" else np.float64
        model = self.image()
        if raw.ndim == 3:
            model = model[..., None]
        return (raw / model).astype(dtype, copy=False)

    # -- files ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "kind": KIND,
            "image": self.name,
            "image_shape": list(self.image_shape),
            "cfa": self.cfa,
            "channel": self.channel,
            "basis": "legendre",
            "degree": int(self.degree),
            "xy": {"offset": self.xy_offset.tolist(), "matrix": self.xy_matrix.tolist()},
            "domain": self.domain.to_dict(),
            "intensity": {
                "offset": float(self.intensity_offset),
                "scale": float(self.intensity_scale),
            },
            "mean_intensity": float(self.mean_intensity),
            "coefficients": self.coefficients.tolist(),
            "selection": to_plain(self.selection),
        }

    def save(self, path: str | Path) -> Path:
        """Write the model as YAML (kind labkit.vignetting_model, format 1), atomically."""
        write_text_atomic(path, yaml.safe_dump(self.to_dict(), sort_keys=False, width=120))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> VignettingModel:
        """Read :meth:`save`'s file; ConfigError naming the file and key of any problem."""
        data = read_model_document(
            path,
            what="vignetting model",
            missing_fix="fit one with `labkit calibrate vignetting`",
            writer="labkit calibrate vignetting",
        )
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: Any, *, source: str = "<vignetting model>") -> VignettingModel:
        """Validate and build a model from its YAML document; errors name `source` and key."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: a vignetting model file must be a YAML mapping")
        if data.get("kind") != KIND:
            raise ConfigError(f"{source}: `kind` is {data.get('kind')!r}, expected {KIND!r}")
        if data.get("format") != FORMAT:
            raise ConfigError(
                f"{source}: `format` {data.get('format')!r} is not supported (expected {FORMAT})"
            )
        for key in (
            "image_shape", "cfa", "channel", "basis", "degree", "xy", "domain", "intensity",
            "mean_intensity", "coefficients",
        ):  # fmt: skip
            if key not in data:
                raise ConfigError(f"{source}: missing key `{key}`")
        shape = data["image_shape"]
        if (
            not isinstance(shape, list)
            or len(shape) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in shape)
        ):
            raise ConfigError(f"{source}: image_shape must be [rows, cols], got {shape!r}")
        try:
            cfa = check_layout(data["cfa"])
        except DataError as exc:
            raise ConfigError(f"{source}: cfa: {exc}") from None
        if data["channel"] not in CHANNELS:
            raise ConfigError(f"{source}: channel must be one of R, G, B, got {data['channel']!r}")
        if data["basis"] != "legendre":
            raise ConfigError(f"{source}: basis is {data['basis']!r}; this labkit reads 'legendre'")
        degree = pb.check_count(f"{source}: degree", data["degree"], least=0)
        for key in ("xy", "domain", "intensity"):
            if not isinstance(data[key], Mapping):
                raise ConfigError(f"{source}: {key} must be a mapping")
        xy, dom, inten = data["xy"], data["domain"], data["intensity"]
        offset = float_array(xy.get("offset"), f"{source}: xy.offset", shape=(2,))
        matrix = float_array(xy.get("matrix"), f"{source}: xy.matrix", shape=(2, 2))
        centre = float_array(dom.get("centre"), f"{source}: domain.centre", shape=(2,))
        half = float_array(dom.get("half_width"), f"{source}: domain.half_width", shape=(2,))
        if np.any(half <= 0):
            raise ConfigError(f"{source}: domain.half_width must be positive")
        i_off = float(float_array(inten.get("offset"), f"{source}: intensity.offset", shape=()))
        i_scale = float(float_array(inten.get("scale"), f"{source}: intensity.scale", shape=()))
        if i_scale <= 0:
            raise ConfigError(f"{source}: intensity.scale must be positive")
        mean = float(float_array(data["mean_intensity"], f"{source}: mean_intensity", shape=()))
        if mean <= 0:
            raise ConfigError(f"{source}: mean_intensity must be positive")
        m = pb.n_terms_xy(degree)
        coef = float_array(data["coefficients"], f"{source}: coefficients", shape=(m,))
        selection = data.get("selection") or {}
        if not isinstance(selection, Mapping):
            raise ConfigError(f"{source}: selection must be a mapping")
        return cls(
            degree=degree,
            xy_offset=offset,
            xy_matrix=matrix,
            domain=pb.Domain(centre, half),
            intensity_offset=i_off,
            intensity_scale=i_scale,
            coefficients=coef,
            mean_intensity=mean,
            image_shape=(shape[0], shape[1]),
            cfa=cfa,
            channel=str(data["channel"]),
            selection=dict(selection),
            name=str(data.get("image", source)),
        )


@fixed_blas_threads
def fit_vignetting(
    raw: np.ndarray,
    *,
    cfa: str,
    mask: np.ndarray | None = None,
    channel: str = "G",
    max_degree: int = 5,
    folds: int = 10,
    rng: np.random.Generator | None = None,
    name: str = "image",
    max_pixels: int = MAX_PIXELS,
    max_condition: float = pb.MAX_CONDITION,
) -> VignettingModel:
    """Fit a polynomial intensity model to the `channel` pixels of `raw` inside `mask`.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Raw mosaic (any real dtype), dark-subtracted, of a scene uniform inside `mask`.
    cfa : str
        Bayer layout of `raw` (e.g. ``"GBRG"``).
    mask : ndarray of bool (rows, cols), optional
        True where the scene should be uniform; default every pixel.
    channel : {"R", "G", "B"}
        Colour channel fitted (thesis: Green, the densest).
    max_degree : int
        Largest total degree tried (thesis: 5).
    folds : int
        Cross-validation folds (thesis: 10).
    rng : numpy.random.Generator, optional
        Folds and subsample; default ``numpy.random.default_rng(0)``.
    name : str
        The image's name for messages and the model file.
    max_pixels : int
        At most this many pixels (a random subsample) are fitted.

    Raises
    ------
    DataError
        Bad image or mask (wrong shape or type, too few pixels, NaN inside the mask), or
        a fitted surface that is not positive everywhere in the image.
    """
    raw = np.asarray(raw)
    layout = _check_inputs(raw, cfa, channel, max_degree, name)
    mask = _checked_mask(mask, raw.shape, name)
    rng = np.random.default_rng(0) if rng is None else rng
    select = mask & (channel_index(layout, raw.shape) == CHANNELS.index(channel))
    rows, cols, intensity = _samples(raw, select, rng, channel, folds, max_pixels, name)
    xy = np.column_stack([cols, rows]).astype(np.float64)
    offset, matrix = pb.whitening(xy, what=f"{name}: vignetting mask")
    u = (xy - offset) @ matrix.T
    domain = pb.Domain.fit(u)
    i_offset = float(intensity.mean())
    i_scale = float(intensity.std())
    if not i_scale > 0:
        i_scale = 1.0
    target = (intensity - i_offset) / i_scale
    X = pb.design_matrix(domain(u), pb.exponent_table(max_degree))
    degree, cv, (mean, std) = _select_degree(X, target, max_degree, folds, rng, max_condition, name)
    size = pb.n_terms_xy(degree)
    coef, cond = pb.solve_lstsq(
        X[:, :size], target, max_condition=max_condition, what=f"{name}: vignetting model"
    )
    mean_intensity = float((X[:, :size] @ coef * i_scale + i_offset).mean())
    if not mean_intensity > 0:
        raise DataError(
            f"{name}: the vignetting model predicts a non-positive mean intensity "
            f"({mean_intensity:.4g}); is the image dark-subtracted and exposed?"
        )
    model = VignettingModel(
        degree=degree,
        xy_offset=offset,
        xy_matrix=matrix,
        domain=domain,
        intensity_offset=i_offset,
        intensity_scale=i_scale,
        coefficients=coef,
        mean_intensity=mean_intensity,
        image_shape=raw.shape,
        cfa=layout,
        channel=channel,
        selection={
            "method": "cv-1se",
            "error_units": "squared normalised intensity (intensity / its standard deviation)",
            "folds": int(folds),
            "cv_error": pb.table(mean),
            "cv_std": pb.table(std),
            "condition_number": cond,
            "skipped": [{"degree": i, "reason": r} for (_, i), r in sorted(cv.skipped.items())],
            "n_pixels": int(select.sum()),
            "n_fitted": len(X),
        },
        name=name,
    )
    _check_positive(model, name)
    return model


def _check_inputs(raw: np.ndarray, cfa: str, channel: str, max_degree: int, name: str) -> str:
    """The checked Bayer layout; an error naming the image for a bad raw image, channel or
    degree."""
    if raw.ndim != 2 or raw.dtype.kind not in "biuf":
        raise DataError(
            f"{name}: vignetting needs a 2-D raw mosaic of numbers, got {raw.shape} {raw.dtype}"
        )
    layout = check_layout(cfa)
    if channel not in CHANNELS:
        raise DataError(f"{name}: channel must be one of R, G, B, got {channel!r}")
    pb.check_count("max_degree", max_degree, least=0)
    return layout


def _checked_mask(mask: np.ndarray | None, shape: tuple[int, ...], name: str) -> np.ndarray:
    """`mask` as a boolean array of the image's shape (every pixel when None)."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != shape or mask.dtype != bool:
        raise DataError(
            f"{name}: the vignetting mask must be a boolean array of the image's shape; "
            f"mask shape {mask.shape} ({mask.dtype}), image shape {shape}"
        )
    return mask


def _samples(
    raw: np.ndarray,
    select: np.ndarray,
    rng: np.random.Generator,
    channel: str,
    folds: int,
    max_pixels: int,
    name: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and intensities of the selected pixels (a random subsample of at most
    `max_pixels`); an error when too few, or when any is not finite."""
    rows, cols = np.nonzero(select)
    if rows.size < max(MIN_PIXELS, folds):
        raise DataError(
            f"{name}: only {rows.size} {channel} pixels inside the vignetting mask (mask shape "
            f"{select.shape}, image shape {raw.shape}); need at least {max(MIN_PIXELS, folds)}"
        )
    if rows.size > max_pixels:
        pick = np.sort(rng.choice(rows.size, size=max_pixels, replace=False))
        rows, cols = rows[pick], cols[pick]
    intensity = raw[rows, cols].astype(np.float64)
    if not np.all(np.isfinite(intensity)):
        raise DataError(f"{name}: the image holds NaN or Inf inside the vignetting mask")
    return rows, cols, intensity


def _select_degree(
    X: np.ndarray,
    target: np.ndarray,
    max_degree: int,
    folds: int,
    rng: np.random.Generator,
    max_condition: float,
    name: str,
) -> tuple[int, pb.CVResult, tuple[np.ndarray, np.ndarray]]:
    """The total degree by `folds`-fold cross-validation and the one-standard-error rule,
    the cross-validation itself, and its mean and standard deviation per degree."""
    splits = pb.kfold_splits(len(X), folds, rng)
    sizes = [pb.n_terms_xy(d) for d in range(max_degree + 1)]
    cv = pb.cross_validate(
        X, target, splits, [[j] for j in range(len(splits))],
        [(np.arange(X.shape[1]), sizes)], max_condition=max_condition,
    )  # fmt: skip
    mean, std = cv.mean_std()
    mean, std = mean[0], std[0]
    if not np.any(np.isfinite(mean)):
        raise DataError(f"{name}: no polynomial intensity model could be fitted")
    return pb.one_standard_error_1d(mean, std), cv, (mean, std)


def _check_positive(model: VignettingModel, name: str) -> None:
    """Refuse a model whose surface is not positive everywhere in the image."""
    image = model.image()
    low = float(image.min())
    if not low > 0:
        r, c = np.unravel_index(int(np.argmin(image)), image.shape)
        raise DataError(
            f"{name}: the vignetting model (degree {model.degree}) predicts non-positive "
            f"intensity ({low * model.mean_intensity:.4g}) at row {r}, column {c}; the mask "
            "probably leaves too much of the image uncovered for the polynomial to extrapolate"
        )
