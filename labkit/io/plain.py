"""Values made safe for YAML files: numpy scalars and arrays, tuples and paths → plain Python;
and the time stamp labkit writes into its files."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any

import numpy as np


def to_plain(value: Any) -> Any:
    """`value` with numpy types, tuples and paths converted to plain Python, recursively.

    Non-finite floats become None (``.nan`` in a YAML file reads back as a string in
    some tools and as NaN in others).
    """
    if isinstance(value, Mapping):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [to_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, PurePath):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def now_iso() -> str:
    """Current UTC time, ISO 8601 to the millisecond (the time stamps of labkit's files)."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")
