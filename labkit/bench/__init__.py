"""The benchmark harness behind ``labkit bench``: each stage writes JSON and Markdown."""

from labkit.bench.calibrate import bench_calibrate
from labkit.bench.capture import bench_capture
from labkit.bench.harness import (
    Measurement,
    Plot,
    Table,
    case_cells,
    case_details,
    fit_exponent,
    format_figure,
    machine_info,
    machine_line,
    measure,
    render_markdown,
    write_report,
)
from labkit.bench.hdr import bench_hdr
from labkit.bench.matrix import bench_matrix
from labkit.bench.reconstruct import bench_reconstruct
from labkit.bench.sim import bench_sim
from labkit.bench.solver import bench_solver

#: Stage name → benchmark function (rig path, repeats[, out][, full]) → (cases, notes); the
#: notes (sentences, :class:`Plot`, :class:`Table`) go under the stage's heading.
BENCHMARKS = {
    "sim": bench_sim,
    "capture": bench_capture,
    "hdr": bench_hdr,
    "calibrate": bench_calibrate,
    "reconstruct": bench_reconstruct,
    "solver": bench_solver,
    "matrix": bench_matrix,
}

__all__ = [
    "BENCHMARKS",
    "Measurement",
    "Plot",
    "Table",
    "bench_calibrate",
    "bench_capture",
    "bench_hdr",
    "bench_matrix",
    "bench_reconstruct",
    "bench_sim",
    "bench_solver",
    "case_cells",
    "case_details",
    "fit_exponent",
    "format_figure",
    "machine_info",
    "machine_line",
    "measure",
    "render_markdown",
    "write_report",
]
