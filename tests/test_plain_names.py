"""What a user reads names things in words, not by the thesis' numbering (issue 55).

Help texts, log records, choices' reasons, reports and error messages describe what a
method does ("reference spectrum from the mean colour", "direct colour estimation"); the
thesis' sections, equations, algorithms and tables are cited in the docstrings and the
documentation (``docs/background.md`` maps them to labkit's functions).
"""

from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

from labkit.cli import build_parser

THESIS_NUMBERING = re.compile(
    r"§\s*\d|\(\d\.\d+\)|\bAlgorithms? \d|\bAlg\. ?\d|\bTable \d\.\d|\beq(uation)?\.? ?\(?\d\.\d"
)


def _docstring_ids(tree: ast.AST) -> set[int]:
    """Every docstring and attribute docstring (a bare string statement)."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            ids.add(id(node.value))
    return ids


def test_no_string_a_user_reads_cites_the_thesis_by_number(repo_root: Path) -> None:
    found = []
    for package in ("labkit", "calibration", "reconstruction"):
        for path in sorted((repo_root / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            docstrings = _docstring_ids(tree)
            for node in ast.walk(tree):
                if (
                    isinstance(node, ast.Constant)
                    and isinstance(node.value, str)
                    and id(node) not in docstrings
                    and THESIS_NUMBERING.search(node.value)
                ):
                    found.append(f"{path.relative_to(repo_root)}:{node.lineno}: {node.value!r}")
    assert not found, "\n".join(found)


def _help_texts(parser: argparse.ArgumentParser) -> list[tuple[str, str]]:
    texts = [(parser.prog, parser.format_help())]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                texts += _help_texts(sub)
    return texts


def test_no_help_text_cites_the_thesis_by_number() -> None:
    texts = _help_texts(build_parser())
    assert len(texts) > 20  # every command and subcommand
    cited = [(prog, m.group()) for prog, text in texts for m in THESIS_NUMBERING.finditer(text)]
    assert not cited, cited


def test_the_pattern_catches_what_it_is_for() -> None:
    for text in ("§6.3 mean-colour", "problem (3.1)", "Algorithm 3", "Table 4.1", "eq. 4.9"):
        assert THESIS_NUMBERING.search(text), text
    for text in ("0.5 (1.2 px)", "σ = 1e-3", "400–700 nm", "Algorithms and tables"):
        assert not THESIS_NUMBERING.search(text), text
