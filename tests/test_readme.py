"""The README is a quick start that works: short, no dated figures, every ``labkit`` command
line in it accepted by the parser, and the blocks marked ``<!-- readme-test: run -->`` run,
in order, in one empty folder, as a new user would paste them."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from snippets import blocks, command_lines, run_marked

from labkit.cli import build_parser

MAX_LINES = 200


def _prose(text: str) -> str:
    return re.sub(r"```.*?```", "", text, flags=re.S)


@pytest.fixture(scope="module")
def readme(repo_root: Path) -> str:
    return (repo_root / "README.md").read_text(encoding="utf-8")


def test_the_readme_is_a_short_quick_start_without_dated_figures(readme: str) -> None:
    lines = readme.splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines (at most {MAX_LINES})"
    dated = [line for line in lines if re.search(r"\b20\d\d-\d\d-\d\d\b", line)]
    assert not dated, dated
    durations = re.findall(
        r"\b\d+(?:\.\d+)?\s?(?:ms|s|min|minutes?|seconds?|hours?)\b", _prose(readme)
    )
    assert not durations, f"measured figures belong in `labkit bench` outputs: {durations}"
    assert "make demo" in "\n".join(lines[:25]) and "make test" in "\n".join(lines[:25])


def test_every_labkit_command_line_in_the_readme_parses(readme: str) -> None:
    parser = build_parser()
    commands = [
        words
        for lang, code, _ in blocks(readme)
        if lang == "sh"
        for words in command_lines(code)
        if words and words[0] == "labkit"
    ]
    assert len(commands) >= 10, commands
    for words in commands:
        try:
            parser.parse_args(words[1:])
        except SystemExit as exc:  # argparse's way of refusing a command line
            pytest.fail(f"README: `{shlex.join(words)}` is refused by the parser ({exc})")


def test_the_readme_walkthrough_runs_as_written(
    readme: str, repo_root: Path, tmp_path: Path
) -> None:
    """The marked blocks: the simulated rig's capture → HDR → calibration → reconstruction,
    then the Python reconstruction of the same image. Each command must succeed and leave
    the files the README says it writes."""
    marked = [lang for lang, _, run in blocks(readme) if run]
    assert marked == ["sh", "python"], marked
    run_marked(readme, tmp_path, repo_root, what="README")
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    for name in ("spectral.exr", "raw_colour.exr", "preview.png", "log.json"):
        assert (tmp_path / "recon" / name).is_file(), name
        assert (tmp_path / "recon-python" / name).is_file(), name
    assert (tmp_path / "lens.yaml").is_file() and (tmp_path / "hdr" / "hdr.yaml").is_file()
    # a first run looks right: the bundled plan's merge prints one line per image, no warning
    again = subprocess.run(
        ["labkit", "hdr", "day1", "--out", "hdr-again", "--no-progress"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert "warning" not in again.stdout + again.stderr, again.stdout + again.stderr
    images = [line for line in again.stdout.splitlines() if not line.startswith("  ")]
    assert len(images) == 17, again.stdout  # 2 scenes × 8 illuminations, the closing line
