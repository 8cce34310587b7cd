"""The user guide works as written: every ``labkit`` command line on its pages is accepted
by the parser, and the blocks marked ``<!-- guide-test: run -->`` run, page by page, each in
an empty folder with the checkout's rigs and data."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
from _snippets import blocks, command_lines, run_marked

from labkit.cli import build_parser

PAGES = ["simulated-rig", "capture", "calibration", "reconstruction", "troubleshooting"]


def _page(repo_root: Path, name: str) -> str:
    return (repo_root / "docs" / "guide" / f"{name}.md").read_text(encoding="utf-8")


def test_every_labkit_command_line_in_the_guide_parses(repo_root: Path) -> None:
    parser = build_parser()
    seen = 0
    for name in PAGES:
        for lang, code, _ in blocks(_page(repo_root, name)):
            for words in command_lines(code) if lang == "sh" else []:
                if words and words[0] == "labkit":
                    seen += 1
                    try:
                        parser.parse_args(words[1:])
                    except SystemExit as exc:
                        pytest.fail(f"guide/{name}: `{shlex.join(words)}` is refused ({exc})")
    assert seen >= 10


@pytest.mark.parametrize("name", ["simulated-rig", "capture", "calibration", "reconstruction"])
def test_the_guide_page_runs_as_written(name: str, repo_root: Path, tmp_path: Path) -> None:
    text = _page(repo_root, name)
    assert any(marked for _, _, marked in blocks(text)), f"guide/{name} runs nothing"
    run_marked(text, tmp_path, repo_root, what=f"guide/{name}")
