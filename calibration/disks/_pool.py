"""The disk fits of whole images on a process pool: the worker count, the pool, and the fits
of one image started (:func:`start`) and collected later (:func:`finish`), so that several
images share one pool and the detection of the next image overlaps the fits of the last.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any, NamedTuple

import numpy as np

from calibration.disks._raw import channel_noise
from calibration.disks._refine import (
    Options,
    Outcome,
    Task,
    ellipse_from_quadratic,
    make_tasks,
    refine_chunk,
)
from calibration.disks.detect import DiskCandidates, detect_disks
from labkit.cfa import channel_index
from labkit.errors import DataError


def _submit(
    tasks: list[Task], options: Options, pool: Executor | None, workers: int
) -> list[Future | list[Outcome]]:
    """Start refining `tasks`: 4 chunks per worker go to the pool, or all run here."""
    if pool is None or len(tasks) < 8:
        return [refine_chunk(tasks, options)]
    n_chunks = min(len(tasks), 4 * workers)
    bounds = np.linspace(0, len(tasks), n_chunks + 1).astype(int)
    return [
        pool.submit(refine_chunk, tasks[a:b], options)
        for a, b in itertools.pairwise(bounds)
        if b > a
    ]


def worker_count(workers: int | None) -> int:
    """Worker count: `workers`, or the CPUs this process may run on."""
    if workers is None:
        try:
            return max(len(os.sched_getaffinity(0)), 1)
        except AttributeError:  # not on Linux
            return os.cpu_count() or 1
    if int(workers) < 1:
        raise DataError(f"workers must be ≥ 1, got {workers}")
    return int(workers)


@contextmanager
def maybe_pool(workers: int) -> Iterator[Executor | None]:
    """A process pool for `workers` > 1, else None (fits run in this process)."""
    if workers <= 1:
        yield None
        return
    pool = ProcessPoolExecutor(max_workers=workers)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


class Pending(NamedTuple):
    """Disk fits of one image under way."""

    name: str
    candidates: DiskCandidates
    outside: int
    per_channel: bool
    parts: list[Future | list[Outcome]]


def start(
    raw: np.ndarray,
    layout: str,
    candidates: DiskCandidates | None,
    per_channel: bool,
    name: str,
    edge_width: float,
    pool: Executor | None,
    workers: int,
) -> Pending:
    """Detect (unless given) and start fitting the disks of one image."""
    if candidates is None:
        candidates = detect_disks(raw, cfa=layout, name=name)
    if candidates.labels.shape != raw.shape:
        raise DataError(
            f"{name}: disk candidates were detected in a {candidates.labels.shape} image, "
            f"but the raw mosaic is {raw.shape}; detect them in this image"
        )
    index = channel_index(layout, raw.shape)
    tasks, outside = make_tasks(raw, index, candidates, edge_width)
    noise = channel_noise(raw, index)
    options = Options(per_channel, edge_width, tuple(float(v) for v in noise))
    return Pending(name, candidates, outside, per_channel, _submit(tasks, options, pool, workers))


def finish(pending: Pending) -> dict[str, Any]:
    """Collect the fits of one image: the fields of its :class:`~calibration.disks.fit.DiskFit`,
    which the caller makes, ``DiskFit(**finish(pending))`` (that module imports this one)."""
    outcomes = [
        outcome
        for part in pending.parts
        for outcome in (part.result() if isinstance(part, Future) else part)
    ]
    rejected: dict[str, int] = {}
    if pending.outside:
        rejected["touches border"] = pending.outside
    good = []
    for outcome in outcomes:
        if outcome.reason:
            rejected[outcome.reason] = rejected.get(outcome.reason, 0) + 1
        else:
            good.append(outcome)
    if not good:
        raise DataError(
            f"{pending.name}: none of the {len(pending.candidates)} detected disks could be "
            f"refined (rejected: {rejected}); check focus and exposure, and that the disks "
            "lie well inside the image"
        )
    centres = np.stack([o.centres for o in good])  # (n, g, 2)
    quads = np.stack([o.quadratic for o in good])
    widths = np.stack([o.edge_width for o in good])
    residuals = np.stack([o.residual for o in good])
    main = 1 if pending.per_channel else 0  # per-channel fits report the Green channel
    axes, angle = ellipse_from_quadratic(quads[:, main])
    return {
        "centres": centres[:, main].copy(),
        "channel_centres": centres if pending.per_channel else None,
        "axes": axes,
        "angle_rad": angle,
        "edge_width_px": widths[:, main].copy(),
        "residual": residuals.max(axis=1),
        "candidate": np.array([o.candidate for o in good], dtype=np.int64),
        "rejected": rejected,
    }
