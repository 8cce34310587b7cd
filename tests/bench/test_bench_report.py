"""The benchmark report: exponent fit, repeats, summaries and Markdown from known JSON."""

from __future__ import annotations

import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from labkit.bench.calibrate import keypoint_table
from labkit.bench.harness import (
    Measurement,
    Plot,
    Table,
    fit_exponent,
    machine_info,
    machine_line,
    render_markdown,
    repeat_timed,
    write_report,
)
from labkit.bench.reconstruct import skipping_line
from labkit.bench.reconstruct_scaling import scaling_summary, scaling_table


@pytest.mark.parametrize("exponent", [1.0, 1.5])
def test_fit_exponent_recovers_a_planted_power_law(exponent: float) -> None:
    pixels = np.array([256.0, 512.0, 1024.0, 2048.0]) ** 2
    seconds = 3.7e-6 * pixels**exponent
    assert abs(fit_exponent(pixels, seconds) - exponent) < 1e-9


def test_fit_exponent_is_least_squares_in_log_log() -> None:
    pixels = [1.0, 2.0, 4.0]
    seconds = [1.0, 2.0, 8.0]  # log2: slopes 1 then 2 → least-squares slope 1.5
    assert fit_exponent(pixels, seconds) == pytest.approx(1.5, abs=1e-12)
    with pytest.raises(ValueError, match="distinct sizes"):
        fit_exponent([5.0, 5.0], [1.0, 2.0])


def test_repeat_timed_repeats_only_short_cases() -> None:
    calls: list[int] = []

    def run() -> int:
        calls.append(1)
        return len(calls)

    first, times, peak = repeat_timed(run, repeats=3, short_s=60.0, trace=True)
    assert first == 1 and len(times) == 3 and len(calls) == 3 and peak >= 0.0
    calls.clear()
    first, times, peak = repeat_timed(run, repeats=3, short_s=0.0)
    assert first == 1 and len(times) == 1 and peak == 0.0


def _size_case(side: int, seconds: float, solve: float) -> Measurement:
    return Measurement(
        f"scaling: {side}×{side}",
        seconds,
        [seconds],
        100.0 + side / 10,
        extra={
            "image": f"{side}×{side}",
            "pixels": side * side,
            "solve_s": solve,
            "weight_s": seconds - solve,
            "spectral_rmse_rel": 0.25,
            "patches": side // 16,
            "flat": 0,
        },
    )


def test_scaling_summary_and_table() -> None:
    sides = [256, 512, 1024, 2048]
    linear = [_size_case(s, 1e-5 * s * s + 1.0, 1e-5 * s * s) for s in sides]
    summary = scaling_summary(linear)
    assert summary.passed is True
    assert summary.extra["exponent_solve"] == pytest.approx(1.0, abs=1e-9)
    assert 0.7 < summary.extra["exponent"] < 0.9  # the constant weight selection
    assert summary.seconds == pytest.approx(sum(m.seconds for m in linear))
    table = scaling_table(linear, summary)
    assert "p = " in table.title and "pass (≤ 1.2)" in table.title
    assert table.rows[-1][:4] == ["2048×2048", "4,194,304", "42.94", "1"]
    steep = [_size_case(s, 1e-7 * (s * s) ** 1.3, 1e-7 * (s * s) ** 1.3) for s in sides]
    assert scaling_summary(steep).passed is False


def test_skipping_line_states_time_patches_and_errors() -> None:
    skip = Measurement(
        "flat",
        2.0,
        [2.0],
        1.0,
        extra={"flat_fraction": 0.8, "flat": 40, "patches": 50, "spectral_rmse_rel": 0.1000},
    )
    no_skip = Measurement(
        "no skip",
        8.0,
        [8.0],
        1.0,
        extra={"flat_fraction": 0.8, "flat": 40, "patches": 50, "spectral_rmse_rel": 0.1005},
    )
    assert skipping_line(skip, no_skip) == (
        "Adaptive skipping saved 75% of the time on the 80%-flat scene: 2.00 s with "
        "skipping, 8.00 s without; 40 of 50 patches skipped as flat; spectral RMSE 0.1000 "
        "with, 0.1005 without (equal within 1 %)."
    )


