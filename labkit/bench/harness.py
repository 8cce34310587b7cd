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


def accepts_out(function: Callable[..., Any]) -> bool:
    """Whether a benchmark function takes the output folder (to write plots there)."""
    return "out" in inspect.signature(function).parameters


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
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def write_report(out: str | Path, stages: dict[str, list[Measurement]], notes: list[str]) -> Path:
    """Write ``bench.json`` and ``bench.md`` into `out`; return the Markdown path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    machine = machine_info()
    payload = {
        "machine": machine,
        "stages": {stage: [asdict(m) for m in cases] for stage, cases in stages.items()},
        "notes": notes,
    }
    write_text_atomic(out / "bench.json", json.dumps(payload, indent=2) + "\n")
    lines = [
        "# labkit benchmark",
        "",
        f"{machine['cpu']}, {machine['cores']} cores; Python {machine['python']}, "
        f"numpy {machine['numpy']}, labkit {machine['labkit']}; {machine['date']}.",
        "",
    ]
    for stage, cases in stages.items():
        lines += [
            f"## {stage}",
            "",
            "| case | median time (s) | repeats | peak memory (MiB) | target (s) | result "
            "| details |",
            "|---|---:|---:|---:|---:|---|---|",
        ]
        for m in cases:
            verdict = "—" if m.passed is None else ("pass" if m.passed else "**FAIL**")
            target = "—" if m.target_s is None else f"{m.target_s:g}"
            details = ", ".join(f"{k}={_fmt(v)}" for k, v in m.extra.items())
            lines.append(
                f"| {m.name} | {m.seconds:.3f} | {len(m.times)} | {m.peak_mib:.0f} | {target} "
                f"| {verdict} | {details} |"
            )
        lines.append("")
    if notes:
        lines += ["## Notes", "", *[f"- {note}" for note in notes], ""]
    write_text_atomic(out / "bench.md", "\n".join(lines))
    return out / "bench.md"


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
