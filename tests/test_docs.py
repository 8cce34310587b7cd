"""The documentation site that `make docs` builds into docs/_build/html.

Every page loads in a browser with all its images; the API reference documents every name
in the ``__all__`` of every public module of the three packages; the command-line
reference has a section for every command and subcommand of ``labkit``. The site must be
built first (`make test` builds it): a missing site fails these tests rather than skipping
them, so that CI cannot pass without it.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import inspect
import json
import pkgutil
import re
import zlib
from html import unescape as html_unescape
from pathlib import Path
from types import ModuleType

import pytest
from _report_check import chromium, pages_in_chromium
from PIL import Image

from labkit.cli import build_parser

PACKAGES = ("labkit", "calibration", "reconstruction")


def _site(repo_root: Path) -> Path:
    """The built site's folder; fails the test when the site was not built."""
    html = repo_root / "docs" / "_build" / "html"
    if not (html / "index.html").is_file():
        pytest.fail(f"{html / 'index.html'} does not exist: run `make docs` to build the site")
    return html


def _pages(html: Path) -> list[str]:
    """Every HTML page of the site (not Sphinx's copies of sources, images and assets)."""
    pages = [p.relative_to(html).as_posix() for p in html.rglob("*.html")]
    return sorted(p for p in pages if not any(part.startswith("_") for part in p.split("/")))


def _public_modules() -> list[ModuleType]:
    """Every module of the three packages with no part of its name starting with ``_``."""
    modules = []
    for root in PACKAGES:
        package = importlib.import_module(root)
        modules.append(package)
        for info in pkgutil.walk_packages(package.__path__, f"{root}."):
            if not any(part.startswith("_") for part in info.name.split(".")):
                modules.append(importlib.import_module(info.name))
    return modules


def _documented(html: Path) -> set[str]:
    """Full names of the Python objects documented in the site, from its inventory
    (objects.inv: four header lines, then zlib-compressed lines ``name domain:role
    priority uri display-name``). Aliases (priority -1: another name of an object that is
    documented elsewhere) do not count."""
    data = (html / "objects.inv").read_bytes()
    *header, body = data.split(b"\n", 4)
    assert header[0] == b"# Sphinx inventory version 2" and b"zlib" in header[3], header
    names = set()
    for line in zlib.decompress(body).decode().splitlines():
        found = re.match(r"(.+?)\s+py:\w+\s+(-?\d+)\s", line)
        if found and found.group(2) != "-1":
            names.add(found.group(1))
    return names


def test_every_page_and_every_image_on_it_loads_in_chromium(repo_root: Path) -> None:
    chromium()
    html = _site(repo_root)
    pages = _pages(html)
    assert "index.html" in pages and "cli.html" in pages and len(pages) > 100, pages
    checked = pages_in_chromium(html, pages)
    assert sorted(checked) == pages
    failed = {
        page: result
        for page, result in checked.items()
        if result["status"] != 200 or not result["loaded"] or result["broken"] or result["error"]
    }
    assert not failed, f"pages that did not load, or whose images did not: {failed}"
    examples = [p for p in pages if re.fullmatch(r"auto_examples/plot_\w+\.html", p)]
    assert len(examples) >= 6 and all(checked[p]["images"] >= 1 for p in examples), {
        p: checked[p]["images"] for p in examples
    }


def test_the_page_check_reports_missing_pages_and_images(tmp_path: Path) -> None:
    Image.new("RGB", (2, 2), "white").save(tmp_path / "good.png")
    (tmp_path / "a.html").write_text(
        '<html><body><p>a</p><img src="good.png"><img src="gone.png"></body></html>'
    )
    checked = pages_in_chromium(tmp_path, ["a.html", "missing.html"])
    assert checked["a.html"]["loaded"] and checked["a.html"]["images"] == 2
    assert checked["a.html"]["broken"] == ["gone.png"]
    assert checked["missing.html"]["status"] == 404


