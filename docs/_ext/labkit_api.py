"""The API reference: one page per public module, and where each public name is documented.

A module of labkit, calibration or reconstruction is public when no part of its dotted
name starts with an underscore. Its public names are its ``__all__``; a module without
one exports the functions and classes it defines whose names do not start with an
underscore, and the module-level values it documents with a ``#:`` comment or a
docstring.

Packages re-export names from their modules (``from calibration import
calibrate_dispersion``), so most names are public in two or more modules. Each object is
documented once, on the page of the public module that defines it; a name whose defining
module is private (``calibration._hdr_inputs``) or does not export it is documented on
the page of the nearest public module that does. Every page lists all its public names in
a summary table (autosummary) whose links lead to where each is documented.

As a Sphinx extension this module writes the pages, ``api/<module>.rst``, from
``_templates/api/module.rst`` when the build starts (:func:`write_pages`). Once every page
is read it registers each re-exported name (``calibration.calibrate_dispersion``) as an
alias of the object documented elsewhere (:func:`register_aliases`), so cross-references,
the gallery's code links and ``objects.inv`` know the object under every public name; and
it resolves references to the members of such names (:func:`resolve_reexport`).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import ModuleType

import jinja2
from docutils.nodes import Element
from sphinx.addnodes import pending_xref
from sphinx.application import Sphinx
from sphinx.domains.python import ObjectEntry
from sphinx.environment import BuildEnvironment
from sphinx.pycode import ModuleAnalyzer

ROOTS = ("labkit", "calibration", "reconstruction")
TEMPLATES = Path(__file__).parents[1] / "_templates" / "api"


@dataclass(frozen=True)
class Name:
    """One public name of one module: what it is and where it is documented."""

    module: str
    name: str
    kind: str  # autodoc's directive: "function", "class", "exception", "data" or "module"
    target: str  # the full name it is documented under


def public_modules(roots: tuple[str, ...] = ROOTS) -> list[str]:
    """Every public module of the packages `roots` (themselves included), sorted."""
    found = []
    for root in roots:
        package = importlib.import_module(root)
        found.append(root)
        for info in pkgutil.walk_packages(package.__path__, f"{root}.", onerror=_raise):
            if not any(part.startswith("_") for part in info.name.split(".")):
                found.append(info.name)
    return sorted(found)


def _raise(name: str) -> None:
    raise ImportError(f"cannot import {name} for the API reference")


@cache
def _assigned(module: str) -> frozenset[str]:
    """Names bound by top-level assignments in `module`'s source."""
    source = inspect.getsource(importlib.import_module(module))
    names = set()
    for node in ast.parse(source).body:
        targets = node.targets if isinstance(node, ast.Assign) else []
        if isinstance(node, ast.AnnAssign):
            targets = [node.target]
        names.update(t.id for t in targets if isinstance(t, ast.Name))
    return frozenset(names)


@cache
def _documented_values(module: str) -> frozenset[str]:
    """Module-level names that `module` documents with ``#:`` comments or docstrings."""
    analyzer = ModuleAnalyzer.for_module(module)
    return frozenset(name for scope, name in analyzer.find_attr_docs() if scope == "")


@cache
def exported(module: str) -> tuple[str, ...]:
    """The public names of `module` (see the module docstring)."""
    mod = importlib.import_module(module)
    if hasattr(mod, "__all__"):
        return tuple(mod.__all__)
    names = []
    for name, value in vars(mod).items():
        if name.startswith("_") or inspect.ismodule(value):
            continue
        defined_here = getattr(value, "__module__", None) == module and (
            inspect.isclass(value) or inspect.isroutine(value)
        )
        if defined_here or name in _documented_values(module):
            names.append(name)
    return tuple(sorted(names))


def _kind(value: object) -> str:
    if inspect.ismodule(value):
        return "module"
    if inspect.isclass(value):
        return "exception" if issubclass(value, BaseException) else "class"
    if inspect.isroutine(value):
        return "function"
    return "data"


def _shared_parts(a: str, b: str) -> int:
    """How many leading parts the dotted names `a` and `b` share."""
    shared = 0
    for x, y in zip(a.split("."), b.split("."), strict=False):
        if x != y:
            break
        shared += 1
    return shared


def _origin(value: object, name: str, module: str, roots: tuple[str, ...]) -> str | None:
    """The module that defines `value`, exported as `name` by `module`.

    A class's or function's ``__module__``; for other values, the loaded module of `roots`
    whose source assigns `name` to that same object, the nearest to `module` where several
    do (equal strings and small integers can be one object).
    """
    if inspect.isclass(value) or inspect.isroutine(value):
        return getattr(value, "__module__", None)
    assigning = [
        module_name
        for module_name, loaded in list(sys.modules.items())
        if module_name.split(".")[0] in roots
        and getattr(loaded, name, None) is value
        and name in _assigned(module_name)
    ]
    if not assigning:
        return None
    return min(assigning, key=lambda m: (-_shared_parts(m, module), m))


