"""Thin-plate spline displacement fields: evaluation and their entry in model files (§3.2.4).

A :class:`SplineField` is one term of a :class:`~calibration.dispersion_model.DispersionModel`
(the model is in :mod:`calibration.spline`'s docstring);
:func:`calibration.spline.fit_spline_model` fits them to keypoints by GCV.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from calibration._model_files import float_array
from calibration._normalise import Normaliser
from calibration._spline_kernel import PHI_SCALE, psi
from labkit.errors import ConfigError, DataError

#: Kernel names written to model files, by input dimension.
KERNELS = {2: "r^2 log r", 3: "-r"}
#: Points × centres per evaluation block (1 MiB of float64 per buffer).
BLOCK_ELEMENTS = 1 << 17
#: Threads evaluating blocks.
WORKERS = max(1, min(4, os.cpu_count() or 1))

_FIELD_KEYS = (
    "kind",
    "dimension",
    "kernel",
    "smoothing",
    "normaliser",
    "centres",
    "weights",
    "affine",
)


@dataclass(frozen=True)
class SplineField:
    """A smoothing thin-plate spline for both displacement components.

    Attributes
    ----------
    normaliser : Normaliser
        Maps px / nm inputs to the normalised u and normalised outputs back to px.
    centres : ndarray (m, dimension)
        Kernel centres u_i, normalised (the keypoints, possibly cell-averaged).
    weights : ndarray (m, 2)
        Kernel coefficients c_i of the x and y components (of φ, see the module doc).
    affine : ndarray (dimension + 1, 2)
        Affine coefficients: constant, then one row per normalised input.
    smoothing : float
        w of ``K + w I`` (normalised units; 8π × the weight of thesis (3.5)).
    """

    kind: ClassVar[str] = "spline"

    normaliser: Normaliser
    centres: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    smoothing: float

    def __post_init__(self) -> None:
        centres = np.asarray(self.centres, dtype=np.float64)
        weights = np.asarray(self.weights, dtype=np.float64)
        affine = np.asarray(self.affine, dtype=np.float64)
        if centres.ndim != 2 or centres.shape[1] not in (2, 3) or len(centres) == 0:
            raise DataError(f"spline centres must be (m, 2) or (m, 3), got {centres.shape}")
        dim = centres.shape[1]
        if weights.shape != (len(centres), 2):
            raise DataError(f"spline weights must be ({len(centres)}, 2), got {weights.shape}")
        if affine.shape != (dim + 1, 2):
            raise DataError(f"spline affine part must be ({dim + 1}, 2), got {affine.shape}")
        if self.normaliser.n_inputs != dim:
            raise DataError(
                f"spline normaliser takes {self.normaliser.n_inputs} inputs, centres have {dim}"
            )
        object.__setattr__(self, "centres", np.ascontiguousarray(centres))
        object.__setattr__(self, "weights", weights)
        object.__setattr__(self, "affine", affine)
        object.__setattr__(self, "smoothing", float(self.smoothing))

    @property
    def dimension(self) -> int:
        """2 for (x, y), 3 for (x, y, λ)."""
        return int(self.centres.shape[1])

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Displacements (n, 2) px at `points` (n, 2) = (x, y) px or (n, 3) = (x, y, λ nm).

        Memory is O(n + block · m); blocks run on :data:`WORKERS` threads.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != self.dimension:
            raise DataError(
                f"this spline takes points of shape (n, {self.dimension}), got {points.shape}"
            )
        if len(points) == 0:
            return np.zeros((0, 2))
        return self.normaliser.restore(self._evaluate_normalised(self.normaliser.inputs(points)))

    def _evaluate_normalised(self, u: np.ndarray) -> np.ndarray:
        u = np.ascontiguousarray(u)
        n, m, dim = len(u), len(self.centres), self.dimension
        out = u @ self.affine[1:] + self.affine[0]
        weights = np.ascontiguousarray(PHI_SCALE[dim] * self.weights.T)
        block = min(n, max(16, BLOCK_ELEMENTS // m))
        workers = max(1, min(WORKERS, -(-n // block)))

        def work(first: int) -> None:
            # each worker takes every `workers`-th block and reuses its own buffers
            buffers = (np.empty((block, m)), np.empty((block, m) if dim == 2 else (0, 0)))
            for start in range(first * block, n, workers * block):
                stop = min(start + block, n)
                views = (buffers[0][: stop - start], buffers[1][: stop - start])
                kernel = psi(u[start:stop], self.centres, dim, views)
                # einsum's own loop, not BLAS: OpenBLAS serialises (and spins on) calls
                # made from several threads at once
                out[start:stop] += np.einsum("ij,kj->ik", kernel, weights)

        if workers == 1:
            work(0)
        else:
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(work, range(workers)))
        return out

    # -- files ----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "dimension": self.dimension,
            "kernel": KERNELS[self.dimension],
            "smoothing": float(self.smoothing),
            "normaliser": self.normaliser.to_dict(),
            "centres": self.centres.tolist(),
            "weights": self.weights.tolist(),
            "affine": self.affine.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Any, where: str) -> SplineField:
        """Read back :meth:`to_dict`; every problem raises a ConfigError naming `where`.key."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"{where} must be a mapping")
        unknown = sorted(str(k) for k in data if k not in _FIELD_KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}")
        for key in _FIELD_KEYS[1:]:
            if key != "kernel" and key not in data:
                raise ConfigError(f"{where}.{key} is missing")
        if data.get("kind", "spline") != "spline":
            raise ConfigError(f"{where}.kind must be 'spline', got {data.get('kind')!r}")
        dim = data["dimension"]
        if isinstance(dim, bool) or not isinstance(dim, int) or dim not in (2, 3):
            raise ConfigError(f"{where}.dimension must be 2 or 3, got {dim!r}")
        if "kernel" in data and data["kernel"] != KERNELS[dim]:
            raise ConfigError(
                f"{where}.kernel must be {KERNELS[dim]!r} for a {dim}-D spline, "
                f"got {data['kernel']!r}"
            )
        smoothing = float(float_array(data["smoothing"], f"{where}.smoothing", shape=()))
        if smoothing < 0:
            raise ConfigError(f"{where}.smoothing must be ≥ 0, got {smoothing}")
        normaliser = Normaliser.from_dict(data["normaliser"], f"{where}.normaliser")
        if normaliser.n_inputs != dim:
            raise ConfigError(
                f"{where}.normaliser has {normaliser.n_inputs} inputs, dimension is {dim} "
                "(a 3-D spline's normaliser needs a `wavelength` entry)"
            )
        centres = float_array(data["centres"], f"{where}.centres", shape=(None, dim))
        weights = float_array(data["weights"], f"{where}.weights", shape=(len(centres), 2))
        affine = float_array(data["affine"], f"{where}.affine", shape=(dim + 1, 2))
        return cls(normaliser, centres, weights, affine, smoothing)