def test_keypoint_table_pairs_models_by_count() -> None:
    def case(kind: str, count: int, seconds: float, rms: float) -> Measurement:
        extra = {"model": kind, "keypoints": count, "error_vs_truth": {"rms_px": rms}}
        return Measurement(kind, seconds, [seconds], 1.0, extra=extra)

    table = keypoint_table(
        [case("polynomial", 100, 0.5, 0.02), case("spline", 100, 1.5, 0.03),
         case("polynomial", 400, 1.0, 0.01)]
    )  # fmt: skip
    assert table.columns[1:3] == ["polynomial fit (s)", "polynomial RMS error (px)"]
    assert table.rows == [
        ["400", "1.000", "0.0100", "—", "—"],
        ["100", "0.500", "0.0200", "1.500", "0.0300"],
    ]


KNOWN = {
    "machine": {
        "cpu": "Test CPU",
        "cores": 2,
        "python": "3.11.0",
        "numpy": "2.0",
        "labkit": "0.1",
        "date": "2025-01-01",
    },
    "stages": {
        "reconstruct": [
            {
                "name": "scaling: time ∝ pixels^p, 256×256 … 2048×2048",
                "seconds": 12.5,
                "times": [1.0, 2.0, 3.5, 6.0],
                "peak_mib": 812.4,
                "target_s": None,
                "passed": True,
                "extra": {"exponent": 0.98},
            }
        ]
    },
    "notes": ["general"],
    "stage_notes": {
        "reconstruct": [
            "a sentence",
            {"kind": "plot", "title": "Time against size", "file": "reconstruct_scaling.png"},
            {"kind": "table", "title": "Sizes:", "columns": ["image", "s"], "rows": [["a", "1"]]},
        ]
    },
}


def test_markdown_from_known_json() -> None:
    lines = render_markdown(KNOWN).splitlines()
    assert "Test CPU, 2 cores; Python 3.11.0, numpy 2.0, labkit 0.1; 2025-01-01." in lines
    heading = lines.index("## reconstruct")
    case = (
        "| scaling: time ∝ pixels^p, 256×256 … 2048×2048 | 12.500 | 4 | 812 | — | pass "
        "| exponent=0.98 |"
    )
    assert lines.index(case) > heading
    bullet, image = (
        lines.index("- a sentence"),
        lines.index("![Time against size](reconstruct_scaling.png)"),
    )
    table = lines.index("| image | s |")
    assert heading < bullet < image < table < lines.index("## Notes")
    assert lines[table - 2 : table + 3] == ["Sizes:", "", "| image | s |", "|---|---|", "| a | 1 |"]
    assert lines[bullet + 1] == ""  # the bullet list ends before the image paragraph
    assert "- general" in lines


def test_markdown_details_round_nested_figures() -> None:
    """Floats in a case's details keep 4 significant digits inside lists and dictionaries
    too (the per-patch cost of a reconstruction), instead of Python's full repr."""
    case = Measurement(
        "r",
        1.0,
        [1.0],
        1.0,
        extra={"cost": {"ms": 182.56082500010962, "n": 56}, "w": [0.01783236790167924]},
    )
    payload = {**KNOWN, "stages": {"reconstruct": [asdict(case)]}, "stage_notes": {}}
    (row,) = [line for line in render_markdown(payload).splitlines() if line.startswith("| r |")]
    assert row.endswith("| cost=(ms=182.6, n=56), w=[0.01783] |")


