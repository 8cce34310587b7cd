"""Patch-wise reconstruction on Dask (thesis §3.8.1), skipping work a patch does not need.

The (normalised) raw image is padded by ``pad_px`` on every side by reflection without
edge repetition, which keeps each pixel's Bayer colour, and split into chunks of about
``patch_px``. ``dask.array.map_overlap`` hands each chunk to :func:`solve_patch` with
``pad_px`` of its neighbours around it (the pre-padding supplies it at the image border);
the patch is solved with periodic priors and only its chunk is kept (the overlap is
discarded, not blended). The graph runs on Dask's local threaded scheduler by default,
or on any ``dask.distributed`` cluster.

What a patch may skip
---------------------
* **Negligible dispersion.** If the model moves no pixel of the patch by more than
  ``negligible_shift_px`` (0.05 px) at any wavelength the camera sees, Φ is dropped and the
  quadratic step is solved exactly by FFT instead of by conjugate gradients.
* **Flat patches.** If every Bayer channel is flat — the 95th percentile of same-channel
  differences 2 px apart exceeds what the image's noise alone gives (:func:`noise_sigma`)
  by less than ``flat_threshold`` times the patch's mean level — translating it changes
  nothing measurable, so Φ is dropped as well, and ADMM's start (below) is then nearly
  the answer: a flat patch converges in one or two iterations. Without the noise
  allowance a 0.2 % noise level alone would already make every patch "textured".
  With the edge-guided prior (``EdgeL2``) a flat patch has no edges to guide by: its edge
  weights are all 1, which makes its problem plain L2's, solved exactly by FFT without Φ.

Every patch with something to split (non-negativity, L1 terms) starts ADMM from
:func:`~reconstruction.solvers.admm.initial_estimate` — one FFT solve with Φ as mean
translations and the priors made quadratic — instead of the thesis' zeros: far fewer
ADMM iterations, and the first CG solve, the longest, no longer starts from nothing
(figures in the README, how it works).

Per-patch diagnostics (solver report, what was skipped, time) travel in an extra plane of
the output blocks, so they survive any scheduler, and are returned as records.
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import dask
import dask.array as da
import dask.callbacks
import numpy as np

from calibration.dispersion_model import DispersionModel
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import ConfigError, DataError
from reconstruction.image_formation import DISCRETE, LatentSpace, build_formation
from reconstruction.prior_terms import PriorTerm
from reconstruction.problem import Problem
from reconstruction.solvers.admm import solve

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
    "texture",
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
        Relative texture above the noise below which a patch counts as flat (None: never).
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
    exact: bool
    direct: bool
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
_NOISE_P95 = 1.96 * np.sqrt(2.0) * 1.15


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


def texture(raw: np.ndarray, noise: float = 0.0) -> float:
    """Relative texture of a raw patch above its noise.

    ``(p95 |same-channel 2-px difference| − 1.96 √2 · 1.15 σ) / mean level``, at least 0;
    with ``noise = 0`` the plain relative p95.
    """
    dx = np.abs(raw[:, 2:] - raw[:, :-2])
    dy = np.abs(raw[2:, :] - raw[:-2, :])
    level = max(float(np.mean(np.abs(raw))), 1e-12)
    p95 = max(np.percentile(dx, 95), np.percentile(dy, 95))
    return float(max(p95 - _NOISE_P95 * noise, 0.0) / level)


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
    record["texture"] = texture(raw, options.noise_sigma)
    flat = options.flat_threshold is not None and record["texture"] < options.flat_threshold
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
        exact_nonneg=solver.exact,
        direct=solver.direct,
    )
    report = solution.report
    # every CG solve: ADMM's quadratic steps and the active-set methods' restricted solves
    cg = report.cg_iterations + ([] if report.polish is None else report.polish.cg_iterations)
    record.update(
        iterations=report.iterations,
        converged=float(report.converged),
        flat=float(flat),
        phi=phi_state,
        cg_max=max(cg) if cg else 0,
        cg_mean=float(np.mean(cg)) if cg else 0.0,
        objective=report.objective,
        samples=formation.colour_matrices.shape[0],
        active=0 if report.polish is None else report.polish.active,
        polish_rounds=0 if report.polish is None else report.polish.rounds,
        exact=float(report.polish is not None and report.polish.status == "optimal"),
        seconds=time.perf_counter() - start,
    )
    return solution.latent, record


def _block(
    block: np.ndarray,
    *,
    block_id: tuple[int, ...] | None = None,
    core_starts: tuple[np.ndarray, np.ndarray],
    solve_kwargs: dict,
) -> np.ndarray:
    i, j = block_id[:2]
    pad = solve_kwargs["options"].pad_px
    counts = (len(core_starts[0]), len(core_starts[1]))
    # the overlap Dask added (none on the outer sides, where the pre-padding stands instead)
    top, left = (pad if i > 0 else 0), (pad if j > 0 else 0)
    bottom = pad if i < counts[0] - 1 else 0
    right = pad if j < counts[1] - 1 else 0
    # every extended block reaches pad_px beyond its chunk's image pixels
    origin = (int(core_starts[0][i]) - pad, int(core_starts[1][j]) - pad)
    latent, record = solve_patch(block, origin=origin, **solve_kwargs)
    core = latent[top : block.shape[0] - bottom, left : block.shape[1] - right]
    info = np.zeros(core.shape[:2])
    info.ravel()[: len(_FIELDS)] = [record[k] for k in _FIELDS]
    return np.concatenate([core, info[..., None]], axis=2)


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
        ``None``/``"threads"`` (local threads), ``"processes"``, ``"sync"``, a
        ``tcp://host:port`` address, or a ``dask.distributed.Client``.
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
    # the first and last chunk of each axis also hold the pre-padding
    chunks = tuple(
        (s[0] + pad, *s[1:-1], s[-1] + pad) if len(s) > 1 else (s[0] + 2 * pad,) for s in cores
    )
    array = da.from_array(padded, chunks=chunks)
    n = latent.channels
    solve_kwargs = dict(
        cfa=cfa, latent=latent, colour_gain=colour_gain, model=model, solver=solver, options=options
    )
    block = functools.partial(_block, core_starts=core_starts, solve_kwargs=solve_kwargs)
    result = da.map_overlap(
        block,
        array,
        depth={0: pad, 1: pad},
        boundary="none",
        trim=False,
        new_axis=[2],
        chunks=(array.chunks[0], array.chunks[1], (n + 1,)),
        dtype=np.float64,
        name="labkit-reconstruct-patch",
    )
    full = _compute(result, scheduler, progress, len(cores[0]) * len(cores[1]))
    records = []
    for i, (r0, core_rows) in enumerate(zip(core_starts[0], cores[0], strict=True)):
        for j, (c0, core_cols) in enumerate(zip(core_starts[1], cores[1], strict=True)):
            # each block wrote its record at its first output pixel (in the padded frame)
            first_row = 0 if i == 0 else int(r0) + pad
            first_col = 0 if j == 0 else int(c0) + pad
            values = full[
                first_row : first_row + core_rows, first_col : first_col + core_cols, n
            ].ravel()[: len(_FIELDS)]
            record = dict(zip(_FIELDS, (float(v) for v in values), strict=True))
            record["phi"] = PHI_STATES[int(record["phi"])]
            record["converged"] = bool(record["converged"])
            record["flat"] = bool(record["flat"])
            record["exact"] = bool(record["exact"])
            for key in ("iterations", "cg_max", "samples", "active", "polish_rounds"):
                record[key] = int(record[key])
            records.append(
                {"row": int(r0), "col": int(c0), "rows": core_rows, "cols": core_cols, **record}
            )
    return full[pad : pad + rows, pad : pad + cols, :n], records


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


def _compute(
    result: da.Array,
    scheduler: str | object | None,
    progress: Callable[[int, int], None] | None,
    total: int,
) -> np.ndarray:
    if scheduler is not None and not isinstance(scheduler, str):
        return scheduler.compute(result).result()  # a distributed.Client
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
            return client.compute(result).result()
    name = scheduler or "threads"
    if name not in ("threads", "processes", *SERIAL_SCHEDULERS):
        raise DataError(
            f"unknown scheduler {scheduler!r}; use threads, processes, sync, tcp://host:port, "
            "tls://host:port or a dask.distributed.Client"
        )
    with dask.config.set(scheduler=name), contextlib.ExitStack() as stack:
        if progress:
            stack.enter_context(_PatchProgress(progress, total))
        return result.compute()


class _PatchProgress(dask.callbacks.Callback):
    """Calls ``progress(done, total)`` as each patch task finishes."""

    def __init__(self, progress: Callable[[int, int], None], total: int) -> None:
        super().__init__()
        self.progress, self.total, self.done = progress, total, 0

    def _posttask(self, key, result, dsk, state, worker_id) -> None:
        name = key[0] if isinstance(key, tuple) else key
        if str(name).startswith("labkit-reconstruct-patch"):
            self.done += 1
            self.progress(self.done, self.total)


__all__: Sequence[str] = (
    "PHI_STATES",
    "SERIAL_SCHEDULERS",
    "PatchOptions",
    "SolverOptions",
    "chunk_sizes",
    "reconstruct_patches",
    "solve_patch",
)
