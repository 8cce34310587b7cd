"""Disk refinement (the second step of :mod:`calibration.disks`): a Levenberg–Marquardt fit of
the disk model to the raw pixels around each candidate, on a process pool.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from calibration.disks.detect import DiskCandidates, _channel_noise, _checked_raw, detect_disks
from calibration.disks.model import _MIN_EDGE, _N_GEOMETRY, _DiskModel
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS, channel_index, check_layout
from labkit.errors import DataError

#: Disks with a relative contrast (exterior − interior) / exterior below this are dropped.
_MIN_RELATIVE_CONTRAST = 0.25
#: Levenberg–Marquardt tolerances (relative change of parameters / of the cost).
_XTOL = 1e-6
_FTOL = 1e-8
#: Contrast-to-noise ratio above which a channel counts as noise-free in joint fits.
_CLEAN_SNR = 50.0


@dataclass(frozen=True)
class DiskFit:
    """Disks refined by fitting the synthetic disk model.

    Attributes
    ----------
    centres : ndarray (n, 2) float64
        Ellipse centres (x, y), px; for per-channel fits, the Green channel's centres.
    channel_centres : ndarray (n, 3, 2) float64 or None
        Per-channel fits: the R, G and B centres (x, y), px; None for joint fits.
    axes : ndarray (n, 2) float64
        Semi-major and semi-minor axes, px (per-channel fits: Green).
    angle_rad : ndarray (n,) float64
        Orientation of the major axis from the x-axis towards the y-axis, rad.
    edge_width_px : ndarray (n,) float64
        Width of the linear edge ramp of the scene (blur), px, not counting the pixel's
        own footprint (≈ 1 px), which the model integrates over; about 0.02 px (the
        floor) for perfectly sharp disks. Per-channel fits: Green.
    residual : ndarray (n,) float64
        RMS fit residual divided by the disk's contrast (dimensionless); per-channel
        fits: the largest over the channels.
    candidate : ndarray (n,) int64
        Index of the :class:`DiskCandidates` entry each fit started from.
    rejected : dict of str to int
        Disks dropped, by reason.
    """

    centres: np.ndarray
    channel_centres: np.ndarray | None
    axes: np.ndarray
    angle_rad: np.ndarray
    edge_width_px: np.ndarray
    residual: np.ndarray
    candidate: np.ndarray
    rejected: dict[str, int]

    def __len__(self) -> int:
        return int(self.centres.shape[0])


class _Task(NamedTuple):
    """One disk to refine: its neighbourhood and initial ellipse."""

    candidate: int
    values: np.ndarray  # (npix,) float64 raw values
    x: np.ndarray  # (npix,) float64 pixel x relative to the initial centre, px
    y: np.ndarray  # (npix,) float64
    channel: np.ndarray  # (npix,) uint8 colour channel of each pixel
    centre: tuple[float, float]  # initial centre (x, y), px
    q0: tuple[float, float, float]  # initial quadratic form · r0² (qxx, qxy, qyy)
    r0: float  # initial mean radius, px
    s0: np.ndarray  # (npix,) initial signed distance, px


class _Outcome(NamedTuple):
    """Result of refining one disk (one row per fitted channel group)."""

    candidate: int
    reason: str  # "" when accepted
    centres: np.ndarray  # (g, 2) x, y px
    quadratic: np.ndarray  # (g, 3) qxx, qxy, qyy in 1/px²
    edge_width: np.ndarray  # (g,)
    residual: np.ndarray  # (g,)


class _Options(NamedTuple):
    """Settings shared by all disk fits of one image."""

    per_channel: bool
    edge_width: float  # initial edge width, px
    noise: tuple[float, float, float]  # pixel noise sigma of R, G, B, raw units


def _fit_group(
    task: _Task, pick: np.ndarray | None, group: np.ndarray, m: int, options: _Options
) -> tuple[str, np.ndarray, np.ndarray, float, float]:
    """Fit the disk model to the pixels `pick` of a task (None = all).

    `group` gives each picked pixel's lightness group (its colour channel for joint fits,
    0 for single-channel fits). Returns (reason, centre (2,), quadratic form (3,) 1/px²,
    edge width px, relative residual); reason is "" for an accepted fit.
    """
    values = task.values if pick is None else task.values[pick]
    x = task.x if pick is None else task.x[pick]
    y = task.y if pick is None else task.y[pick]
    s0 = task.s0 if pick is None else task.s0[pick]
    channel = task.channel if pick is None else task.channel[pick]
    failed = np.full(2, np.nan), np.full(3, np.nan), np.nan, np.nan
    inner = np.zeros(m)
    outer = np.zeros(m)
    noise = np.zeros(m)
    for g in range(m):
        mine = group == g
        inside = mine & (s0 < -1.5)
        outside = mine & (s0 > 1.5)
        if not inside.any() or not outside.any():
            return ("too few pixels", *failed)
        inner[g] = np.median(values[inside])
        outer[g] = np.median(values[outside])
        noise[g] = options.noise[int(channel[np.argmax(mine)])]
    contrast = outer - inner
    main = int(np.argmax(contrast))
    scale = float(outer[main])
    if not scale > 0 or contrast[main] < _MIN_RELATIVE_CONTRAST * scale:
        return ("low contrast", *failed)
    data = values / scale
    weight = None
    if m > 1:
        # each channel counts by its contrast, or by its noise where that is the larger
        # (channels of a filtered image without signal then add noise, not bias)
        spread = np.maximum(np.abs(contrast), _CLEAN_SNR * noise)
        spread = np.maximum(spread, 1e-3 * contrast[main]) / scale
        weight = 1.0 / spread[group]
        data = data * weight
    model = _DiskModel(x, y, group, m, task.r0, weight)
    start_w = max(options.edge_width - 1.0, 0.25)  # less the pixel footprint (~1 px)
    p0 = np.concatenate([[0.0, 0.0, *task.q0, start_w**2, 0.0, 0.0], inner / scale, outer / scale])
    if data.size <= 2 * p0.size:
        return ("too few pixels", *failed)
    try:
        fit = least_squares(
            model.residuals,
            p0,
            jac=model.jacobian,
            method="lm",
            x_scale="jac",
            xtol=_XTOL,
            ftol=_FTOL,
            gtol=1e-10,
            max_nfev=200,
            args=(data,),
        )
    except (ValueError, np.linalg.LinAlgError):
        return ("not converged", *failed)
    p = fit.x
    if fit.status <= 0 or not np.all(np.isfinite(p)) or not np.all(np.isfinite(fit.fun)):
        return ("not converged", *failed)
    centre = np.array([task.centre[0] + p[0], task.centre[1] + p[1]])
    quad = np.array(p[2:5]) * model.inv_r02
    width = float(np.sqrt(_MIN_EDGE**2 + max(p[5], 0.0)))
    fitted_contrast = float(p[_N_GEOMETRY + m + main] - p[_N_GEOMETRY + main])
    misfit = fit.fun if weight is None else fit.fun / weight
    residual = float(np.sqrt(np.mean(misfit**2))) / max(abs(fitted_contrast), 1e-12)
    relative = fitted_contrast / max(float(p[_N_GEOMETRY + m + main]), 1e-12)
    reason = _checked_geometry(task, p, quad, width, relative)
    return reason, centre, quad, width, residual


def _checked_geometry(
    task: _Task, p: np.ndarray, quad: np.ndarray, width: float, contrast: float
) -> str:
    """Why a converged fit is implausible, or "" if it is fine."""
    if np.hypot(p[0], p[1]) > max(2.0, 0.3 * task.r0):
        return "moved too far"
    if quad[0] <= 0 or quad[0] * quad[2] - quad[1] ** 2 <= 0:
        return "implausible axes"
    semi, _ = _ellipse_from_quadratic(quad[None, :])
    major, minor = semi[0]
    if not (0.6 * task.r0 < minor <= major < 1.6 * task.r0) or major > 2.0 * minor:
        return "implausible axes"
    if width > 0.5 * task.r0:
        return "implausible edge width"
    if contrast < _MIN_RELATIVE_CONTRAST:
        return "low contrast"
    return ""


def _refine(task: _Task, options: _Options) -> _Outcome:
    """Refine one disk: jointly over all channels, or per channel (R, G, B)."""
    if not options.per_channel:
        groups = [(None, task.channel.astype(np.intp), 3)]
    else:
        groups = []
        for c in range(3):
            pick = np.flatnonzero(task.channel == c)
            groups.append((pick, np.zeros(pick.size, dtype=np.intp), 1))
    centres = np.full((len(groups), 2), np.nan)
    quads = np.full((len(groups), 3), np.nan)
    widths = np.full(len(groups), np.nan)
    residuals = np.full(len(groups), np.nan)
    for g, (pick, group, m) in enumerate(groups):
        reason, centres[g], quads[g], widths[g], residuals[g] = _fit_group(
            task, pick, group, m, options
        )
        if reason:
            if options.per_channel:
                reason = f"{reason} ({CHANNELS[g]})"
            return _Outcome(task.candidate, reason, centres, quads, widths, residuals)
    return _Outcome(task.candidate, "", centres, quads, widths, residuals)


@fixed_blas_threads
def _refine_chunk(tasks: list[_Task], options: _Options) -> list[_Outcome]:
    """Refine a chunk of disks (the unit of work of the process pool)."""
    return [_refine(task, options) for task in tasks]


def _quadratic_form(axes: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(n, 3) qxx, qxy, qyy of ellipses with semi-axes (n, 2) and major-axis angles (n,)."""
    c, s = np.cos(angle), np.sin(angle)
    ia = 1.0 / np.maximum(axes[:, 0], 1e-6) ** 2
    ib = 1.0 / np.maximum(axes[:, 1], 1e-6) ** 2
    return np.column_stack([ia * c * c + ib * s * s, (ia - ib) * c * s, ia * s * s + ib * c * c])


