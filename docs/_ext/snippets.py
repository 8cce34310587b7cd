"""Code blocks of the README, the user guide and the API tour, as a new user would paste
them: fenced blocks marked by an HTML comment (``<!-- readme-test: run -->``, ``<!--
guide-test: run -->``) run in order, in one folder, with ``rigs/`` and ``labkit/data/``
where a checkout has them.

The documentation build runs the guide's blocks and shows their output
(``_ext/labkit_guide.py``); the tests run the README's and the guide's
(``tests/test_readme.py``, ``tests/test_guide.py``). Both go through :func:`run_blocks`.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

FENCE = re.compile(r"(?P<mark><!-- [\w-]+: run -->\n)?```(?P<lang>[^\n`]*)\n(?P<code>.*?)```", re.S)

#: Longest a block may run, s; a block that takes longer fails.
BLOCK_TIMEOUT_S = 900


def blocks(text: str) -> list[tuple[str, str, bool]]:
    """Every fenced code block: (language, code, marked to run)."""
    return [(m["lang"], m["code"], m["mark"] is not None) for m in FENCE.finditer(text)]


def command_lines(code: str) -> list[list[str]]:
    """The shell command lines of a block, continuation lines joined, comments dropped."""
    joined = code.replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in joined.splitlines() if line.strip()]


@dataclass(frozen=True)
class BlockRun:
    """One marked block, run: where it ends in the text, its code and what it printed."""

    end: int  # offset in the text just after the block's closing fence
    lang: str
    code: str
    returncode: int
    stdout: str
    stderr: str


def run_blocks(text: str, folder: Path, repo_root: Path) -> Iterator[BlockRun]:
    """Run the marked blocks of `text` in `folder`, in order, stopping after one fails.

    Shell blocks run with ``bash -euo pipefail``, Python blocks with this interpreter and
    ``-P`` (the folder's ``labkit/``, data only, must not shadow the package). The
    checkout's ``rigs`` and ``labkit/data`` are linked into `folder` first.
    """
    (folder / "rigs").symlink_to(repo_root / "rigs")
    (folder / "labkit").mkdir()
    (folder / "labkit" / "data").symlink_to(repo_root / "labkit" / "data")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    for match in FENCE.finditer(text):
        if match["mark"] is None:
            continue
        lang, code = match["lang"], match["code"]
        argv = (
            ["bash", "-euo", "pipefail", "-c", code]
            if lang == "sh"
            else [sys.executable, "-P", "-c", code]
        )
        done = subprocess.run(
            argv, cwd=folder, env=env, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S
        )
        yield BlockRun(match.end(), lang, code, done.returncode, done.stdout, done.stderr)
        if done.returncode != 0:
            return


def run_marked(text: str, folder: Path, repo_root: Path, *, what: str) -> None:
    """Run the marked blocks of `text` in `folder` (:func:`run_blocks`); fail naming the
    block and its error."""
    for run in run_blocks(text, folder, repo_root):
        assert run.returncode == 0, (
            f"{what}: {run.lang} block failed:\n{run.code}\n{run.stderr[-3000:]}"
        )