def test_write_report_keeps_json_and_markdown_in_step(tmp_path: Path) -> None:
    case = Measurement("render", 2.0, [1.9, 2.0, 2.1], 100.0, 15.0, True, {"size": "64x96"})
    notes = {"sim": ["sentence", Plot("A plot", "sim.png"), Table("T", ["a"], [["1"]])]}
    md = write_report(tmp_path, {"sim": [case]}, [], stage_notes=notes)
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["plots"] == {"sim": ["sim.png"]}
    assert data["stage_notes"]["sim"][1] == {"kind": "plot", "title": "A plot", "file": "sim.png"}
    assert md.read_text() == render_markdown(data)
    assert "![A plot](sim.png)" in md.read_text()
    assert "## Notes" not in md.read_text()


def test_cli_runs_the_full_cases_for_all_and_puts_notes_under_stages(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import labkit.bench
    from labkit.cli import main

    seen: dict[str, object] = {}

    def fake_full(rig_path, *, repeats: int, out: Path, full: bool | None):
        seen["full"] = full
        (out / "fake.png").write_bytes(b"png")
        case = Measurement("fast case", 0.5, [0.5] * repeats, 1.0, 1.0, True)
        return [case], ["a stage note", Plot("Fake plot", "fake.png")]

    def fake_plain(rig_path, *, repeats: int):
        return [Measurement("plain case", 0.1, [0.1], 1.0)], []

    for stage in list(labkit.bench.BENCHMARKS):
        monkeypatch.setitem(labkit.bench.BENCHMARKS, stage, fake_plain)
    monkeypatch.setitem(labkit.bench.BENCHMARKS, "reconstruct", fake_full)
    monkeypatch.delenv("LABKIT_BENCH_FULL", raising=False)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["bench", "all", "--out", str(out), "--repeats", "1"]) == 0
    assert seen["full"] is True
    text = (out / "bench.md").read_text()
    section = text.split("## reconstruct", 1)[1]
    assert "- a stage note" in section and "![Fake plot](fake.png)" in section
    assert main(["bench", "reconstruct", "--out", str(out)]) == 0
    assert seen["full"] is None  # the stage reads LABKIT_BENCH_FULL itself
    assert main(["bench", "all", "--no-full", "--out", str(out)]) == 0
    assert seen["full"] is False


def test_full_run_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    from labkit.bench.reconstruct import full_run

    monkeypatch.delenv("LABKIT_BENCH_FULL", raising=False)
    assert full_run(None) is False and full_run(True) is True
    monkeypatch.setenv("LABKIT_BENCH_FULL", "1")
    assert full_run(None) is True and full_run(False) is False


