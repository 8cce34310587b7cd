"""`labkit.blas_threads`: the library's own BLAS thread count, nested, concurrent, restored."""

from __future__ import annotations

import importlib
import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from labkit.blas_threads import (
    BLAS_THREADS,
    fixed_blas_threads,
    has_fixed_blas_threads,
    library_blas_threads,
)

#: Every public numerical entry point whose result rounding can swing (module, name).
ENTRY_POINTS = [
    ("reconstruction.solve.solvers.admm", "solve_admm"),
    ("reconstruction.solve.solvers.exact", "solve_exact"),
    ("reconstruction.solve.solvers.direct", "solve_direct"),
    ("reconstruction.solve.solvers.quadratic", "initial_estimate"),
    ("reconstruction.solve.solvers.active_set", "polish"),
    ("reconstruction.solve.solvers.active_set", "solve_periodic"),
    ("reconstruction.solve.weights", "select_weights"),
    ("reconstruction.solve.patches", "solve_patch"),
    ("reconstruction.solve.patches", "reconstruct_patches"),
    ("reconstruction.reconstruct", "reconstruct"),
    ("reconstruction.evaluate.evaluation", "evaluate"),
    ("reconstruction.evaluate.evaluation", "baseline_images"),
    ("reconstruction.evaluate.metrics", "registration_scale"),
    ("reconstruction.evaluate.metrics", "spectral_errors"),
    ("reconstruction.evaluate.metrics", "colour_errors"),
    ("reconstruction.evaluate.residual_aberration", "residual_aberration"),
    ("calibration.dispersion_calibration", "calibrate_dispersion"),
    ("calibration.polynomial", "fit_polynomial_model"),
    ("calibration.spline", "fit_spline_model"),
    ("calibration.spline", "gcv_grid_search"),
    ("calibration.vignetting", "fit_vignetting"),
    ("calibration.sensitivity", "channel_sensitivity"),
    ("calibration.disks", "detect_disks"),
    ("calibration.disks", "fit_disks"),
    ("calibration.disks", "disk_keypoints"),
    ("calibration.disks", "channel_disk_keypoints"),
    ("calibration.disks._refine", "refine_chunk"),  # runs in the process pool's workers
    ("calibration.registration", "patch_shifts"),
    ("calibration.registration", "registration_keypoints"),
    ("calibration.registration", "channel_registration_keypoints"),
    ("calibration.multispectral", "synthesize_multispectral"),
    ("calibration._polybasis", "cross_validate"),
    ("calibration._polybasis", "solve_lstsq"),
    ("labkit.hdr.merge", "merge_exposures"),
    ("labkit.hdr.scaling", "fit_pair_factor"),
    ("labkit.hdr.session", "run_hdr"),
    ("labkit.fitting", "principal_slope"),
]


def blas_counts() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


@pytest.mark.parametrize(("module", "name"), ENTRY_POINTS)
def test_numerical_entry_points_fix_the_blas_thread_count(module: str, name: str) -> None:
    assert has_fixed_blas_threads(getattr(importlib.import_module(module), name))


def test_the_limit_applies_inside_and_the_callers_setting_comes_back() -> None:
    assert blas_counts(), "no BLAS library found"
    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_counts()
        with library_blas_threads():
            assert blas_counts() == [BLAS_THREADS] * len(before)
            with library_blas_threads():
                assert blas_counts() == [BLAS_THREADS] * len(before)
            assert blas_counts() == [BLAS_THREADS] * len(before)  # the inner exit kept it
        assert blas_counts() == before


def test_the_decorator_keeps_the_function_and_its_result() -> None:
    @fixed_blas_threads
    def product(a: np.ndarray, *, scale: float) -> tuple[np.ndarray, list[int]]:
        """Docstring kept."""
        return scale * (a @ a.T), blas_counts()

    a = np.arange(12.0).reshape(3, 4)
    result, inside = product(a, scale=2.0)
    np.testing.assert_array_equal(result, 2.0 * a @ a.T)
    assert set(inside) == {BLAS_THREADS}
    assert product.__doc__ == "Docstring kept." and product.__name__ == "product"
    assert has_fixed_blas_threads(product) and not has_fixed_blas_threads(product.__wrapped__)


def test_the_limit_holds_until_the_last_concurrent_caller_leaves() -> None:
    """Thread A enters, thread B enters, A leaves: B must still compute at the library's
    count (a per-call set/restore would hand B the caller's count mid-computation)."""
    a_inside, b_inside, a_left, b_may_leave = (threading.Event() for _ in range(4))
    seen: dict[str, list[int]] = {}

    def first() -> None:
        with library_blas_threads():
            a_inside.set()
            b_inside.wait(5)
        a_left.set()

    def second() -> None:
        a_inside.wait(5)
        with library_blas_threads():
            b_inside.set()
            a_left.wait(5)
            seen["after A left"] = blas_counts()
            b_may_leave.wait(5)

    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_counts()
        threads = [threading.Thread(target=first), threading.Thread(target=second)]
        for t in threads:
            t.start()
        a_left.wait(5)
        b_may_leave.set()
        for t in threads:
            t.join(10)
        assert seen["after A left"] == [BLAS_THREADS] * len(before)
        assert blas_counts() == before


def test_an_error_inside_still_restores_the_callers_setting() -> None:
    @fixed_blas_threads
    def fails() -> None:
        raise ValueError("boom")

    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_counts()
        with pytest.raises(ValueError, match="boom"):
            fails()
        assert blas_counts() == before
