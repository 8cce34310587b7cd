"""Disk refinement (the second step of :mod:`calibration.disks`): a Levenberg–Marquardt fit of
the disk model to the raw pixels around each candidate, on a process pool.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.disks._pool import finish, maybe_pool, start, worker_count
from calibration.disks._raw import checked_raw
from calibration.disks.detect import DiskCandidates
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import check_layout
from labkit.errors import DataError


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
    raw = checked_raw(raw, name)
    if not edge_width_px > 0:
        raise DataError(f"edge_width_px must be > 0, got {edge_width_px}")
    n_workers = worker_count(workers)
    with maybe_pool(n_workers) as pool:
        pending = start(raw, layout, candidates, per_channel, name, edge_width_px, pool, n_workers)
        return DiskFit(**finish(pending))