def test_the_api_reference_documents_every_public_name(repo_root: Path) -> None:
    """Every name in a public module's ``__all__`` is in the inventory, under that module
    or under another public module that exports the same object (each object is
    documented once), and the module's page links to it."""
    html = _site(repo_root)
    documented = _documented(html)
    modules = _public_modules()
    missing = []
    for module in modules:
        assert module.__name__ in documented, f"no page for module {module.__name__}"
        page = (html / "api" / f"{module.__name__}.html").read_text()
        for name in getattr(module, "__all__", ()):
            value = getattr(module, name)
            if inspect.ismodule(value):
                if value.__name__ not in documented:
                    missing.append(f"{module.__name__}.{name} (module)")
                continue
            homes = [
                f"{other.__name__}.{name}"
                for other in [module, *modules]
                if getattr(other, name, None) is value and f"{other.__name__}.{name}" in documented
            ]
            if not homes:
                missing.append(f"{module.__name__}.{name}")
            elif not any(f'#{home}"' in page for home in homes):
                missing.append(f"{module.__name__}.{name} (no link on its module's page)")
    assert not missing, f"missing from the API reference: {missing}"


def _commands(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """`parser` and every subcommand under it, nested ones included."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                found += _commands(sub)
    return found


def test_the_cli_reference_has_a_section_for_every_command(repo_root: Path) -> None:
    page = (_site(repo_root) / "cli.html").read_text()
    commands = _commands(build_parser())
    assert len(commands) > 20
    progs = {c.prog for c in commands}
    assert {"labkit correct warp", "labkit calibrate dispersion", "labkit session import"} <= progs
    missing = []
    for command in commands:
        anchor = re.sub(r"[^a-z0-9]+", "-", command.prog.lower())
        if f'<section id="{anchor}">' not in page:
            missing.append(command.prog)
            continue
        shown = [a for a in command._actions if a.help != argparse.SUPPRESS]
        options = [s for a in shown for s in a.option_strings]
        missing += [f"{command.prog} {o}" for o in options if f">{o}" not in page]
    assert not missing, f"missing from the command-line reference: {missing}"


def test_the_guide_ran_as_written_when_the_site_was_built(repo_root: Path) -> None:
    """The user guide's pages and the API tour ran while the site was built (a failing block
    fails the build), the text they ran is the text of the pages now, and each page shows
    what its blocks printed. ``guide-runs.json`` records each page's run."""
    html = _site(repo_root)
    runs = json.loads((html / "guide-runs.json").read_text(encoding="utf-8"))
    expected = {"guide/simulated-rig", "guide/capture", "guide/bluesky", "guide/calibration"}
    expected |= {"guide/reconstruction", "python-api"}
    assert expected <= set(runs), sorted(runs)
    for page, run in runs.items():
        assert run["blocks"] >= 1 and run["seconds"] > 0, (page, run)
        source = (repo_root / "docs" / f"{page}.md").read_bytes()
        assert hashlib.sha256(source).hexdigest() == run["sha256"], (
            f"docs/{page}.md changed since the site was built: run `make docs`"
        )
        text = (html / f"{page}.html").read_text(encoding="utf-8")
        assert "Output, from the build of this page" in text, page
    tour = (html / "python-api.html").read_text(encoding="utf-8")
    assert "frames" in tour and "patches" in tour  # what the capture and the solve printed


def test_the_benchmarks_page_is_made_from_the_published_bench_json(repo_root: Path) -> None:
    """Each stage and case of ``docs/benchmarks/bench.json`` is on the page, with its plots."""
    html = _site(repo_root)
    page = (html / "benchmarks.html").read_text(encoding="utf-8")
    published = repo_root / "docs" / "benchmarks" / "bench.json"
    if not published.is_file():
        assert "No benchmark has been published" in page
        return
    payload = json.loads(published.read_text(encoding="utf-8"))
    # the page's text, as a reader sees it (Sphinx typesets ' as ’)
    text = html_unescape(re.sub(r"<[^>]+>", " ", page)).replace("\u2019", "'")
    text = " ".join(text.split())
    assert payload["machine"]["date"] in text
    for stage, cases in payload["stages"].items():
        assert f">{stage}<" in page, stage
        for case in cases:
            assert " ".join(case["name"].split()) in text, case["name"]
    for files in payload["plots"].values():
        for name in files:
            assert (html / "_images" / name).is_file(), name