def test_plots_are_written(tmp_path: Path) -> None:
    from labkit.bench.plots import plot_scaling, plot_time_vs_error

    plot_time_vs_error(
        {"a": [(1.0, 0.1, "x"), (2.0, 0.05, "y")], "b": [(0.5, 0.2, "")], "empty": []},
        tmp_path / "te.png",
        title="t",
        error_label="e",
        connect=True,
        reference=("bound", 0.01),
        log_error=True,
    )
    plot_scaling(
        [1e4, 4e4, 16e4], {"total": ([1.0, 4.0, 16.0], 1.0)}, tmp_path / "s.png", title="s"
    )
    for name in ("te.png", "s.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    assert not list(tmp_path.glob(".*.part"))  # written atomically, nothing left over


def test_stage_plots_from_cases(tmp_path: Path) -> None:
    from labkit.bench import calibrate, hdr

    merges = [
        Measurement(
            f"hdr merge, {m}",
            s,
            [s],
            1.0,
            extra={"method": m, "relative_rms_error": e, "cramer_rao_relative_rms": 0.004},
        )
        for m, s, e in (("thesis", 3.0, 0.009), ("noise", 4.0, 0.005))
    ]
    plot = hdr.time_error_plot(merges, tmp_path)
    fits = [
        Measurement(
            k, s, [s], 1.0, extra={"model": k, "keypoints": n, "error_vs_truth": {"rms_px": e}}
        )
        for k, n, s, e in (("polynomial", 100, 0.1, 0.02), ("spline", 100, 0.3, 0.03))
    ]
    plot2 = calibrate.time_error_plot(fits, tmp_path)
    assert plot.file == "hdr_time_vs_error.png" and plot2.file == "calibrate_time_vs_error.png"
    assert (tmp_path / plot.file).is_file() and (tmp_path / plot2.file).is_file()


def test_reconstruct_stage_plots_real_and_simulated_errors(tmp_path: Path) -> None:
    """The reconstruction stage's plots: time against error per knob, the main variants on
    both kinds of data by MRAE and by per-pixel spectral RMSE, and the scaling sweep."""
    from labkit.bench.harness import Plot
    from labkit.bench.reconstruct import _plots

    def row(name: str, seconds: float, **extra: float | str) -> Measurement:
        return Measurement(name, seconds, [seconds], 1.0, extra=extra)

    knobs = [row("204×172 texture, L2", 1.0, spectral_rmse_rel=0.23)]
    real = [row("real, defaults", 3.0, variant="defaults", mrae=0.197, spectral_rmse=0.18)]
    simulated = [
        row("sim, defaults", 4.0, variant="defaults", spectral_mrae=0.12, spectral_rmse_rel=0.07)
    ]
    sizes = [row(f"{n}²", s, pixels=n * n, solve_s=0.8 * s) for n, s in ((256, 2.0), (512, 8.0))]
    summary = row("scaling", 10.0, exponent=1.0, exponent_solve=1.0)
    plots = _plots(tmp_path, knobs, real, simulated, sizes, summary)
    assert len(plots) == 4 and all(isinstance(p, Plot) for p in plots)
    for plot in plots:
        assert (tmp_path / plot.file).read_bytes()[:4] == b"\x89PNG"


def test_the_report_says_which_commit_and_how_busy_the_machine_was() -> None:
    machine = {**KNOWN["machine"], "commit": "abc1234+", "load_average": [1.5, 1.0, 0.5]}
    line = machine_line(machine)
    assert line == (
        "Test CPU, 2 cores; Python 3.11.0, numpy 2.0, labkit 0.1 at commit abc1234+; "
        "2025-01-01 (load average 1.5 / 1 / 0.5 at the end)."
    )
    assert line in render_markdown({**KNOWN, "machine": machine}).splitlines()
    assert set(machine_info()) >= {"commit", "load_average", "date", "cpu", "cores"}


def test_the_benchmarks_page_renders_a_report_as_valid_restructuredtext() -> None:
    """``docs/_ext/labkit_bench.py`` turns a ``bench.json`` into the page: every stage a
    section, every case a row, notes, plots and tables, with no docutils error."""
    from docutils.core import publish_doctree
    from labkit_bench import bench_rst

    awkward = "mean |model − lens truth| px, a*b, `name`, case_ and [1] <x>"  # markup characters
    notes = {"reconstruct": [*KNOWN["stage_notes"]["reconstruct"], awkward]}
    payload = {**KNOWN, "stage_notes": notes}
    text = "\n".join(["Benchmarks", "==========", "", *bench_rst(payload, folder="benchmarks")])
    warnings = io.StringIO()  # docutils' warnings and errors (level ≥ 2) go here
    tree = publish_doctree(
        text, settings_overrides={"report_level": 2, "halt_level": 5, "warning_stream": warnings}
    )
    assert not warnings.getvalue(), warnings.getvalue()
    page = tree.astext()
    assert "reconstruct" in page and "scaling: time ∝ pixels^p" in page and "812" in page
    assert "exponent=0.98" in page and "a sentence" in page and "Time against size" in page
    assert awkward in page
    (figure,) = [n for n in tree.findall() if n.tagname == "image"]
    assert figure["uri"] == "/benchmarks/reconstruct_scaling.png"
