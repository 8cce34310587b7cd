"""Benchmark harness: timing with repeats, peak memory, machine facts, JSON + Markdown."""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import platform
import statistics
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from labkit.io.atomic import write_text_atomic


@dataclass
class Measurement:
    """One benchmark case.

    Attributes
    ----------
    name : str
        Case name, e.g. ``"sim.render.colorchecker"``.
    seconds : float
        Median wall time over `times`, s.
    times : list of float
        Every repeat's wall time, s.
    peak_mib : float
        Peak traced memory (numpy and Python allocations) of one run, MiB.
    target_s : float or None
        Time the issue requires, s; `passed` compares against it.
    extra : dict
        Case-specific figures (sizes, errors, counts).
    """

    name: str
    seconds: float
    times: list[float]
    peak_mib: float
    target_s: float | None = None
    passed: bool | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def measure(
    name: str,
    run: Callable[[], Any],
    *,
    repeats: int = 3,
    setup: Callable[[], Any] | None = None,
    target_s: float | None = None,
) -> Measurement:
    """Time `run` `repeats` times (calling `setup` untimed before each); trace memory once."""
    times = []
    peak = 0.0
    for index in range(repeats):
        if setup is not None:
            setup()
        if index == 0:
            tracemalloc.start()
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
        if index == 0:
            peak = tracemalloc.get_traced_memory()[1] / 2**20
            tracemalloc.stop()
    median = statistics.median(times)
    passed = None if target_s is None else median <= target_s
    return Measurement(name, median, times, peak, target_s, passed)


def peak_rss_mib() -> float:
    """Largest resident set of this process or of any finished child process so far, MiB."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024


def accepts(function: Callable[..., Any], name: str) -> bool:
    """Whether a benchmark function takes the keyword `name` (``out``, ``full``)."""
    return name in inspect.signature(function).parameters


def accepts_out(function: Callable[..., Any]) -> bool:
    """Whether a benchmark function takes the output folder (to write plots there)."""
    return accepts(function, "out")


def machine_info() -> dict[str, Any]:
    """Facts about this machine and the software versions that were measured."""
    import numpy
    import scipy

    import labkit

    cpu = platform.processor()
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as handle:  # Linux only
        cpu = next((line.split(":", 1)[1].strip() for line in handle if "model name" in line), cpu)
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "labkit": labkit.__version__,
        "commit": _commit(Path(labkit.__file__).parent),
        "load_average": _load_average(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def _commit(folder: Path) -> str | None:
    """The git commit of the checkout labkit runs from (``+`` if it has changes), or None."""
    import subprocess

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", *args], cwd=folder, capture_output=True, text=True, timeout=10, check=True
        )
        return done.stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        changed = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+" if changed else "")


def _load_average() -> list[float] | None:
    """The system's 1-, 5- and 15-minute load averages when the report is written: how busy
    the machine was while it was measured (Unix only)."""
    try:
        return [round(value, 2) for value in os.getloadavg()]
    except (AttributeError, OSError):
        return None


@dataclass
class Plot:
    """A figure written next to ``bench.md`` and embedded under its stage's heading.

    Attributes
    ----------
    title : str
        Alt text and caption.
    file : str
        PNG file name, relative to the report's folder.
    """

    title: str
    file: str


@dataclass
class Table:
    """A Markdown table under a stage's heading (cells already formatted).

    Attributes
    ----------
    title : str
        One line above the table.
    columns : list of str
        Column headers.
    rows : list of list of str
        Cells, one list per row.
    """

    title: str
    columns: list[str]
    rows: list[list[str]]


def repeat_timed(
    run: Callable[[], Any], *, repeats: int, short_s: float, trace: bool = False
) -> tuple[Any, list[float], float]:
    """Run `run` once, and `repeats` − 1 more times if that took less than `short_s` seconds.

    Parameters
    ----------
    run : callable
        The timed work; its first return value is kept.
    repeats : int
        Runs of a short case (median of them is reported).
    short_s : float
        A case whose first run takes this long or longer (s) runs once.
    trace : bool
        Trace the first run's memory (numpy and Python allocations) with tracemalloc.

    Returns
    -------
    first : Any
        `run`'s value from the first run.
    times : list of float
        Wall time of every run, s.
    peak_mib : float
        Peak traced memory of the first run, MiB (0 without `trace`).
    """
    if trace:
        tracemalloc.start()
    start = time.perf_counter()
    try:
        first = run()
        times = [time.perf_counter() - start]
        peak = tracemalloc.get_traced_memory()[1] / 2**20 if trace else 0.0
    finally:
        if trace:
            tracemalloc.stop()
    if times[0] < short_s:
        for _ in range(max(1, repeats) - 1):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
    return first, times, peak


def write_report(
    out: str | Path,
    stages: dict[str, list[Measurement]],
    notes: list[str],
    *,
    stage_notes: dict[str, list[str | Plot | Table]] | None = None,
) -> Path:
    """Write ``bench.json`` and ``bench.md`` into `out`; return the Markdown path.

    Parameters
    ----------
    out : str or Path
        Report folder (created); plots named by `stage_notes` should already be there.
    stages : dict
        Stage name → its cases.
    notes : list of str
        Notes about the whole run (a list at the end of the report).
    stage_notes : dict, optional
        Stage name → sentences, :class:`Plot` and :class:`Table` shown under that stage's
        heading after its cases.

    Returns
    -------
    Path
        ``out/bench.md``; the Markdown is :func:`render_markdown` of the JSON.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stage_notes = stage_notes or {}
    payload = {
        "machine": machine_info(),
        "stages": {stage: [asdict(m) for m in cases] for stage, cases in stages.items()},
        "notes": list(notes),
        "stage_notes": {
            stage: [_note_json(note) for note in items] for stage, items in stage_notes.items()
        },
        "plots": {
            stage: [note.file for note in items if isinstance(note, Plot)]
            for stage, items in stage_notes.items()
        },
    }
    write_text_atomic(out / "bench.json", json.dumps(payload, indent=2) + "\n")
    write_text_atomic(out / "bench.md", render_markdown(payload))
    return out / "bench.md"


