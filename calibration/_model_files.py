"""Validated values read from model files (dispersion and vignetting YAML).

Every reader of a model file checks its numbers here, so that a bad value raises one
:class:`~labkit.errors.ConfigError` that names the file's key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from labkit.errors import ConfigError
from labkit.io.output_folder import check_file_set


def read_model_document(path: str | Path, *, what: str, missing_fix: str, writer: str) -> Any:
    """The YAML document of a model file, after checking it is there, is text, and is not
    the previous file of a set a killed run left half replaced (its plots newer than it).

    `what` names the model ("dispersion model"), `missing_fix` says how to make one, and
    `writer` is the command that writes such files, for messages.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path} is a folder; give the model's YAML file")
    if not path.is_file():
        raise ConfigError(f"{what} {path} does not exist; {missing_fix}")
    check_file_set(path, what=what)
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(
            f"{what} {path} cannot be read as YAML text ({exc}); give the model file "
            f"`{writer}` wrote"
        ) from None


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
