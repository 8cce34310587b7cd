"""A persistent pool of worker processes for the patches (the ``processes`` scheduler).

A patch's solve is many NumPy operations on arrays of some 30 000 values, each a few tens
of µs; on threads, part of that time is spent waiting for the interpreter lock, which
separate processes do not share. Whether that makes them faster depends on the machine
and the image (measurements so far disagree: an open question of issue 53). Starting a
pool of processes costs seconds (each imports NumPy, SciPy and labkit), so one pool is
started per Python process, in the background as soon as a reconstruction begins
(:func:`start_worker_pool`, during the weight search), and kept for later reconstructions.

The workers are forked from a ``forkserver`` that has imported :data:`PRELOAD`: no thread
of the caller is copied into a worker (``fork`` of a process with threads can deadlock the
child). Like every ``spawn``-type pool, each worker imports the caller's main module, so a
script that uses this pool needs the ``if __name__ == "__main__":`` guard; that is why it
is not the default scheduler. A worker exits as soon as the process that made the pool is
gone, even killed with ``kill -9``.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor

PRELOAD = ("reconstruction.solve.patches",)
"""Modules the forkserver imports once, so that each worker starts with them loaded."""

_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_size = 0


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def worker_pool(workers: int | None = None) -> ProcessPoolExecutor:
    """The pool of `workers` processes (default :func:`available_cores`), made on first use
    and again after a worker died (a broken pool) or for another size."""
    global _pool, _size
    workers = workers or available_cores()
    with _lock:
        if _pool is not None and (_size != workers or getattr(_pool, "_broken", False)):
            _pool.shutdown(wait=False, cancel_futures=True)
            _pool = None
        if _pool is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(list(PRELOAD))
            _pool = ProcessPoolExecutor(
                workers, mp_context=context, initializer=_exit_with, initargs=(os.getpid(),)
            )
            _size = workers
        return _pool


WATCH_INTERVAL_S = 0.5
"""How often a worker checks that the process it works for is still alive, s."""


def _exit_with(owner: int) -> None:
    """Worker initializer: exit as soon as `owner` (the process that made the pool) is gone.

    A worker waits on a queue whose other end it holds itself, so it would outlive an owner
    killed with ``kill -9`` (keeping its stdout open, and its memory). Its parent, the
    forkserver, exits with the owner, so a changed parent pid says the owner is gone.
    """
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(WATCH_INTERVAL_S)
            if os.getppid() != parent or not _alive(owner):
                os._exit(0)

    threading.Thread(target=watch, name="labkit-worker-watch", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's (cannot happen for our owner)
        return True
    return True


def _ready() -> int:
    return os.getpid()


def start_worker_pool(workers: int | None = None) -> None:
    """Start the pool's processes in the background (returns at once)."""

    count = workers or available_cores()

    def start() -> None:
        pool = worker_pool(count)
        with contextlib.suppress(Exception):  # a broken pool is the run's to report
            for future in [pool.submit(_ready) for _ in range(count)]:
                future.result()

    threading.Thread(target=start, name="labkit-worker-pool-start", daemon=True).start()


def worker_pids() -> list[int]:
    """Process ids of the pool's live workers (none before the pool starts)."""
    with _lock:
        if _pool is None:
            return []
        processes = getattr(_pool, "_processes", None) or {}
        return [p.pid for p in processes.values() if p.pid is not None]


__all__ = ["PRELOAD", "available_cores", "start_worker_pool", "worker_pids", "worker_pool"]
