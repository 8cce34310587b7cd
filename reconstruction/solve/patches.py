"""Patch-wise reconstruction on Dask (thesis §3.8.1), skipping work a patch does not need.

The (normalised) raw image is padded by ``pad_px`` on every side by reflection without
edge repetition, which keeps each pixel's Bayer colour, and split into chunks of about
``patch_px``. Each chunk, with ``pad_px`` of its neighbours around it (the pre-padding
supplies them at the image border), is one Dask task of :func:`solve_patch`; the patch is
solved with periodic priors and only its chunk is kept (the overlap is discarded, not
blended). The tasks run on local threads by default, on a persistent pool of local
processes (:mod:`~reconstruction.solve.worker_pool`, which share no interpreter lock), on the
calling thread, or on any ``dask.distributed`` cluster.

What a patch may skip
---------------------
* **Negligible dispersion.** If the model moves no pixel of the patch by more than
  ``negligible_shift_px`` (0.05 px) at any wavelength the camera sees, Φ is dropped and the
  quadratic step is solved exactly by FFT instead of by conjugate gradients.
* **Flat patches.** If every Bayer channel is flat — the largest same-channel difference
  2 px apart exceeds what the image's noise alone gives (:func:`noise_sigma`) by less
  than ``flat_threshold`` times the patch's mean level (:func:`largest_step`) —
  translating it changes nothing measurable, so Φ is dropped as well, and ADMM's start
  (below) is then nearly the answer: a flat patch converges in one or two iterations.
  Without the noise allowance a 0.2 % noise level alone would already make every patch
  "textured". The largest difference, not a percentile: an edge crossing a corner of a
  patch is a few percent of its pixels, and a percentile passes over it (the docs'
  choices page has the disk chart where it did). With the edge-guided prior (``EdgeL2``)
  a flat patch has no edges to guide by: its edge weights are all 1, which makes its
  problem plain L2's, solved exactly by FFT without Φ.

Every patch with something to split (non-negativity, L1 terms) starts ADMM from
:func:`~reconstruction.solve.solvers.quadratic.initial_estimate` — one FFT solve with Φ as mean
translations and the priors made quadratic — instead of the thesis' zeros: far fewer
ADMM iterations, and the first CG solve, the longest, no longer starts from nothing
(figures in docs/notes/solver.md).

Each task returns its patch's diagnostics (solver report, what was skipped, time) with
its image; they are returned as records.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

import dask
import dask.callbacks
import numpy as np
from scipy.special import ndtri

from calibration.dispersion_model import DispersionModel
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import ConfigError, DataError, LabkitError
from reconstruction.model.image_formation import DISCRETE, LatentSpace, build_formation
from reconstruction.model.prior_terms import PriorTerm
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers import solve
from reconstruction.solve.worker_pool import worker_pool

#: Meaning of the ``phi`` field of a patch record.
PHI_STATES = {0: "no model", 1: "used", 2: "skipped: negligible", 3: "skipped: flat patch"}
_FIELDS = (
    "iterations",
    "converged",
    "phi",
    "cg_max",
    "cg_mean",
    "objective",
    "seconds",
    "max_shift_px",
    "largest_step",
    "samples",
    "flat",
    "active",
    "polish_rounds",
    "exact",
    "formation_seconds",
)


@dataclass(frozen=True)
class PatchOptions:
    """How patches are cut and what they may skip.

    Attributes
    ----------
    patch_px : int
        Target chunk size, px (even); chunks are spread evenly over the image.
    pad_px : int
        Context on every side of a chunk, px (even); must exceed the largest dispersion.
    negligible_shift_px : float
        Drop Φ where no pixel moves more than this, px.
    flat_threshold : float
        Largest same-channel step above the noise, relative to the patch's level, below
        which a patch counts as flat (:func:`largest_step`; None: never).
    noise_sigma : float
        White-noise standard deviation of the (normalised) raw image, from
        :func:`noise_sigma`; 0 counts all variation as texture.
    """

    patch_px: int = 48
    pad_px: int = 8
    negligible_shift_px: float = 0.05
    flat_threshold: float | None = 0.01
    noise_sigma: float = 0.0

    def __post_init__(self) -> None:
        if self.patch_px < 8 or self.patch_px % 2:
            raise DataError(f"patch_px must be an even number ≥ 8, got {self.patch_px}")
        if self.pad_px < 2 or self.pad_px % 2:
            raise DataError(f"pad_px must be an even number ≥ 2, got {self.pad_px}")


@dataclass(frozen=True, kw_only=True)
class SolverOptions:
    """Problem and solver settings shared by all patches (normalised units).

    Every setting a user can choose is given explicitly: the defaults are resolved once,
    by :func:`reconstruction.choices.resolve_choices`, not here. `cg_rtol` and `step_px`
    are the method's constants (§3.2.5's 0.1 px dispersion sampling step).
    """

    terms: tuple[PriorTerm, ...]
    weights: tuple[float, ...]
    nonneg: bool
    rtol: float
    atol: float | None
    max_iter: int
    method: str
    interpolation: str
    smoothness: float
    cg_rtol: float = 1e-5
    step_px: float = 0.1


def chunk_sizes(length: int, target: int) -> tuple[int, ...]:
    """Even chunk sizes close to `target` that add up to the even `length`."""
    count = max(1, round(length / target))
    pairs = length // 2
    base, extra = divmod(pairs, count)
    return tuple(2 * (base + (1 if i < extra else 0)) for i in range(count))


NOISE_BLOCK_PX = 16

SCHEDULER_TIMEOUT_S = 20.0
"""How long a ``tcp://`` Dask scheduler may take to connect and answer the handshake, s."""
REMOTE_SCHEMES = ("tcp://", "tls://")
"""How the address of a ``dask.distributed`` scheduler starts."""
#: p95 of |a − b| for independent N(0, σ²) samples, in σ (1.96 √2), with 15 % allowance
#: for :func:`noise_sigma`'s low-percentile estimate (≈ 0.91 σ on pure noise).
_NOISE_ESTIMATE_MARGIN = 1.15
_NOISE_P95 = 1.96 * np.sqrt(2.0) * _NOISE_ESTIMATE_MARGIN
#: Chance that pure noise alone makes a flat patch's largest step exceed its allowance.
_NOISE_MAX_EXCEEDANCE = 0.01


