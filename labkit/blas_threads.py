"""The BLAS thread count of labkit's own numerical work, whatever the environment says.

OpenBLAS (and MKL) split a product or a factorisation differently over different thread
counts, so the last bits of a result depend on ``OPENBLAS_NUM_THREADS`` /
``OMP_NUM_THREADS`` and on the number of cores, and an iterative method can amplify them
into a different stopping iteration and a visibly different result. So every public
numerical entry point of labkit (solvers, weight selection, reconstruction, calibration
fits, the HDR merge) runs its BLAS work at :data:`BLAS_THREADS` threads, set with
threadpoolctl on entry and restored on exit; the same inputs then give bit-identical
results under any BLAS setting of the caller.

Parallelism comes from labkit's own workers instead (Dask patches, process pools), whose
BLAS calls would only oversubscribe the cores if BLAS threaded too.

The limit is process-wide (OpenBLAS' own thread pool is shared by the process). Entry
points nest and may run on several threads at once: the first to enter sets the limit and
the last to leave restores the caller's, so no thread restores it while another is still
computing. The first and the last may be different threads; threadpoolctl (≥ 3.8) lets
only one "controlling" thread change OpenBLAS' limit and silently ignores the others, so
labkit releases that control before and after each change it makes.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable, Iterator
from typing import Any, ParamSpec, TypeVar

import threadpoolctl

#: BLAS threads inside labkit's numerical entry points.
BLAS_THREADS = 1

_P = ParamSpec("_P")
_R = TypeVar("_R")

_lock = threading.Lock()
_depth = 0
_limiter: Any = None


@contextlib.contextmanager
def library_blas_threads() -> Iterator[None]:
    """Run the block with BLAS at :data:`BLAS_THREADS` threads, then restore the caller's.

    Re-entrant and thread-safe: nested and concurrent blocks share one limit, lifted when
    the last of them ends.
    """
    global _depth, _limiter
    with _lock:
        if _depth == 0:
            _release_control()
            _limiter = threadpoolctl.threadpool_limits(limits=BLAS_THREADS, user_api="blas")
            _release_control()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                limiter, _limiter = _limiter, None
                _release_control()
                limiter.restore_original_limits()
                _release_control()


def _release_control() -> None:
    """Let any thread change OpenBLAS' limit next (threadpoolctl ≥ 3.8 gives that right
    to one thread at a time and ignores the others without a word)."""
    controller = getattr(threadpoolctl, "OpenBLASController", None)
    clear = getattr(controller, "clear_controlling_thread", None)
    if clear is not None:
        clear(force=True)


def fixed_blas_threads(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorate a numerical entry point so that it runs under :func:`library_blas_threads`.

    The wrapper is marked (``__labkit_blas_threads__``), so that tests can check that an
    entry point carries it.
    """

    @functools.wraps(func)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with library_blas_threads():
            return func(*args, **kwargs)

    wrapper.__labkit_blas_threads__ = True  # type: ignore[attr-defined]
    return wrapper


def has_fixed_blas_threads(func: Callable[..., Any]) -> bool:
    """Whether `func` (or a method's function) was decorated with :func:`fixed_blas_threads`."""
    return bool(getattr(func, "__labkit_blas_threads__", False))


__all__ = ["BLAS_THREADS", "fixed_blas_threads", "has_fixed_blas_threads", "library_blas_threads"]
