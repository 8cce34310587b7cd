"""The user guide and the API tour, run while the site is built.

Each page under ``guide/`` and the page ``python-api`` is read as a new user would follow
it: its blocks marked ``<!-- guide-test: run -->`` run in order, in one empty folder with
the checkout's ``rigs/`` and ``labkit/data/`` (:func:`snippets.run_blocks`). What a block
prints goes onto the page under it, so the output a reader sees is the output of this
build. A block that fails stops the build, naming the page, the block and its error.

The time each page took is logged and written to ``guide-runs.json`` in the output folder
(page → seconds, blocks run and the SHA-256 of the page's text): the time a reader
following that page waits, and, for ``tests/test_docs.py``, which text was run.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from pathlib import Path

from snippets import run_blocks
from sphinx.application import Sphinx
from sphinx.errors import ExtensionError
from sphinx.util import logging

logger = logging.getLogger(__name__)

#: Lines of a block's output shown on the page (its last lines).
OUTPUT_LINES = 30


def _runs(docname: str) -> bool:
    return docname.startswith("guide/") or docname == "python-api"


def _output_block(stdout: str) -> str:
    lines = stdout.rstrip("\n").splitlines()
    if not lines:
        return ""
    if len(lines) > OUTPUT_LINES:
        lines = [f"… ({len(lines) - OUTPUT_LINES} lines before)", *lines[-OUTPUT_LINES:]]
    body = "\n".join(lines)
    return f"\n\n*Output, from the build of this page:*\n\n```text\n{body}\n```\n"


def run_page(app: Sphinx, docname: str, source: list[str]) -> None:
    """``source-read`` handler: run the page's marked blocks and add their output."""
    if not _runs(docname):
        return
    text = source[0]
    repo_root = Path(app.srcdir).parent
    start = time.perf_counter()
    pieces, last, count = [], 0, 0
    with tempfile.TemporaryDirectory(prefix="labkit-guide-") as folder:
        for run in run_blocks(text, Path(folder), repo_root):
            count += 1
            if run.returncode != 0:
                raise ExtensionError(
                    f"{docname}: its {run.lang} block no. {count} failed "
                    f"(exit status {run.returncode}):\n{run.code}\n{run.stderr[-3000:]}"
                )
            pieces += [text[last : run.end], _output_block(run.stdout)]
            last = run.end
    if not count:
        return
    source[0] = "".join([*pieces, text[last:]])
    seconds = time.perf_counter() - start
    app.env.labkit_guide_runs = {  # type: ignore[attr-defined]
        **getattr(app.env, "labkit_guide_runs", {}),
        docname: {
            "seconds": round(seconds, 1),
            "blocks": count,
            "sha256": hashlib.sha256(text.encode("utf-8")).hexdigest(),
        },
    }
    logger.info(f"[labkit-guide] {docname}: {count} blocks ran in {seconds:.0f} s")


def write_runs(app: Sphinx, exception: Exception | None) -> None:
    """``build-finished`` handler: ``guide-runs.json`` in the output folder."""
    runs = getattr(app.env, "labkit_guide_runs", {})
    if exception is None and runs:
        path = Path(app.outdir) / "guide-runs.json"
        path.write_text(json.dumps(runs, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def setup(app: Sphinx) -> dict[str, bool]:
    app.connect("source-read", run_page)
    app.connect("build-finished", write_runs)
    return {"parallel_read_safe": False, "parallel_write_safe": True}