def _home(origin: str | None, exporters: list[str]) -> str:
    """The module whose page documents a name: its origin if that exports it, else the
    exporter nearest to the origin (then the shallowest)."""
    if origin in exporters:
        return origin
    return min(exporters, key=lambda m: (-_shared_parts(m, origin or ""), m.count("."), m))


@cache
def api_names(roots: tuple[str, ...] = ROOTS) -> dict[str, list[Name]]:
    """Module → its public names, each with the full name it is documented under."""
    modules = public_modules(roots)
    loaded: dict[str, ModuleType] = {m: importlib.import_module(m) for m in modules}
    pages: dict[str, list[Name]] = {}
    for module in modules:
        names = []
        for name in exported(module):
            value = getattr(loaded[module], name)
            kind = _kind(value)
            if kind == "module":
                names.append(Name(module, name, kind, value.__name__))
                continue
            exporters = [
                m
                for m in modules
                if name in exported(m) and getattr(loaded[m], name, None) is value
            ]
            home = _home(_origin(value, name, module, roots), exporters)
            names.append(Name(module, name, kind, f"{home}.{name}"))
        pages[module] = names
    return pages


def api_pages(roots: tuple[str, ...] = ROOTS) -> dict[str, dict[str, list]]:
    """What the module template needs, per public module.

    ``documented``: ``[name, kind]`` of the names documented on the module's page;
    ``summary``: the full names of all its public names but modules, for the table;
    ``modules``: ``[name, summary]`` of its public submodules.
    """
    modules = public_modules(roots)
    pages = {}
    for module, names in api_names(roots).items():
        pages[module] = {
            "documented": [
                [n.name, n.kind]
                for n in names
                if n.kind != "module" and n.target == f"{module}.{n.name}"
            ],
            "summary": [n.target for n in names if n.kind != "module"],
            "modules": [[m, summary_line(m)] for m in modules if m.rpartition(".")[0] == module],
        }
    return pages


def summary_line(module: str) -> str:
    """The first paragraph of `module`'s docstring, on one line."""
    doc = inspect.getdoc(importlib.import_module(module)) or ""
    return " ".join(doc.split("\n\n")[0].split())


def render_pages(roots: tuple[str, ...] = ROOTS) -> dict[str, str]:
    """Module → the reStructuredText of its page."""
    environment = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES), keep_trailing_newline=True
    )
    template = environment.get_template("module.rst")
    return {
        module: template.render(fullname=module, page=page)
        for module, page in api_pages(roots).items()
    }


def write_pages(app: Sphinx) -> None:
    """Write ``api/<module>.rst`` for every public module (files whose text is unchanged
    are left alone) and remove the pages of modules that are gone."""
    folder = Path(app.srcdir) / "api"
    folder.mkdir(exist_ok=True)
    pages = render_pages()
    for module, text in pages.items():
        path = folder / f"{module}.rst"
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)
    for path in folder.glob("*.rst"):
        if path.stem not in pages:
            path.unlink()


@cache
def aliases(roots: tuple[str, ...] = ROOTS) -> dict[str, str]:
    """``module.name`` → the full name it is documented under, where the two differ
    (``calibration.DispersionModel`` → ``calibration.dispersion_model.DispersionModel``)."""
    return {
        f"{n.module}.{n.name}": n.target
        for names in api_names(roots).values()
        for n in names
        if n.kind != "module" and n.target != f"{n.module}.{n.name}"
    }


def resolve_reexport(
    app: Sphinx, env: BuildEnvironment, node: pending_xref, contnode: Element
) -> Element | None:
    """Resolve a Python cross-reference through a re-exported name
    (``:meth:`calibration.DispersionModel.displacement```) to the page that documents the
    object; the aliases of :func:`register_aliases` cover the names themselves, not their
    members."""
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"]
    module = node.get("py:module")
    known = aliases()
    for candidate in (target, f"{module}.{target}" if module else None):
        if not candidate:
            continue
        parts = candidate.split(".")
        for end in range(len(parts), 0, -1):
            real = known.get(".".join(parts[:end]))
            if real is not None:
                full = ".".join([real, *parts[end:]])
                return env.get_domain("py").resolve_xref(
                    env, node["refdoc"], app.builder, node["reftype"], full, node, contnode
                )
    return None


def register_aliases(app: Sphinx, env: BuildEnvironment) -> None:
    """Add every re-exported name to the Python domain as an alias of the documented object
    (as autodoc's ``:canonical:`` does for a class's defining module)."""
    domain = env.get_domain("py")
    objects = domain.objects  # type: ignore[attr-defined]
    for alias, target in aliases().items():
        entry = objects.get(target)
        if entry is not None and alias not in objects:
            objects[alias] = ObjectEntry(entry.docname, entry.node_id, entry.objtype, True)


def setup(app: Sphinx) -> dict[str, object]:
    app.connect("builder-inited", write_pages)
    app.connect("env-updated", register_aliases)
    app.connect("missing-reference", resolve_reexport)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
