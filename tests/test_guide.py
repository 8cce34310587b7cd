"""The user guide works as written: every ``labkit`` command line on its pages is accepted
by the parser. The blocks marked ``<!-- guide-test: run -->`` run, page by page, each in an
empty folder with the checkout's rigs and data, while the site is built
(``docs/_ext/labkit_guide.py``); ``tests/test_docs.py`` checks that the built site ran the
pages as they are now."""

from __future__ import annotations

import shlex
from pathlib import Path
from types import SimpleNamespace

import labkit_guide
import pytest
from snippets import blocks, command_lines
from sphinx.errors import ExtensionError

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


def _fake_app(repo_root: Path) -> SimpleNamespace:
    return SimpleNamespace(srcdir=str(repo_root / "docs"), env=SimpleNamespace())


def test_the_build_shows_a_blocks_output_under_it_and_fails_on_a_failing_block(
    repo_root: Path,
) -> None:
    """What ``labkit_guide`` does to a page: each marked block runs, its output goes under
    it, unmarked blocks do not run; a failing block stops the build naming page and block."""
    page = (
        "# A page\n\n<!-- guide-test: run -->\n```sh\necho planted-output-42\n```\n\n"
        "```sh\nexit 1\n```\n\n<!-- guide-test: run -->\n```python\nprint(6 * 7)\n```\nend\n"
    )
    app = _fake_app(repo_root)
    source = [page]
    labkit_guide.run_page(app, "guide/example", source)
    shown = source[0]
    assert shown.index("planted-output-42\n```") > shown.index("echo planted-output-42")
    assert shown.count("Output, from the build of this page") == 2 and "\n42\n" in shown
    assert shown.endswith("end\n") and "exit 1" in shown
    assert app.env.labkit_guide_runs["guide/example"]["blocks"] == 2
    source = [page.replace("print(6 * 7)", "import nonexistent_module_xyz")]
    with pytest.raises(ExtensionError, match=r"guide/example: its python block no\. 2 failed"):
        labkit_guide.run_page(app, "guide/example", source)
    untouched = ["<!-- guide-test: run -->\n```sh\nexit 3\n```\n"]
    labkit_guide.run_page(app, "formats", untouched)  # not a guide page: nothing runs
    assert untouched == ["<!-- guide-test: run -->\n```sh\nexit 3\n```\n"]