def _ellipse_from_quadratic(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (n, 2) (major, minor) and major-axis angles (n,) of quadratic forms (n, 3)."""
    a, b, c = quad[:, 0], quad[:, 1], quad[:, 2]
    half_trace = 0.5 * (a + c)
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    small, large = half_trace - root, half_trace + root
    # the major axis is the eigenvector of the smaller eigenvalue
    angle = 0.5 * np.arctan2(-2.0 * b, c - a)
    return np.column_stack([1.0 / np.sqrt(small), 1.0 / np.sqrt(large)]), angle


def _make_tasks(
    raw: np.ndarray, index: np.ndarray, candidates: DiskCandidates, edge_width: float
) -> tuple[list[_Task], int]:
    """Neighbourhoods of the candidates; also the number that leave the image."""
    rows, cols = raw.shape
    quads = _quadratic_form(candidates.axes, candidates.angle_rad)
    r0s = np.sqrt(np.maximum(candidates.axes[:, 0] * candidates.axes[:, 1], 1.0))
    tasks: list[_Task] = []
    outside = 0
    for k in range(len(candidates)):
        r0 = float(r0s[k])
        margin = int(np.ceil(max(3.0, 0.5 * r0)))
        row0, col0, row1, col1 = (int(v) for v in candidates.bbox[k])
        row0, col0, row1, col1 = row0 - margin, col0 - margin, row1 + margin, col1 + margin
        if row0 < 0 or col0 < 0 or row1 > rows or col1 > cols:
            outside += 1
            continue
        cx, cy = (float(v) for v in candidates.centres[k])
        yy, xx = np.mgrid[row0:row1, col0:col1]
        dx = (xx - cx).ravel().astype(np.float64)
        dy = (yy - cy).ravel().astype(np.float64)
        q = quads[k]
        r = np.hypot(dx, dy)
        safe = np.maximum(r, 1e-9)
        ex, ey = dx / safe, dy / safe
        s0 = r - 1.0 / np.sqrt(
            np.maximum(q[0] * ex * ex + 2 * q[1] * ex * ey + q[2] * ey * ey, 1e-12)
        )
        # the ring around the initial edge holds all the information on the geometry
        band = max(3.0, 1.5 + edge_width)
        ring = np.flatnonzero(np.abs(s0) <= band)
        tasks.append(
            _Task(
                candidate=k,
                values=raw[row0:row1, col0:col1].ravel()[ring].astype(np.float64),
                x=dx[ring],
                y=dy[ring],
                channel=index[row0:row1, col0:col1].ravel()[ring],
                centre=(cx, cy),
                q0=tuple(float(v) * r0 * r0 for v in q),
                r0=r0,
                s0=s0[ring],
            )
        )
    return tasks, outside


def _submit(
    tasks: list[_Task], options: _Options, pool: Executor | None, workers: int
) -> list[Future | list[_Outcome]]:
    """Start refining `tasks`: 4 chunks per worker go to the pool, or all run here."""
    if pool is None or len(tasks) < 8:
        return [_refine_chunk(tasks, options)]
    n_chunks = min(len(tasks), 4 * workers)
    bounds = np.linspace(0, len(tasks), n_chunks + 1).astype(int)
    return [
        pool.submit(_refine_chunk, tasks[a:b], options)
        for a, b in itertools.pairwise(bounds)
        if b > a
    ]


def _workers(workers: int | None) -> int:
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
def _maybe_pool(workers: int) -> Iterator[Executor | None]:
    """A process pool for `workers` > 1, else None (fits run in this process)."""
    if workers <= 1:
        yield None
        return
    pool = ProcessPoolExecutor(max_workers=workers)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@fixed_blas_threads
def fit_disks(
    raw: np.ndarray,
    *,
    cfa: str,
    candidates: DiskCandidates | None = None,
    per_channel: bool = False,
    name: str = "image",
    edge_width_px: float = 1.5,
    workers: int | None = None,
) -> DiskFit:
    """Refine disk positions with Levenberg–Marquardt fits of a synthetic disk (§3.2.1).

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Bayer mosaic, linear.
    cfa : str
        CFA layout.
    candidates : DiskCandidates, optional
        Detected disks (default: :func:`detect_disks` on `raw`).
    per_channel : bool
        False (filtered images): one fit per disk over all channels, each channel with its
        own lightnesses. True (unfiltered images): one fit per disk and colour channel,
        using only that channel's pixels.
    name : str
        What the image is, for error messages.
    edge_width_px : float
        Initial width of the edge as it appears in the image, px, including the pixel
        footprint (≈ 1 px); the model's ramp width starts at ``edge_width_px − 1``
        (at least 0.25 px).
    workers : int, optional
        Processes (default: the CPUs available); 1 fits in this process.

    Returns
    -------
    DiskFit
        The accepted fits, with the reasons and counts of rejected disks.

    Raises
    ------
    DataError
        The image is malformed, shows no disks, or no disk could be refined.

    Notes
    -----
    The fit uses the pixels within max(3 px, 1.5 px + `edge_width_px`) of the detected
    edge, inside the detected bounding box enlarged by half a radius (≥ 3 px); disks
    whose neighbourhood leaves the image are skipped ("touches border"). In joint fits
    each channel's residuals are divided by the larger of its disk contrast and 50 × its
    pixel noise, so that every channel with signal counts equally (their sampling
    lattices then average out) and channels without signal add noise, not bias. Fits are
    rejected when Levenberg–Marquardt does not converge, the centre moves more than
    max(2 px, 0.3 radius), the axes are implausible (outside 0.6–1.6 × the detected
    radius or aspect > 2), the edge ramp is wider than half the radius, or the disk is
    not at least 25 % darker than the paper.
    """
    layout = check_layout(cfa)
    raw = _checked_raw(raw, name)
    if not edge_width_px > 0:
        raise DataError(f"edge_width_px must be > 0, got {edge_width_px}")
    n_workers = _workers(workers)
    with _maybe_pool(n_workers) as pool:
        pending = _start(raw, layout, candidates, per_channel, name, edge_width_px, pool, n_workers)
        return _finish(pending)


class _Pending(NamedTuple):
    """Disk fits of one image under way."""

    name: str
    candidates: DiskCandidates
    outside: int
    per_channel: bool
    parts: list[Future | list[_Outcome]]


def _start(
    raw: np.ndarray,
    layout: str,
    candidates: DiskCandidates | None,
    per_channel: bool,
    name: str,
    edge_width: float,
    pool: Executor | None,
    workers: int,
) -> _Pending:
    """Detect (unless given) and start fitting the disks of one image."""
    if candidates is None:
        candidates = detect_disks(raw, cfa=layout, name=name)
    if candidates.labels.shape != raw.shape:
        raise DataError(
            f"{name}: disk candidates were detected in a {candidates.labels.shape} image, "
            f"but the raw mosaic is {raw.shape}; detect them in this image"
        )
    index = channel_index(layout, raw.shape)
    tasks, outside = _make_tasks(raw, index, candidates, edge_width)
    noise = _channel_noise(raw, index)
    options = _Options(per_channel, edge_width, tuple(float(v) for v in noise))
    return _Pending(name, candidates, outside, per_channel, _submit(tasks, options, pool, workers))


def _finish(pending: _Pending) -> DiskFit:
    """Collect the fits of one image into a :class:`DiskFit`."""
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
    axes, angle = _ellipse_from_quadratic(quads[:, main])
    return DiskFit(
        centres=centres[:, main].copy(),
        channel_centres=centres if pending.per_channel else None,
        axes=axes,
        angle_rad=angle,
        edge_width_px=widths[:, main].copy(),
        residual=residuals.max(axis=1),
        candidate=np.array([o.candidate for o in good], dtype=np.int64),
        rejected=rejected,
    )
