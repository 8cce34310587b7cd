"""``labkit --help`` and ``labkit --version`` answer without importing any command: the
commands' modules, and NumPy, SciPy and the rest behind them, load only for the command that
runs."""

from __future__ import annotations

import json
import subprocess
import sys

from labkit.cli import build_parser
from labkit.cli._commands import COMMANDS

HEAVY = ("numpy", "scipy", "matplotlib", "dask", "pydantic", "calibration", "reconstruction")


def _imported_after(argv: list[str]) -> list[str]:
    """The heavy top-level packages and command modules imported by ``main(argv)``, run in a
    fresh interpreter."""
    modules = sorted(command.module for command in COMMANDS.values())
    code = (
        "import contextlib, io, json, sys\n"
        "from labkit.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    main({argv!r})\n"
        "print(json.dumps(sorted(name for name in sys.modules\n"
        f"    if name.split('.')[0] in {HEAVY!r} or name in {modules!r})))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_help_and_version_import_no_command_and_no_numpy() -> None:
    for argv in (["--help"], ["--version"], []):
        assert _imported_after(argv) == [], argv


def test_a_command_imports_its_own_module_only() -> None:
    imported = _imported_after(["export", "--help"])
    assert "labkit.cli.export" in imported
    assert not set(imported) & {c.module for n, c in COMMANDS.items() if n != "export"}


def test_the_short_listing_is_the_full_parsers(capsys) -> None:
    from labkit.cli import main

    main(["--help"])
    short = capsys.readouterr().out
    build_parser().print_help()
    assert short == capsys.readouterr().out
    for name, command in COMMANDS.items():
        assert name in short and command.summary.split()[0] in short
