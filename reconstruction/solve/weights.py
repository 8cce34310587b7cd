"""Regularisation weight selection (thesis §3.6, Algorithm 3).

Criteria, each evaluated on the solution I* for a weight tuple:

* ``"mdc"`` — the normalised minimum-distance criterion (3.22): squared distance of
  (‖A I* − y‖², S_1(I*), …) from the ideal point, each coordinate divided by its range.
  The ideal point and ranges come from solves with all weights at machine epsilon and
  with one or all at 10¹⁰, as the thesis prescribes. A range smaller than the selection
  solves' accuracy, (rtol·‖y‖)² for the misfit, counts as that accuracy: on a flat image
  every weight fits the data, and the solves' noise must not pick the weight.
* ``"msec"`` — mean squared error against a known latent image (3.23; simulation only).
* ``"dmc"`` — the demosaicing criterion (3.24): mean squared difference between the
  Green channel of the solution, ``(Ω B I*)_G``, and the bilinear demosaic of the raw
  Green channel. The thesis' cross-validation view: Green values the mosaic does not
  sample act as the validation set.
* ``"dmc-malvar"``, ``"dmc-menon"`` — the same criterion against the Green channel of a
  stronger demosaic (Malvar et al. 2004, Menon et al. 2007; :mod:`reconstruction.baselines`),
  which §3.6 anticipates ("set the smoothness … based on the latest demosaicing
  algorithms"). Bilinear interpolation blurs edges, so the weight that best matches it
  blurs them too; Menon's green keeps them, and with the VTV prior the weight matched to it
  suits edges and spectra alike: on the simulated rig with VTV and cubic Φ it picks a
  larger weight than the bilinear DMC on the ColorChecker, with a lower spectral error and
  a green edge error below Menon's own, and on the textured scene it escapes the DMC's
  failure mode at tiny weights (§3.6), with far lower spectral and colour errors (figures
  in docs/notes/larger-sigma.md, colour fringes along edges). Like Menon's demosaic
  itself, it relies on the colour channels' correlation, which narrow-band light breaks: the thesis
  keeps bilinear
  for that reason, and so does the default.

Algorithm 3 searches a log grid per weight: four log-spaced values from a_j to b_j, the
criterion at every combination of the two inner values, the interval narrowed around the
best, at least 6 and at most 19 rounds, stopping early when the best value improves by
less than 1e-6 relative. As in §5.4.1 the selection runs without the dispersion model, on
one or more representative patches; each solve is warm-started from the nearest previous
solution, and uses a looser tolerance than the final reconstruction.

Those loose solves stop short of the images the reconstruction returns, and where they
stop depends on the order of the search, so the weight they choose can move when the
reconstruction's tolerance is tightened. Where the reconstruction reaches the optimum —
non-negative L2-type problems with spectral smoothness, the default — ``exact=True``
scores every weight on the exact optimum instead (the dual active-set method, cheap
without Φ), and the criterion is then a smooth function of the weight that Brent's method
(golden sections and parabolic steps) minimises with one solve per step instead of
Algorithm 3's two per round. So does a single weight whose solves start from their own
initial estimate (L1-type and VTV terms, below): each weight's loose solve is then a
function of that weight alone, not of the search's order, and Brent's local search finds
the value Algorithm 3's grid finds, or one a little above it, in fewer than half the
solves (figures in docs/notes/solver.md, weight selection). Brent's method is local, so a walk
first brackets the minimum nearest :data:`SCAN_START` (:func:`_brent`): over the whole
range [ε, 1e10] it could stop on the plateau of tiny weights, where the data alone fix the
image and the criterion barely changes (figures in docs/notes/solver.md, weight
selection). At σ = 0 the problem's optimum is not the image ADMM's early stop returns, and the
criterion scored on
either (the optimum, or the early stop at the reconstruction's own tolerance) drifts to
tiny weights (the DMC's failure mode, §3.6), so the thesis' loose search stays there
(figures in docs/notes/solver.md, weight selection). So it does for the MDC, whose ideal point needs
solves at w = ε, whose exact optimum only the ridge fixes.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from calibration.multispectral import green_bilinear
from labkit.blas_threads import fixed_blas_threads
from labkit.errors import DataError
from reconstruction.baselines import BASELINES
from reconstruction.model.problem import Problem
from reconstruction.solve.solvers import solve

CRITERIA = ("mdc", "msec", "dmc", "dmc-malvar", "dmc-menon")
LOWEST, HIGHEST = float(np.finfo(np.float64).eps), 1e10
MIN_ROUNDS, MAX_ROUNDS, TOLERANCE = 6, 19, 1e-6
DECADES_TOLERANCE = 0.02
"""Width (log10 w) of the bracket at which the search of a single weight stops: 5 %."""
SCAN_START, SCAN_STEP = -5.0, 0.5
"""log10 w (normalised units) where the bracketing walk of a single weight starts, and its
step, decades: two decades below the smallest weight the criteria pick on the simulated and
real frames, where the plateau of tiny weights ends."""
SCAN_RISE = 1e-3
"""A relative increase of the criterion that ends the walk (loose solves' noise is below)."""


@dataclass
class WeightSelection:
    """Chosen weights and the search path.

    Attributes
    ----------
    weights : tuple of float
    criterion : str
    value : float
        Criterion at the chosen weights.
    rounds : int
    solves : int
        Number of patch solves made.
    path : list of dict
        Every evaluated tuple: ``{"weights": [...], "value": float}``.
    """

    weights: tuple[float, ...]
    criterion: str
    value: float
    rounds: int
    solves: int
    path: list[dict] = field(default_factory=list)


def reference_green(raw: np.ndarray, cfa: str, criterion: str) -> np.ndarray | None:
    """Green channel (rows, cols) float64 of the demosaic a DMC criterion compares against
    (bilinear for ``"dmc"``, else the one it names); None for the other criteria."""
    if criterion == "dmc":
        return green_bilinear(raw, cfa)
    if criterion.startswith("dmc-"):
        return BASELINES[criterion[4:]](raw, cfa)[..., 1].astype(np.float64)
    return None


class _Evaluator:
    """Solves the patch problems for a weight tuple and scores them."""

    def __init__(
        self,
        problems: Sequence[Problem],
        criterion: str,
        truths: Sequence[np.ndarray] | None,
        truth_matrix: np.ndarray | None,
        solve_options: dict,
    ) -> None:
        self.truth_matrix = truth_matrix
        self.problems = list(problems)
        self.criterion = criterion
        self.truths = truths
        self.solve_options = solve_options
        self.solves = 0
        self._cache: dict[tuple[float, ...], list[np.ndarray]] = {}
        self._greens = [reference_green(p.raw, p.formation.cfa, criterion) for p in self.problems]
        self.ideal = self.ranges = None
        # an L1 term moves ADMM's iterate by O(w/ρ) per iteration, so a solve warm-started
        # from a neighbouring weight's solution can stop at once with that solution, every
        # weight then scores alike and the search drifts to machine epsilon; each weight
        # starts from its own initial estimate instead: on the simulated ColorChecker the
        # DMC then picks sensible weights for VTV and for L1 with σ instead of tiny ones,
        # and for L1 without σ a slightly better image. L2 priors keep the warm start: with
        # their own starts the DMC picked a far smaller L2 weight and a worse image
        # (figures in docs/notes/larger-sigma.md, colour fringes along edges).
        # An exact solve's result does not depend on its start, so the order of the search
        # cannot move it; it starts from the nearest weight's optimum, which the active-set
        # rounds reach from in fewer steps than from the initial estimate (docs, speed).
        self.exact = solve_options.get("method") == "exact"
        self.own_starts = self.exact or any(t.norm == 1 for t in self.problems[0].terms)
        self._lock = threading.Lock()  # solutions() may run on several threads (prefetch)

    def solutions(self, weights: tuple[float, ...]) -> list[np.ndarray]:
        with self._lock:
            cached = self._cache.get(weights)
            if cached is not None:
                return cached
            start = self._nearest(weights) if self.exact or not self.own_starts else None
        out = []
        for i, p in enumerate(self.problems):
            if self.exact:
                x0 = None if start is None else start[i]
            elif self.own_starts:
                x0 = None  # solve()'s default: initial_estimate at these weights
            elif start is None:
                # the first weight starts from zeros (Algorithm 3): from solve()'s
                # default, the unconstrained optimum, ADMM at a tiny weight barely moves
                # before its test stops it, and the criteria then favour weights near
                # machine epsilon
                x0 = np.zeros(p.shape)
            else:
                x0 = start[i]
            out.append(solve(p.with_weights(weights), x0=x0, **self.solve_options).latent)
        with self._lock:
            self.solves += len(out)
            return self._cache.setdefault(weights, out)

    def prefetch(self, candidates: Sequence[tuple[float, ...]], workers: int) -> None:
        """Solve the `candidates` not yet solved on up to `workers` threads at once (their
        scores then come from the cache, in the search's own order). Only for searches
        whose solves do not depend on their order (:attr:`own_starts`)."""
        if workers < 2 or not self.own_starts:
            return
        with self._lock:
            missing = [w for w in dict.fromkeys(candidates) if w not in self._cache]
        if len(missing) < 2:
            return
        with ThreadPoolExecutor(min(workers, len(missing))) as pool:
            list(pool.map(self.solutions, missing))

    def _nearest(self, weights: tuple[float, ...]) -> list[np.ndarray] | None:
        if not self._cache:
            return None
        logs = np.log10(weights)
        key = min(self._cache, key=lambda k: float(np.sum((np.log10(k) - logs) ** 2)))
        return self._cache[key]

    def coordinates(self, weights: tuple[float, ...]) -> np.ndarray:
        """(misfit, S_1, …, S_N) summed over the patches."""
        total = np.zeros(1 + len(weights))
        for p, x in zip(self.problems, self.solutions(weights), strict=True):
            total += [p.data_misfit(x), *p.prior_values(x)]
        return total

    def prepare_mdc(self, count: int, rtol: float) -> None:
        low = (LOWEST,) * count
        ideal = [self.coordinates(low)[0]]
        for j in range(count):
            high_j = tuple(HIGHEST if i == j else LOWEST for i in range(count))
            ideal.append(self.coordinates(high_j)[1 + j])
        ideal = np.array(ideal)
        ranges = np.empty(count + 1)
        ranges[0] = self.coordinates((HIGHEST,) * count)[0] - ideal[0]
        ranges[1:] = self.coordinates(low)[1:] - ideal[1:]
        self.ideal = ideal
        # on a flat image every weight fits the data: the misfit's range is then the loose
        # solves' own error, and dividing by it lets that noise pick the weight (a striped
        # image at w = ε). Differences below the solves' accuracy, (rtol·‖y‖)², do not count.
        data = sum(float(np.sum(np.square(p.raw, dtype=np.float64))) for p in self.problems)
        floors = np.zeros(count + 1)
        floors[0] = rtol**2 * data
        ranges = np.maximum(np.abs(ranges), floors)
        self.ranges = np.where(ranges > 0, ranges, 1.0)

    def __call__(self, weights: tuple[float, ...]) -> float:
        if self.criterion == "mdc":
            c = self.coordinates(weights)
            return float(np.sum(((c - self.ideal) / self.ranges) ** 2))
        values = []
        for i, (p, x) in enumerate(zip(self.problems, self.solutions(weights), strict=True)):
            if self.criterion == "msec":
                estimate = x if self.truth_matrix is None else x @ self.truth_matrix.T
                values.append(np.mean((estimate - self.truths[i]) ** 2))
            else:
                colour = x @ p.formation.colour_matrix.T
                values.append(np.mean((colour[..., 1] - self._greens[i]) ** 2))
        return float(np.mean(values))


@fixed_blas_threads
def select_weights(
    problems: Sequence[Problem],
    *,
    criterion: str = "dmc",
    truths: Sequence[np.ndarray] | None = None,
    truth_matrix: np.ndarray | None = None,
    rtol: float = 1e-3,
    max_iter: int = 300,
    exact: bool = False,
    progress: Callable[[int, float], None] | None = None,
    workers: int = 1,
) -> WeightSelection:
    """Choose the prior weights by a criterion evaluated on patch solves (§3.6).

    With ``exact=True`` every weight is scored on the exact optimum of the patch problem;
    otherwise on the thesis' loose solves. A single weight whose score does not depend on
    the search's order (exact solves, or loose ones from each weight's own start: L1-type
    and VTV terms) is searched in log10 w over [ε, 1e10]: a walk from :data:`SCAN_START`
    brackets the nearest local minimum, and Brent's method narrows it until the bracket is
    about :data:`DECADES_TOLERANCE` wide; otherwise (warm-started loose solves,
    and two or more weights) by Algorithm 3 (module docstring).

    Parameters
    ----------
    problems : sequence of Problem
        Patch problems without dispersion, sharing their prior terms.
    criterion : {"mdc", "msec", "dmc", "dmc-malvar", "dmc-menon"}
    truths : sequence of ndarray, optional
        The true image of each patch (``"msec"`` only), normalised like the problem.
    truth_matrix : ndarray (m, n), optional
        Maps a latent pixel to the truth's channels (e.g. B at the band centres); default
        the identity.
    rtol, max_iter : float, int
        ADMM tolerance and iteration limit of the loose selection solves. They stop on
        ADMM's residual test alone (``settle=False`` of
        :class:`~reconstruction.solve.solvers.admm.ADMM`): at the thesis' loose tolerance they
        promise no distance to the optimum.
    exact : bool
        Score the exact optimum (the ``"exact"`` method of
        :func:`~reconstruction.solve.solvers.solve`; non-negative L2-type problems; found
        without Φ by the dual active-set method): the image a reconstruction with
        spectral smoothness returns to within 1e-4, so that the weight chosen does not
        depend on any solver tolerance.
    progress : callable, optional
        ``progress(round, best_value)`` after each round.
    workers : int
        Threads on which the bracketing walk of a single weight solves its next two
        weights at once (:func:`_first_minimum_bracket`); 1: one after the other. The
        weights and scores are those of the serial walk (its solves do not depend on
        their order), so the choice is the same.

    Raises
    ------
    DataError
        Unknown criterion, missing truths for ``"msec"``, or no prior terms.
    """
    if criterion not in CRITERIA:
        raise DataError(f"unknown weight criterion {criterion!r}; use one of {', '.join(CRITERIA)}")
    if not problems:
        raise DataError("weight selection needs at least one patch")
    count = len(problems[0].terms)
    if count == 0:
        raise DataError("the prior has no terms whose weights could be selected")
    if criterion == "msec" and (truths is None or len(truths) != len(problems)):
        raise DataError("the MSE criterion needs the true latent image of every patch (simulation)")
    evaluate = _Evaluator(
        problems,
        criterion,
        truths,
        truth_matrix,
        {"method": "exact"} if exact else {"rtol": rtol, "max_iter": max_iter, "settle": False},
    )
    if criterion == "mdc":
        evaluate.prepare_mdc(count, rtol)
    path: list[dict] = []

    def score(weights: tuple[float, ...]) -> float:
        value = evaluate(weights)
        path.append({"weights": list(weights), "value": value})
        return value

    # Brent's steps need a criterion that is a function of the weight alone: exact solves,
    # or solves from each weight's own start, not warm starts that follow the search's path
    if evaluate.own_starts and count == 1:

        def prefetch(log_weights: Sequence[float]) -> None:
            evaluate.prefetch([(float(10.0**v),) for v in log_weights], workers)

        rounds, weights, value = _brent(score, count, progress, prefetch)
    else:
        rounds, weights, value = _grid_search(score, count, progress)
    return WeightSelection(weights, criterion, value, rounds, evaluate.solves, path)


def _brent(
    score: Callable[[tuple[float, ...]], float],
    count: int,
    progress: Callable[[int, float], None] | None,
    prefetch: Callable[[Sequence[float]], None] | None = None,
) -> tuple[int, tuple[float, ...], float]:
    """The local minimum of one log10 weight nearest :data:`SCAN_START`, downhill: (solves,
    best weights, best value).

    A walk in steps of :data:`SCAN_STEP` decades brackets it (upwards from
    :data:`SCAN_START`, or downwards where the criterion rises there), then Brent's bounded
    method (golden sections and parabolic steps) narrows the bracket, with one solve per
    step. Brent's method alone over [ε, 1e10] is as local, but where it lands depends on
    its first golden sections: on the plateau of tiny weights, or in a second minimum at
    large weights, where the image is about as blurred as the bilinear reference the DMC
    scores against (docs/notes/solver.md, weight selection).
    """
    values: dict[float, float] = {}

    def criterion(log_weight: float) -> float:
        log_weight = float(log_weight)
        if log_weight not in values:
            values[log_weight] = score((float(10.0**log_weight),))
            if progress:
                progress(len(values), min(values.values()))
        return values[log_weight]

    low, high = _first_minimum_bracket(
        criterion, np.log10(LOWEST), np.log10(HIGHEST), prefetch=prefetch
    )
    # it stops once the bracket around its best point is at most 4/3 xatol wide
    scipy.optimize.minimize_scalar(
        criterion,
        bounds=(low, high),
        method="bounded",
        options={"xatol": 0.75 * DECADES_TOLERANCE},
    )
    best = min((x for x in values if low <= x <= high), key=values.__getitem__)
    return len(values), (float(10.0**best),), values[best]


def _first_minimum_bracket(
    criterion: Callable[[float], float],
    lowest: float,
    highest: float,
    *,
    prefetch: Callable[[Sequence[float]], None] | None = None,
) -> tuple[float, float]:
    """(low, high) log10 weights around the first local minimum a walk from
    :data:`SCAN_START` meets; a bound where the criterion falls all the way to it.

    `prefetch` is given the next two weights before each step: it may solve them at once
    (the walk goes on to the second unless the first ends it, so that solve is rarely
    wasted), and the criterion then reads them in the walk's order."""

    def rises(after: float, before: float) -> bool:
        return criterion(after) > criterion(before) + SCAN_RISE * abs(criterion(before))

    def clip(value: float) -> float:
        return min(max(value, lowest), highest)

    start = min(max(SCAN_START, lowest), highest - SCAN_STEP)
    if prefetch:
        prefetch([start, start + SCAN_STEP])
    step = SCAN_STEP if not rises(start + SCAN_STEP, start) else -SCAN_STEP
    behind, at = (start, start + step) if step > 0 else (start + SCAN_STEP, start)
    while True:
        ahead = clip(at + step)
        if prefetch:
            prefetch([ahead, clip(ahead + step)])
        if ahead == at or rises(ahead, at):
            return (min(behind, ahead), max(behind, ahead))
        behind, at = at, ahead


def _grid_search(
    score: Callable[[tuple[float, ...]], float],
    count: int,
    progress: Callable[[int, float], None] | None,
) -> tuple[int, tuple[float, ...], float]:
    """Algorithm 3 over `count` log10 weights: (rounds, best weights, best value)."""
    low = np.full(count, np.log10(LOWEST))
    high = np.full(count, np.log10(HIGHEST))
    best_weights: tuple[float, ...] = (LOWEST,) * count
    best_value = previous = np.inf
    rounds = 0
    for rounds in range(1, MAX_ROUNDS + 1):
        grids = [np.logspace(lo, hi, 4) for lo, hi in zip(low, high, strict=True)]
        candidates = list(itertools.product(*[g[1:3] for g in grids]))
        values = [score(tuple(float(v) for v in c)) for c in candidates]
        k = int(np.argmin(values))
        current = values[k]
        chosen = candidates[k]
        improved = current <= previous
        if improved:
            best_weights, best_value = tuple(float(w) for w in chosen), current
        if progress:
            progress(rounds, best_value)
        if improved:
            change = abs(current - previous) / max(abs(previous), 1e-300)
            if np.isfinite(previous) and change < TOLERANCE and rounds >= MIN_ROUNDS:
                break
            previous = current
        # narrow every weight's interval around its best inner value
        for j in range(count):
            index = 1 + list(grids[j][1:3]).index(chosen[j])
            low[j] = np.log10(grids[j][index - 1])
            high[j] = np.log10(grids[j][index + 1])
    return rounds, best_weights, float(best_value)
