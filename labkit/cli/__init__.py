"""The ``labkit`` command: a thin layer over the Python API.

Each subcommand lives in its own module with a ``register(subparsers)`` function. Errors
that labkit raises on purpose (:class:`~labkit.errors.LabkitError`) are printed as one
line without a traceback, exit status 2.
"""

from __future__ import annotations

import argparse
import sys

import labkit
from labkit.cli import (
    bench,
    calibrate,
    capture,
    correct,
    demo,
    devices,
    dispersion,
    evaluate,
    export,
    hdr,
    reconstruct,
    rig,
    session,
    sim,
    synthesize,
)
from labkit.errors import LabkitError

_MODULES = (
    rig,
    devices,
    capture,
    session,
    hdr,
    calibrate,
    synthesize,
    dispersion,
    correct,
    reconstruct,
    evaluate,
    export,
    sim,
    demo,
    bench,
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = argparse.ArgumentParser(
        prog="labkit",
        description=(
            "Spectral camera lab toolkit: capture, HDR merging, chromatic-aberration "
            "calibration and spectral reconstruction (Llanos, 2019), on real or simulated rigs."
        ),
    )
    parser.add_argument("--version", action="version", version=f"labkit {labkit.__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _MODULES:
        module.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``labkit`` command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0 if args.command is None else 2
    try:
        return int(args.handler(args) or 0)
    except LabkitError as error:
        print(f"labkit: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("labkit: interrupted", file=sys.stderr)
        return 130