def noise_sigma(raw: np.ndarray) -> float:
    """White-noise σ of a raw mosaic, in its units (0 for images under 24 px).

    Same-channel second differences ``x[i−2] − 2x[i] + x[i+2]`` (along rows and columns)
    cancel smooth shading; their median absolute value per 16×16-px block over
    ``0.6745 √6`` estimates σ there, and the 10th percentile over blocks keeps edges and
    texture (which only ever add) out of it. An image with no smooth area at all gets an
    overestimate, and so more patches taken as flat: pass ``flat_threshold=None`` there.
    """
    raw = np.asarray(raw, dtype=np.float64)
    d2x = np.abs(raw[:, 4:] - 2 * raw[:, 2:-2] + raw[:, :-4])[2:-2]
    d2y = np.abs(raw[4:] - 2 * raw[2:-2] + raw[:-4])[:, 2:-2]
    b = NOISE_BLOCK_PX
    rows, cols = (v - v % b for v in d2x.shape)
    if rows == 0 or cols == 0:
        return 0.0
    blocks = np.concatenate(
        [d[:rows, :cols].reshape(rows // b, b, cols // b, b) for d in (d2x, d2y)], axis=1
    )
    per_block = np.median(blocks.transpose(0, 2, 1, 3).reshape(rows // b, cols // b, -1), -1)
    return float(np.percentile(per_block, 10) / (0.6745 * np.sqrt(6.0)))


def _same_channel_steps(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """|differences 2 px apart| along rows and along columns (same Bayer channel), and the
    patch's mean level (at least 1e-12)."""
    dx = np.abs(raw[:, 2:] - raw[:, :-2])
    dy = np.abs(raw[2:, :] - raw[:-2, :])
    return dx, dy, max(float(np.mean(np.abs(raw))), 1e-12)


def texture(raw: np.ndarray, noise: float = 0.0) -> float:
    """Relative texture of a raw patch above its noise.

    ``(p95 |same-channel 2-px difference| − 1.96 √2 · 1.15 σ) / mean level``, at least 0;
    with ``noise = 0`` the plain relative p95.
    """
    dx, dy, level = _same_channel_steps(raw)
    p95 = max(np.percentile(dx, 95), np.percentile(dy, 95))
    return float(max(p95 - _NOISE_P95 * noise, 0.0) / level)


def largest_step(raw: np.ndarray, noise: float = 0.0) -> float:
    """Largest same-channel step of a raw patch above its noise, relative to its level.

    ``(max |same-channel difference 2 px apart| − z √2 · 1.15 σ) / mean level``, at least
    0, where z is the normal quantile that pure noise exceeds in one of the patch's
    differences with probability 1 % (about 4.9 for a 64 × 64 patch); with ``noise = 0``
    the plain relative maximum. Unlike :func:`texture`'s 95th percentile, one edge
    crossing a corner of the patch counts: translating the patch moves that edge.
    """
    dx, dy, level = _same_channel_steps(raw)
    count = dx.size + dy.size
    if count == 0:
        return 0.0
    z = float(ndtri(1.0 - _NOISE_MAX_EXCEEDANCE / (2 * count)))
    allowance = z * np.sqrt(2.0) * _NOISE_ESTIMATE_MARGIN * noise
    return float(max(max(dx.max(), dy.max()) - allowance, 0.0) / level)


def max_dispersion(
    model: DispersionModel,
    latent: LatentSpace,
    origin: tuple[int, int],
    shape: tuple[int, int],
) -> float:
    """Largest displacement |e| (px) on a 5×5 grid over the patch at 7 wavelengths (or channels)."""
    ys = origin[0] + np.linspace(0, shape[0] - 1, 5)
    xs = origin[1] + np.linspace(0, shape[1] - 1, 5)
    gx, gy = np.meshgrid(xs, ys)
    if model.variables == "xylambda":
        waves = latent.phi_nm if latent.kernel == DISCRETE else np.linspace(*latent.support_nm, 7)
        ex, ey = model.displacement(gx[..., None], gy[..., None], waves[None, None, :])
        return float(np.sqrt(np.max(ex * ex + ey * ey)))
    longest = 0.0
    for channel in model.channels:
        ex, ey = model.displacement(gx, gy, channel=channel)
        longest = max(longest, float(np.sqrt(np.max(ex * ex + ey * ey))))
    return longest


@fixed_blas_threads
def solve_patch(
    raw: np.ndarray,
    *,
    origin: tuple[int, int],
    cfa: str,
    latent: LatentSpace,
    colour_gain: float,
    model: DispersionModel | None,
    solver: SolverOptions,
    options: PatchOptions,
) -> tuple[np.ndarray, dict]:
    """Solve one padded patch; returns its latent image (rows, cols, n) and a record."""
    start = time.perf_counter()
    shape = raw.shape
    record = dict.fromkeys(_FIELDS, 0.0)
    record["largest_step"] = largest_step(raw, options.noise_sigma)
    flat = options.flat_threshold is not None and record["largest_step"] < options.flat_threshold
    phi_state = 0
    use_model = None
    if model is not None:
        shift = max_dispersion(model, latent, origin, shape)
        record["max_shift_px"] = shift
        if shift < options.negligible_shift_px:
            phi_state = 2
        elif flat:
            phi_state = 3
        else:
            phi_state, use_model = 1, model
    built = time.perf_counter()
    formation = build_formation(
        latent,
        shape,
        cfa,
        model=use_model,
        origin=origin,
        overhang_px=options.pad_px,
        step_px=solver.step_px,
        colour_gain=colour_gain,
        interpolation=solver.interpolation,
    )
    record["formation_seconds"] = time.perf_counter() - built
    # a flat patch has no edges to guide by: unit weights keep its problem circulant
    guided = any(t.guided for t in solver.terms)
    problem = Problem(
        formation,
        raw,
        solver.terms,
        solver.weights,
        solver.nonneg,
        smoothness=solver.smoothness,
        edge_weights=np.ones((*shape, 2)) if guided and flat else None,
    )
    solution = solve(
        problem,
        rtol=solver.rtol,
        atol=solver.atol,
        max_iter=solver.max_iter,
        cg_rtol=solver.cg_rtol,
        method=solver.method,
    )
    report = solution.report
    # every CG solve: ADMM's quadratic steps and the active-set methods' restricted solves
    cg = report.cg_iterations + ([] if report.polish is None else report.polish.cg_iterations)
    record.update(
        iterations=int(report.iterations),
        converged=bool(report.converged),
        flat=bool(flat),
        phi=PHI_STATES[phi_state],
        cg_max=int(max(cg)) if cg else 0,
        cg_mean=float(np.mean(cg)) if cg else 0.0,
        objective=float(report.objective),
        samples=int(formation.colour_matrices.shape[0]),
        active=0 if report.polish is None else int(report.polish.active),
        polish_rounds=0 if report.polish is None else int(report.polish.rounds),
        exact=report.polish is not None and report.polish.status == "optimal",
        seconds=time.perf_counter() - start,
    )
    return solution.latent, record


def _solve_block(
    block: np.ndarray, core: tuple[int, int, int, int], origin: tuple[int, int], solve_kwargs: dict
) -> tuple[np.ndarray, dict]:
    """One patch task: solve the padded `block` and keep its core rows and columns
    (``core`` = top, bottom, left, right offsets in the block)."""
    latent, record = solve_patch(block, origin=origin, **solve_kwargs)
    top, bottom, left, right = core
    return latent[top:bottom, left:right], record


@fixed_blas_threads
def reconstruct_patches(
    raw: np.ndarray,
    *,
    cfa: str,
    latent: LatentSpace,
    colour_gain: float,
    model: DispersionModel | None,
    solver: SolverOptions,
    options: PatchOptions = PatchOptions(),
    scheduler: str | object | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, list[dict]]:
    """Reconstruct a whole normalised raw image patch by patch.

    Parameters
    ----------
    raw : ndarray (rows, cols)
        Normalised raw mosaic, even size.
    cfa, latent, colour_gain, model, solver, options
        As for :func:`solve_patch`.
    scheduler : str or distributed.Client, optional
        ``"processes"`` (a persistent pool of local processes,
        :mod:`~reconstruction.solve.worker_pool`), ``"threads"``, ``"sync"``, a
        ``tcp://host:port`` address, or a ``dask.distributed.Client``; default
        :func:`default_scheduler`.
    progress : callable, optional
        ``progress(done, total)`` after each patch (local schedulers only).

    Returns
    -------
    latent : ndarray (rows, cols, n)
        Normalised latent image.
    records : list of dict
        One per patch: ``row``, ``col`` (chunk origin), ``rows``, ``cols`` and the fields
        of :func:`solve_patch`, ``phi`` decoded by :data:`PHI_STATES`.
    """
    rows, cols = raw.shape
    if rows % 2 or cols % 2:
        raise DataError(f"raw image size {rows}×{cols} must be even (whole Bayer blocks)")
    pad = options.pad_px
    if pad > min(rows, cols) - 1:
        raise DataError(
            f"the image ({rows}×{cols}) is too small for pad_px={pad}; use a smaller pad_px"
        )
    padded = np.pad(raw, pad, mode="reflect")
    cores = (chunk_sizes(rows, options.patch_px), chunk_sizes(cols, options.patch_px))
    core_starts = tuple(np.cumsum([0, *sizes[:-1]]) for sizes in cores)
    solve_kwargs = dict(
        cfa=cfa, latent=latent, colour_gain=colour_gain, model=model, solver=solver, options=options
    )
    # each patch is its chunk with pad_px of the (reflection-padded) image around it: one
    # task with its own block, no tasks that cut and join neighbours' overlaps
    tasks, places = [], []
    for i, (r0, core_rows) in enumerate(zip(core_starts[0], cores[0], strict=True)):
        for j, (c0, core_cols) in enumerate(zip(core_starts[1], cores[1], strict=True)):
            r0, c0 = int(r0), int(c0)
            block = padded[r0 : r0 + core_rows + 2 * pad, c0 : c0 + core_cols + 2 * pad]
            core = (pad, pad + core_rows, pad, pad + core_cols)
            tasks.append(
                dask.delayed(_solve_block, pure=False)(
                    block,
                    core,
                    (r0 - pad, c0 - pad),
                    solve_kwargs,
                    dask_key_name=f"{PATCH_TASK}-{i}-{j}",
                )
            )
            places.append((r0, c0, core_rows, core_cols))
    results = _compute(tasks, scheduler, progress)
    full = np.empty((rows, cols, latent.channels))
    records = []
    for (r0, c0, core_rows, core_cols), (core, record) in zip(places, results, strict=True):
        full[r0 : r0 + core_rows, c0 : c0 + core_cols] = core
        records.append({"row": r0, "col": c0, "rows": core_rows, "cols": core_cols, **record})
    return full, records


def probe_scheduler(address: str, *, timeout_s: float | None = None) -> None:
    """Check that a ``tcp://`` or ``tls://host:port`` Dask scheduler answers, within
    `timeout_s`.

    A scheduler greets every new connection at once (its handshake); something that
    accepts the connection and stays silent would make ``distributed.Client`` wait for
    ever, so the greeting is awaited here with a deadline. Over ``tls://`` the TLS
    handshake comes first, with the credentials of Dask's configuration
    (:func:`scheduler_security`).

    Raises
    ------
    DataError
        Nothing listens there, it does not greet within the deadline
        (:data:`SCHEDULER_TIMEOUT_S` by default), or the TLS handshake fails.
    ConfigError
        ``tls://`` without TLS credentials in Dask's configuration.
    """
    import socket
    import ssl

    timeout_s = SCHEDULER_TIMEOUT_S if timeout_s is None else timeout_s
    scheme, host, port = scheduler_address(address)
    context = None
    if scheme == "tls":
        context = scheduler_security().get_connection_args("client")["ssl_context"]
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as s:
            s.settimeout(timeout_s)
            if context is not None:
                with context.wrap_socket(s, server_hostname=host) as secure:
                    greeting = secure.recv(1)
            else:
                greeting = s.recv(1)
    except TimeoutError:
        raise DataError(
            f"Dask scheduler {address} did not answer within {timeout_s:g} s; check that a "
            "`dask scheduler` listens there, or use --scheduler threads"
        ) from None
    except ssl.SSLError as error:
        raise DataError(
            f"Dask scheduler {address}: the TLS handshake failed ({error.reason or error}); "
            "check that Dask's TLS settings (distributed.comm.tls.*) hold this cluster's "
            "CA and a client certificate it accepts"
        ) from None
    except OSError as error:
        raise DataError(
            f"cannot reach the Dask scheduler {address} ({error}); start one "
            "(`dask scheduler`) or use --scheduler threads"
        ) from None
    if not greeting:
        raise DataError(
            f"Dask scheduler {address} closed the connection without a greeting; is it a "
            "`dask scheduler`?"
        )


def scheduler_address(address: str) -> tuple[str, str, int]:
    """``tcp://HOST:PORT`` or ``tls://HOST:PORT`` → (scheme, host, port); an IPv6 host may
    be bracketed. :class:`ConfigError` for anything else."""
    scheme, _, rest = address.partition("://")
    host, _, port = rest.rpartition(":")
    host = host.strip("[]")
    if f"{scheme}://" not in REMOTE_SCHEMES or not host or not port.isdigit():
        raise ConfigError(
            f"{address!r} is not a Dask scheduler address: give tcp://HOST:PORT or tls://HOST:PORT"
        )
    return scheme, host, int(port)


def scheduler_security() -> Any:
    """The ``distributed.Security`` for ``tls://`` schedulers, from Dask's configuration
    (``distributed.comm.tls.ca-file``, ``.client.cert``, ``.client.key``, e.g. set by
    ``DASK_DISTRIBUTED__COMM__TLS__CA_FILE``); :class:`ConfigError` when it is incomplete."""
    from distributed import Security

    security = Security()
    if not (security.tls_ca_file and security.tls_client_cert):
        raise ConfigError(
            "a tls:// Dask scheduler needs TLS credentials in Dask's configuration: set "
            "distributed.comm.tls.ca-file and distributed.comm.tls.client.cert (and .key) in "
            "~/.config/dask/distributed.yaml, or DASK_DISTRIBUTED__COMM__TLS__CA_FILE, "
            "DASK_DISTRIBUTED__COMM__TLS__CLIENT__CERT and DASK_DISTRIBUTED__COMM__TLS__CLIENT__KEY"
        )
    return security


SERIAL_SCHEDULERS = ("sync", "synchronous", "single-threaded")
"""Dask's names for its scheduler that runs every task on the calling thread."""

LOCAL_SCHEDULERS = ("processes", "threads", *SERIAL_SCHEDULERS)
"""The local schedulers by name."""

PATCH_TASK = "labkit-reconstruct-patch"
"""How the key of every patch task starts."""


def default_scheduler() -> str:
    """``"threads"``. The pool of processes is chosen by name: its workers import the
    caller's main module, as every ``spawn``-type pool's do, which runs a script without an
    ``if __name__ == "__main__"`` guard again."""
    return "threads"


def _compute(
    tasks: list[Any],
    scheduler: str | object | None,
    progress: Callable[[int, int], None] | None,
) -> list[Any]:
    if scheduler is not None and not isinstance(scheduler, str):
        return scheduler.gather(scheduler.compute(tasks))  # a distributed.Client
    if isinstance(scheduler, str) and scheduler.startswith(REMOTE_SCHEMES):
        from distributed import Client

        probe_scheduler(scheduler)
        security = scheduler_security() if scheduler.startswith("tls://") else None
        try:
            client = Client(scheduler, timeout=SCHEDULER_TIMEOUT_S, security=security)
        except (OSError, TimeoutError) as error:
            raise DataError(
                f"Dask scheduler {scheduler} did not answer within {SCHEDULER_TIMEOUT_S:g} s "
                f"({error}); check that a `dask scheduler` listens there"
            ) from None
        with client:
            return client.gather(client.compute(tasks))
    name = scheduler or default_scheduler()
    if name not in LOCAL_SCHEDULERS:
        raise DataError(
            f"unknown scheduler {scheduler!r}; use processes, threads, sync, tcp://host:port, "
            "tls://host:port or a dask.distributed.Client"
        )
    settings: dict[str, Any] = {"scheduler": name}
    if name == "processes":
        # one patch per message: patches take 0.05–0.5 s each, Dask's default of 6 leaves
        # one worker idle while the other finishes the last batch
        settings.update(pool=worker_pool(), chunksize=1)
    with dask.config.set(settings), contextlib.ExitStack() as stack:
        if progress:
            stack.enter_context(_PatchProgress(progress, len(tasks)))
        try:
            return list(dask.compute(*tasks))
        except BrokenProcessPool:
            raise LabkitError(
                "a worker process solving the patches died (killed, or out of memory); "
                "nothing was written: run again (a new pool starts), or use --scheduler "
                "threads"
            ) from None


class _PatchProgress(dask.callbacks.Callback):
    """Calls ``progress(done, total)`` as each patch task finishes."""

    def __init__(self, progress: Callable[[int, int], None], total: int) -> None:
        super().__init__()
        self.progress, self.total, self.done = progress, total, 0

    def _posttask(self, key, result, dsk, state, worker_id) -> None:
        name = key[0] if isinstance(key, tuple) else key
        if str(name).startswith(PATCH_TASK):
            self.done += 1
            self.progress(self.done, self.total)


__all__: Sequence[str] = (
    "LOCAL_SCHEDULERS",
    "PATCH_TASK",
    "PHI_STATES",
    "SERIAL_SCHEDULERS",
    "PatchOptions",
    "SolverOptions",
    "chunk_sizes",
    "default_scheduler",
    "reconstruct_patches",
    "solve_patch",
)
