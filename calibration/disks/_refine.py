"""Refining one disk (the second step of :mod:`calibration.disks`): the Levenberg–Marquardt
fit of the disk model to the raw pixels of a neighbourhood of a candidate, and those
neighbourhoods (the tasks that :mod:`calibration.disks._pool` runs).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from calibration.disks.detect import DiskCandidates
from calibration.disks.model import MIN_EDGE_WIDTH_PX, N_GEOMETRY, DiskModel
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import CHANNELS

#: Disks with a relative contrast (exterior − interior) / exterior below this are dropped.
_MIN_RELATIVE_CONTRAST = 0.25
#: Levenberg–Marquardt tolerances (relative change of parameters / of the cost).
_XTOL = 1e-6
_FTOL = 1e-8
#: Contrast-to-noise ratio above which a channel counts as noise-free in joint fits.
_CLEAN_SNR = 50.0


class Task(NamedTuple):
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


class Outcome(NamedTuple):
    """Result of refining one disk (one row per fitted channel group)."""

    candidate: int
    reason: str  # "" when accepted
    centres: np.ndarray  # (g, 2) x, y px
    quadratic: np.ndarray  # (g, 3) qxx, qxy, qyy in 1/px²
    edge_width: np.ndarray  # (g,)
    residual: np.ndarray  # (g,)


class Options(NamedTuple):
    """Settings shared by all disk fits of one image."""

    per_channel: bool
    edge_width: float  # initial edge width, px
    noise: tuple[float, float, float]  # pixel noise sigma of R, G, B, raw units


def _fit_group(
    task: Task, pick: np.ndarray | None, group: np.ndarray, m: int, options: Options
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
    model = DiskModel(x, y, group, m, task.r0, weight)
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
    width = float(np.sqrt(MIN_EDGE_WIDTH_PX**2 + max(p[5], 0.0)))
    fitted_contrast = float(p[N_GEOMETRY + m + main] - p[N_GEOMETRY + main])
    misfit = fit.fun if weight is None else fit.fun / weight
    residual = float(np.sqrt(np.mean(misfit**2))) / max(abs(fitted_contrast), 1e-12)
    relative = fitted_contrast / max(float(p[N_GEOMETRY + m + main]), 1e-12)
    reason = _checked_geometry(task, p, quad, width, relative)
    return reason, centre, quad, width, residual


def _checked_geometry(
    task: Task, p: np.ndarray, quad: np.ndarray, width: float, contrast: float
) -> str:
    """Why a converged fit is implausible, or "" if it is fine."""
    if np.hypot(p[0], p[1]) > max(2.0, 0.3 * task.r0):
        return "moved too far"
    if quad[0] <= 0 or quad[0] * quad[2] - quad[1] ** 2 <= 0:
        return "implausible axes"
    semi, _ = ellipse_from_quadratic(quad[None, :])
    major, minor = semi[0]
    if not (0.6 * task.r0 < minor <= major < 1.6 * task.r0) or major > 2.0 * minor:
        return "implausible axes"
    if width > 0.5 * task.r0:
        return "implausible edge width"
    if contrast < _MIN_RELATIVE_CONTRAST:
        return "low contrast"
    return ""


def _refine(task: Task, options: Options) -> Outcome:
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
            return Outcome(task.candidate, reason, centres, quads, widths, residuals)
    return Outcome(task.candidate, "", centres, quads, widths, residuals)


@fixed_blas_threads
def refine_chunk(tasks: list[Task], options: Options) -> list[Outcome]:
    """Refine a chunk of disks (the unit of work of the process pool)."""
    return [_refine(task, options) for task in tasks]


def _quadratic_form(axes: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(n, 3) qxx, qxy, qyy of ellipses with semi-axes (n, 2) and major-axis angles (n,)."""
    c, s = np.cos(angle), np.sin(angle)
    ia = 1.0 / np.maximum(axes[:, 0], 1e-6) ** 2
    ib = 1.0 / np.maximum(axes[:, 1], 1e-6) ** 2
    return np.column_stack([ia * c * c + ib * s * s, (ia - ib) * c * s, ia * s * s + ib * c * c])


def ellipse_from_quadratic(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (n, 2) (major, minor) and major-axis angles (n,) of quadratic forms (n, 3)."""
    a, b, c = quad[:, 0], quad[:, 1], quad[:, 2]
    half_trace = 0.5 * (a + c)
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    small, large = half_trace - root, half_trace + root
    # the major axis is the eigenvector of the smaller eigenvalue
    angle = 0.5 * np.arctan2(-2.0 * b, c - a)
    return np.column_stack([1.0 / np.sqrt(small), 1.0 / np.sqrt(large)]), angle


def make_tasks(
    raw: np.ndarray, index: np.ndarray, candidates: DiskCandidates, edge_width: float
) -> tuple[list[Task], int]:
    """Neighbourhoods of the candidates; also the number that leave the image."""
    rows, cols = raw.shape
    quads = _quadratic_form(candidates.axes, candidates.angle_rad)
    r0s = np.sqrt(np.maximum(candidates.axes[:, 0] * candidates.axes[:, 1], 1.0))
    tasks: list[Task] = []
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
            Task(
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
