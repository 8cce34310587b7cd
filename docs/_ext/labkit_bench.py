"""The ``labkit-bench`` directive: the benchmarks page, from ``labkit bench``'s own output.

``.. labkit-bench:: benchmarks/bench.json`` renders a ``bench.json`` that ``make bench``
published into ``docs/benchmarks/`` (with the plots next to it): the machine and versions
it ran on, then per stage a table of its cases (median time, repeats, peak memory, the
target the issue set and whether it was met, the case's figures), the stage's notes,
tables and plots. Nothing on the page is typed by hand, so it says what the last
``make bench`` measured. Without a published ``bench.json`` the page says how to make one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

from labkit.bench.harness import case_cells, case_details, machine_line

#: Columns of a stage's table of cases.
CASE_COLUMNS = ["case", "median time (s)", "repeats", "peak memory (MiB)", "target (s)", "result"]


def _text(text: str) -> str:
    """Plain text as reStructuredText on one line: markup characters escaped, so that
    ``|x|``, ``a*b`` or ``name_`` stay as written."""
    text = " ".join(str(text).split())
    for char in "\\|*`_[]<>":
        text = text.replace(char, "\\" + char)
    return text


def _cell(text: str) -> str:
    """A table cell: its text escaped, or a dash when empty; ``**FAIL**`` stays bold."""
    return text if text == "**FAIL**" else (_text(text) or "—")


def _list_table(title: str, columns: list[str], rows: list[list[str]]) -> list[str]:
    lines = [f".. list-table:: {_text(title)}".rstrip(), "   :header-rows: 1", ""]
    for row in [columns, *rows]:
        lines.append(f"   * - {_cell(row[0])}")
        lines += [f"     - {_cell(cell)}" for cell in row[1:]]
    return [*lines, ""]


def bench_rst(payload: dict[str, Any], *, folder: str) -> list[str]:
    """The page body as reStructuredText lines; plots are looked up in `folder`."""
    lines = [f"Measured on {machine_line(payload['machine'])}", ""]
    stage_notes = payload.get("stage_notes", {})
    for stage, cases in payload["stages"].items():
        lines += [_text(stage), "-" * max(len(_text(stage)), 3), ""]
        lines += _list_table("", CASE_COLUMNS, [case_cells(case) for case in cases])
        details = [(case["name"], case_details(case)) for case in cases]
        details = [(name, text) for name, text in details if text]
        if details:
            lines += ["The cases' figures:", ""]
            lines += [f"* {_text(name)}: {_text(text)}" for name, text in details]
            lines.append("")
        for note in stage_notes.get(stage, []):
            if isinstance(note, str):
                lines += [f"* {_text(note)}", ""]
            elif note["kind"] == "plot":
                lines += [
                    f".. figure:: /{folder}/{note['file']}",
                    f"   :alt: {' '.join(note['title'].split())}",
                    "",
                    f"   {_text(note['title'])}",
                    "",
                ]
            else:
                lines += _list_table(note["title"], note["columns"], note["rows"])
    return lines


class BenchDirective(SphinxDirective):
    """``.. labkit-bench:: PATH``: PATH relative to the source folder."""

    required_arguments = 1

    def run(self) -> list[nodes.Node]:
        relative = self.arguments[0]
        path = Path(self.env.srcdir) / relative
        self.env.note_dependency(str(path))
        if not path.is_file():
            text = (
                f"No benchmark has been published here ({relative} is missing): run "
                "``make bench``, which measures every stage and publishes the result."
            )
            lines = [text]
        else:
            payload = json.loads(path.read_text(encoding="utf-8"))
            lines = bench_rst(payload, folder=Path(relative).parent.as_posix())
        container = nodes.section()
        container.document = self.state.document
        nested_parse_with_titles(self.state, StringList(lines, source=str(path)), container)
        return container.children


def setup(app: Any) -> dict[str, bool]:
    app.add_directive("labkit-bench", BenchDirective)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
