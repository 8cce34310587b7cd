"""Sphinx configuration of labkit's documentation site (``make docs``).

The site is built from the repository alone, offline: no intersphinx, no fonts or scripts
from a CDN, no theme option that fetches anything (version switcher, announcements,
analytics). Pages may link to external URLs; nothing is needed from them to build or read
the site.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

DOCS = Path(__file__).parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(DOCS.parent))  # the packages of this checkout, installed or not

from sphinx.application import Sphinx  # noqa: E402

import labkit  # noqa: E402

project = "labkit"
author = "labkit contributors"
copyright = "labkit contributors"
release = labkit.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
    "labkit_api",  # _ext/labkit_api.py: the API pages, one per public module
    "labkit_cli",  # _ext/labkit_cli.py: the command-line reference from build_parser()
    "labkit_bench",  # _ext/labkit_bench.py: the benchmarks page from make bench's bench.json
    "labkit_guide",  # _ext/labkit_guide.py: runs the guide's marked blocks, shows their output
    "myst_parser",  # the guide's pages and the design notes are Markdown
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
# headings get anchors, so that a page can link to a section of another: [text](page.md#slug)
myst_heading_anchors = 3

templates_path = ["_templates"]
# examples/: the gallery's scripts, not pages; sg_execution_times.rst: sphinx-gallery's
# timings, kept as files but not built (its table loads jQuery and DataTables from CDNs)
exclude_patterns = [
    "_build",
    "examples",
    "sg_execution_times.rst",
    "auto_examples/sg_execution_times.rst",
]
root_doc = "index"
# `--option` stays two hyphens in docstrings and help texts (no en dashes)
smartquotes = False

# --- API reference --------------------------------------------------------------------
# A small generator, _ext/labkit_api.py, writes one page per public module (no part of its
# name starting with "_") into docs/api/ when the build starts, from
# _templates/api/module.rst: the module's docstring, a summary table (autosummary) of its
# public names and its submodules, then autodoc's documentation of the names it defines.
# Its public names are its __all__, else what it defines without a leading underscore.
# Each name is documented once, on the page of the public module that defines it (else of
# the nearest public module that exports it), and every exporting page links there.
# Autosummary's own recursive stubs cannot do this: it would document each re-exported
# name on every page that exports it, and it cannot reach a module hidden behind a
# package attribute of the same name (calibration.warp, the function, hides the module
# calibration.warp; likewise reconstruction.model.prior_terms and residual_aberration).
# tests/test_docs.py checks that every name in every public module's __all__ is in the
# built inventory and linked from its module's page.
autosummary_generate = False  # the summary tables link to the pages above; no stubs
autodoc_default_options = {"member-order": "bysource"}
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
autodoc_class_signature = "mixed"
autoclass_content = "class"

# numpydoc renders the docstrings' sections; the class members come from autodoc's
# :members:, not from numpydoc's own member tables (which would need stubs of their own).
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks: set[str] = set()

# --- Example gallery ------------------------------------------------------------------
# The scripts in examples/ run during the build (on small simulated sensors and the
# packaged real frames, all together about a minute on 2 cores) and write only to
# temporary folders; sphinx-gallery captures their matplotlib figures. Code links are
# resolved from this site's own inventory (sphinx-gallery needs no network for that).
sphinx_gallery_conf = {
    "examples_dirs": "examples",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "within_subsection_order": "FileNameSortKey",
    "doc_module": ("labkit", "calibration", "reconstruction"),
    "backreferences_dir": None,
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "image_scrapers": ("matplotlib",),
    "matplotlib_animations": False,
    "min_reported_time": 0,
    "show_memory": False,
    "binder": {},
    "jupyterlite": {},
}

# --- HTML -------------------------------------------------------------------------------
html_theme = "pydata_sphinx_theme"
html_title = f"labkit {release}"
html_static_path: list[str] = []
html_show_sourcelink = False
html_copy_source = False
html_theme_options = {
    # nothing fetched at build time or when a page is read
    "check_switcher": False,
    "show_version_warning_banner": False,
    "announcement": "",
    "analytics": {},
    "icon_links": [],
    "navigation_with_keys": False,
    "show_nav_level": 1,
    "show_toc_level": 2,
    "navbar_align": "left",
    "header_links_before_dropdown": 5,
    "secondary_sidebar_items": ["page-toc"],
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version"],
}
html_sidebars = {"index": [], "cli": []}


def _callables_only(handler: Callable[..., Any]) -> Callable[..., Any]:
    """`handler` (numpydoc's signature hook) for everything but module-level values."""

    def hook(app: Sphinx, what: str, *args: Any) -> Any:
        return None if what in ("data", "attribute") else handler(app, what, *args)

    return hook


def setup(app: Sphinx) -> None:
    # numpydoc gives every callable object a signature, values too; a type alias such as
    # labkit.bench.plots.Point (tuple[float, float, str] is callable) then breaks autodata
    # in Sphinx 9 ("error while formatting signature ... list assignment index out of
    # range"). Values keep autodoc's own signature (none).
    for listener in list(app.events.listeners["autodoc-process-signature"]):
        if getattr(listener.handler, "__module__", "") == "numpydoc.numpydoc":
            app.disconnect(listener.id)
            app.connect(
                "autodoc-process-signature",
                _callables_only(listener.handler),
                priority=listener.priority,
            )
