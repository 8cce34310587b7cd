"""``labkit demo``: run the main job on the simulated rig and write a report."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    """Add ``labkit demo``."""
    parser = commands.add_parser(
        "demo",
        help="run the main job on the simulated rig and write a report",
        description="Render the thesis-style frame set of the simulated rig (every scene "
        "under unfiltered light and each filter, plus dark frames) and write "
        "DIR/report.md with previews and plots.",
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument("--rig", type=Path, default=None, help="rig YAML (default: simulated rig)")
    parser.add_argument("--quick", action="store_true", help="small sensor, for a fast check")
    parser.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    from labkit.demo import run_demo

    report = run_demo(args.out, rig_path=args.rig, quick=args.quick)
    print(f"wrote {report}")
    return 0
