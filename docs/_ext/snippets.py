"""Code blocks of the README and the user guide, as a new user would paste them: fenced
blocks marked by an HTML comment (``<!-- readme-test: run -->``, ``<!-- guide-test: run
-->``) run in order, in one folder, with ``rigs/`` and ``labkit/data/`` where a checkout
has them."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

FENCE = re.compile(r"(?P<mark><!-- [\w-]+: run -->\n)?```(?P<lang>[^\n`]*)\n(?P<code>.*?)```", re.S)


def blocks(text: str) -> list[tuple[str, str, bool]]:
    """Every fenced code block: (language, code, marked to run)."""
    return [(m["lang"], m["code"], m["mark"] is not None) for m in FENCE.finditer(text)]


def command_lines(code: str) -> list[list[str]]:
    """The shell command lines of a block, continuation lines joined, comments dropped."""
    joined = code.replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in joined.splitlines() if line.strip()]


def run_marked(text: str, folder: Path, repo_root: Path, *, what: str) -> None:
    """Run the marked blocks of `text` in `folder` (sh with bash -e, python with this
    interpreter), the checkout's ``rigs`` and ``labkit/data`` linked in; fail naming the
    block and its error. Python runs with ``-P``: the folder's ``labkit/`` (data only)
    must not shadow the package."""
    (folder / "rigs").symlink_to(repo_root / "rigs")
    (folder / "labkit").mkdir()
    (folder / "labkit" / "data").symlink_to(repo_root / "labkit" / "data")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    for lang, code, marked in blocks(text):
        if not marked:
            continue
        argv = (
            ["bash", "-euo", "pipefail", "-c", code]
            if lang == "sh"
            else [sys.executable, "-P", "-c", code]
        )
        done = subprocess.run(
            argv, cwd=folder, env=env, capture_output=True, text=True, timeout=900
        )
        assert done.returncode == 0, f"{what}: {lang} block failed:\n{code}\n{done.stderr[-3000:]}"