def _note_json(note: str | Plot | Table) -> str | dict[str, Any]:
    if isinstance(note, Plot):
        return {"kind": "plot", **asdict(note)}
    if isinstance(note, Table):
        return {"kind": "table", **asdict(note)}
    return str(note)


def render_markdown(payload: dict[str, Any]) -> str:
    """The Markdown report of a ``bench.json`` payload (what :func:`write_report` writes).

    Parameters
    ----------
    payload : dict
        ``machine``, ``stages`` (stage → list of :class:`Measurement` fields), ``notes``
        and optionally ``stage_notes`` (stage → sentences or ``{"kind": "plot" | "table",
        …}``).

    Returns
    -------
    str
        The report: a table of cases per stage, that stage's notes, plots (relative image
        links) and tables under its heading, then the general notes.
    """
    lines = [
        "# labkit benchmark",
        "",
        machine_line(payload["machine"]),
        "",
    ]
    stage_notes = payload.get("stage_notes", {})
    for stage, cases in payload["stages"].items():
        lines += [
            f"## {stage}",
            "",
            "| case | median time (s) | repeats | peak memory (MiB) | target (s) | result "
            "| details |",
            "|---|---:|---:|---:|---:|---|---|",
        ]
        for m in cases:
            lines.append("| " + " | ".join([*case_cells(m), case_details(m)]) + " |")
        lines.append("")
        lines += _render_notes(stage_notes.get(stage, []))
    if payload.get("notes"):
        lines += ["## Notes", "", *[f"- {note}" for note in payload["notes"]], ""]
    return "\n".join(lines)


def machine_line(machine: dict[str, Any]) -> str:
    """One sentence on what was measured where: a report's :func:`machine_info`."""
    commit = f" at commit {machine['commit']}" if machine.get("commit") else ""
    load = machine.get("load_average")
    busy = f" (load average {load[0]:g} / {load[1]:g} / {load[2]:g} at the end)" if load else ""
    return (
        f"{machine['cpu']}, {machine['cores']} cores; Python {machine['python']}, "
        f"numpy {machine['numpy']}, labkit {machine['labkit']}{commit}; {machine['date']}{busy}."
    )


def case_cells(case: dict[str, Any]) -> list[str]:
    """A case's cells in a report's table of cases: name, median time (s), repeats, peak
    memory (MiB), target (s) and result (``pass``, ``**FAIL**`` or ``—`` without a target).

    Parameters
    ----------
    case : dict
        A :class:`Measurement`'s fields, as ``bench.json`` holds them.
    """
    passed = case.get("passed")
    target = case.get("target_s")
    return [
        case["name"],
        f"{case['seconds']:.3f}",
        str(len(case["times"])),
        f"{case['peak_mib']:.0f}",
        "—" if target is None else f"{target:g}",
        "—" if passed is None else ("pass" if passed else "**FAIL**"),
    ]


def case_details(case: dict[str, Any]) -> str:
    """A case's own figures (its ``extra``) as ``key=value`` pairs (:func:`format_figure`)."""
    return ", ".join(f"{k}={format_figure(v)}" for k, v in case.get("extra", {}).items())


def _render_notes(notes: list[str | dict[str, Any]]) -> list[str]:
    """Sentences as a bullet list, plots as image paragraphs, tables as Markdown tables."""
    lines: list[str] = []
    bullets = False
    for note in notes:
        if isinstance(note, str):
            lines.append(f"- {note}")
            bullets = True
            continue
        if bullets:
            lines.append("")
            bullets = False
        if note["kind"] == "plot":
            lines += [f"![{note['title']}]({note['file']})", ""]
        else:
            lines += [
                note["title"],
                "",
                "| " + " | ".join(note["columns"]) + " |",
                "|" + "---|" * len(note["columns"]),
                *["| " + " | ".join(row) + " |" for row in note["rows"]],
                "",
            ]
    if bullets:
        lines.append("")
    return lines


def fit_exponent(sizes: Any, seconds: Any) -> float:
    """Exponent p of ``seconds ∝ sizes**p``, least squares on log(seconds) against log(sizes).

    Parameters
    ----------
    sizes : array_like
        Problem sizes (e.g. pixels), > 0, at least two distinct values.
    seconds : array_like
        Times, s, > 0, one per size.

    Returns
    -------
    float
        The fitted slope p in log–log space.
    """
    import numpy as np

    x = np.log(np.asarray(sizes, dtype=np.float64))
    y = np.log(np.asarray(seconds, dtype=np.float64))
    if x.shape != y.shape or x.ndim != 1 or np.ptp(x) == 0:
        raise ValueError("fit_exponent needs as many times as sizes and ≥ 2 distinct sizes")
    dx = x - x.mean()
    return float(dx @ (y - y.mean()) / (dx @ dx))


def format_figure(value: Any) -> str:
    """A figure as the reports print it: floats to 4 significant digits, also inside lists and
    dictionaries (a case's nested figures, e.g. its per-patch cost)."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, dict):
        return "(" + ", ".join(f"{k}={format_figure(v)}" for k, v in value.items()) + ")"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_figure(v) for v in value) + "]"
    return str(value)
