"""Helpers of the numerical stress suite (importable: pytest puts tests/stress on sys.path)."""

from __future__ import annotations

import numpy as np

#: Machine epsilon of float64: the low end of every regularisation-weight sweep.
EPS = float(np.finfo(np.float64).eps)


def assert_finite(*arrays: np.ndarray) -> None:
    """Assert that every value of every array is finite (no NaN, no ±Inf).

    Parameters
    ----------
    *arrays : ndarray
        Outputs to check (any shape, any numeric dtype).
    """
    for index, array in enumerate(arrays):
        values = np.asarray(array)
        bad = int(np.count_nonzero(~np.isfinite(values)))
        assert bad == 0, f"output {index} holds {bad} NaN/Inf value(s) of {values.size}"


def relative_rms(estimate: np.ndarray, reference: np.ndarray) -> float:
    """RMS of ``estimate − reference`` relative to the RMS of `reference`.

    Parameters
    ----------
    estimate, reference : ndarray
        Arrays of one shape; computed in float64.

    Returns
    -------
    float
        ``‖estimate − reference‖ / ‖reference‖`` (0 when both are zero).
    """
    e = np.asarray(estimate, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    norm = float(np.linalg.norm(r))
    difference = float(np.linalg.norm(e - r))
    return difference / norm if norm > 0 else difference
