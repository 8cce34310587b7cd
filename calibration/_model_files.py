"""Validated values read from model files (dispersion and vignetting YAML).

Every reader of a model file checks its numbers here, so that a bad value raises one
:class:`~labkit.errors.ConfigError` that names the file's key.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labkit.errors import ConfigError


def _float_array(value: Any, where: str) -> np.ndarray:
    """A finite float array from YAML lists, or a ConfigError naming `where`."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must hold numbers") from None
    if array.size == 0 or not np.all(np.isfinite(array)):
        raise ConfigError(f"{where} must be a non-empty list of finite numbers")
    return array


def float_array(
    value: Any, where: str, *, shape: tuple[int | None, ...] | None = None
) -> np.ndarray:
    """Validated float array for field readers: finite, and of `shape` (None = any size)."""
    array = _float_array(value, where)
    if shape is not None and (
        array.ndim != len(shape)
        or any(s is not None and s != a for s, a in zip(shape, array.shape, strict=True))
    ):
        want = " × ".join("n" if s is None else str(s) for s in shape)
        raise ConfigError(f"{where} must be an array of shape {want}, got {array.shape}")
    return array
