"""``labkit bench STAGE --out DIR``: benchmarks written as JSON and Markdown."""

from __future__ import annotations

import argparse
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.cli._options import positive_int


def register(commands: Commands) -> None:
    """Add ``labkit bench``."""
    from labkit.bench import BENCHMARKS

    parser = commands.add_parser(
        "bench",
        description="Run benchmarks and write DIR/bench.json and DIR/bench.md with times "
        "(median of repeats), peak memory, errors, the issue targets they are held to, and "
        "plots (time against error, time against image size) next to them.",
    )
    parser.add_argument("stage", choices=[*BENCHMARKS, "all"], help="what to benchmark")
    parser.add_argument("--out", type=Path, default=Path("bench-out"), help="output folder")
    parser.add_argument("--rig", type=Path, default=None, help="rig YAML (default: simulated rig)")
    parser.add_argument(
        "--repeats", type=positive_int, default=3, help="repeats per case (median), ≥ 1"
    )
    parser.add_argument(
        "--full",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also run the slow cases: the full-size reconstruction and the 1024² and 2048² "
        "sizes of the scaling sweep (default: on for 'all', else LABKIT_BENCH_FULL=1)",
    )
    parser.set_defaults(handler=_bench)


def _bench(args: argparse.Namespace) -> int:
    from labkit.bench import BENCHMARKS, write_report
    from labkit.bench.harness import accepts
    from labkit.io.output_folder import check_output_folder, staged_output_folder
    from labkit.rig import default_rig_path

    stages = list(BENCHMARKS) if args.stage == "all" else [args.stage]
    full = args.full if args.full is not None else (True if args.stage == "all" else None)
    check_output_folder(args.out, command="labkit bench")
    results, notes = {}, {}
    with staged_output_folder(args.out, command="labkit bench") as out:
        for stage in stages:
            function = BENCHMARKS[stage]
            extra = {"out": out} if accepts(function, "out") else {}
            if accepts(function, "full"):
                extra["full"] = full
            rig = args.rig or default_rig_path()
            cases, stage_notes = function(rig, repeats=args.repeats, **extra)
            results[stage] = cases
            notes[stage] = stage_notes
            for case in cases:
                verdict = "" if case.passed is None else (" pass" if case.passed else " FAIL")
                target = "" if case.target_s is None else f" (target ≤ {case.target_s:g} s)"
                print(f"{stage}: {case.name}: {case.seconds:.3f} s{target}{verdict}, "
                      f"peak {case.peak_mib:.0f} MiB")  # fmt: skip
        write_report(out, results, [], stage_notes=notes)
    report = args.out / "bench.md"
    print(f"wrote {report} and {report.with_suffix('.json')}")
    failed = [c.name for cases in results.values() for c in cases if c.passed is False]
    return 1 if failed else 0
