"""The ``labkit`` command: a thin layer over the Python API.

Each subcommand lives in its own module with a ``register(subparsers)`` function.

``labkit`` never prints a traceback. Exit statuses:

- 0: success;
- 2: an error labkit expects (:class:`~labkit.errors.LabkitError`, a bad option, a full
  disk, a folder it may not write, too little memory), printed as one line saying what and
  how to fix it;
- 3: an unexpected failure (a bug): one line, and the traceback written to a log file
  whose path the line gives (``$LABKIT_LOG_DIR``, else ``~/.local/state/labkit``);
- 130 / 143: interrupted (Ctrl-C / SIGTERM), after the command's clean-up ran.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import signal
import sys
import threading
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import labkit
from labkit.cli._commands import COMMANDS, Commands
from labkit.errors import LabkitError

_DESCRIPTION = (
    "Spectral camera lab toolkit: capture, HDR merging, chromatic-aberration "
    "calibration and spectral reconstruction (Llanos, 2019), on real or simulated rigs."
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    return _parser(set(COMMANDS))


def _parser(full: set[str]) -> argparse.ArgumentParser:
    """The parser with the commands in `full` registered by their modules; every other
    command is listed with its summary but its module is not imported."""
    parser = argparse.ArgumentParser(prog="labkit", description=_DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"labkit {labkit.__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands = Commands(subparsers)
    for name, command in COMMANDS.items():
        if name in full:
            importlib.import_module(command.module).register(commands)
        else:
            commands.add_parser(name, add_help=False)
    return parser


def _command_in(argv: list[str]) -> str | None:
    """The command an argument list runs: its first word, when that names a command."""
    first = next((word for word in argv if word == "--" or not word.startswith("-")), None)
    return first if first in COMMANDS else None


EXPECTED = 2
"""Exit status of an error labkit expects (bad input, full disk, …)."""
UNEXPECTED = 3
"""Exit status of an unexpected failure (a bug), whose traceback goes to a log file."""


def main(argv: list[str] | None = None) -> int:
    """Run the ``labkit`` command line; return the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command_in(argv)
    parser = _parser({command} if command else set())
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit:  # a bad option (argparse printed it), --help, --version
        return exit.code if isinstance(exit.code, int) else EXPECTED
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0 if args.command is None else 2
    restore = _terminate_as_exit()
    try:
        status = int(args.handler(args) or 0)
        sys.stdout.flush()  # a closed pipe is reported here, not at interpreter exit
        return status
    except LabkitError as error:
        return _fail(str(error))
    except KeyboardInterrupt:
        print("labkit: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("labkit: terminated", file=sys.stderr)
        return 143
    except BrokenPipeError:
        _silence_stdout()  # `labkit … | head`: the reader left; nothing more to say
        return 141
    except MemoryError:
        return _fail(
            "not enough memory for this job; use a smaller image or region, smaller "
            "patches (--patch-px) or fewer workers"
        )
    except OSError as error:
        message = _system_error(error)
        if message is None:
            return _crash(args, error)
        return _fail(message)
    except Exception as error:
        return _crash(args, error)
    finally:
        restore()


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that clean-up (``finally``) runs."""


def _terminate_as_exit() -> Callable[[], None]:
    """Make SIGTERM raise :class:`_Terminated`; returns what puts the previous handling back."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None  # signals are only for the main thread

    def handler(signum: int, frame: Any) -> None:
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, handler)
    default = signal.SIG_DFL if previous is None else previous  # None: not set from Python
    return lambda: signal.signal(signal.SIGTERM, default)


def _fail(message: str) -> int:
    print(f"labkit: error: {message}", file=sys.stderr)
    return EXPECTED


_SYSTEM_ERRORS = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "the file system is read-only",
    errno.ENOENT: "no such file or folder",
    errno.ENOTDIR: "a part of the path is not a folder",
    errno.EISDIR: "it is a folder, not a file",
    errno.EEXIST: "it already exists",
    errno.ENAMETOOLONG: "the name is too long",
}


def _system_error(error: OSError) -> str | None:
    """One line for an operating-system error users cause (full disk, permissions)."""
    what = _SYSTEM_ERRORS.get(error.errno or 0)
    if what is None:
        return None
    where = " → ".join(str(f) for f in (error.filename, error.filename2) if f)
    fix = (
        "free some space and run the command again (outputs are written as one set, so "
        "nothing half-written was kept)"
        if error.errno in (errno.ENOSPC, errno.EDQUOT)
        else "check the path and its permissions"
    )
    return f"{where + ': ' if where else ''}{what}; {fix}"


def _crash(args: argparse.Namespace, error: BaseException) -> int:
    """One line for an unexpected failure; the traceback goes to a log file."""
    text = "".join(traceback.format_exception(error))
    log = _write_crash_log(args, text)
    where = f"the traceback is in {log}" if log else "its traceback could not be written"
    print(
        f"labkit: internal error ({type(error).__name__}: {error}); {where}. This is a bug: "
        "please report it with that file",
        file=sys.stderr,
    )
    return UNEXPECTED


def _write_crash_log(args: argparse.Namespace, text: str) -> Path | None:
    import datetime as dt
    import os
    import tempfile

    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%S")
    header = f"labkit {labkit.__version__}\nargv: {sys.argv!r}\ncommand: {args.command}\n\n"
    places = [
        os.environ.get("LABKIT_LOG_DIR"),
        str(Path.home() / ".local" / "state" / "labkit"),
        tempfile.gettempdir(),
    ]
    for place in filter(None, places):
        try:
            folder = Path(place)
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / f"crash-{stamp}-{os.getpid()}.log"
            path.write_text(header + text, encoding="utf-8")
            return path
        except OSError:
            continue
    return None


def _silence_stdout() -> None:
    import contextlib
    import os

    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
