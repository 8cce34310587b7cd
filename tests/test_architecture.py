"""The layers of pyproject.toml's import contracts cover the code, and imports stay visible.

``lint-imports`` (run by ``make test``) checks the contracts themselves: no module imports
from a layer above its own, and no package's modules import each other in a cycle, counting
imports inside functions too. These tests check what it cannot: that every part of the
code has a layer (a part in none would be unchecked), and that imports inside functions,
which hide a module's dependencies from its reader, are kept to the places that need them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT_PACKAGES = ("labkit", "calibration", "reconstruction")

#: Application modules: they load the stack of each command or benchmark on use, so that
#: ``labkit --help`` and every command start without importing what they do not run.
DEFERRING_MODULES = (
    "labkit.cli",
    "labkit.bench",
    "labkit.demo",
    "labkit.demo_real",
    "labkit.real_chart",
    "labkit.demo_steps",
)

#: Imports inside functions of library modules, and why each is there.
DEFERRED_IMPORTS = {
    ("calibration.sensitivity.plot", "labkit.plots"): "matplotlib, for the one function that plots",
    ("labkit.io.preview", "labkit.spectra.conversion"): (
        "the spectral tables, for spectral previews only: most users of labkit.io write raw images"
    ),
    ("labkit.io.spectral_exr", "labkit.spectra.conversion"): (
        "the spectral tables, for the RGB channels of spectral EXRs only (as for previews)"
    ),
    ("labkit.protocol.hardware", "labkit.devices.aravis"): (
        "Aravis through PyGObject: a system library that only an Aravis rig needs"
    ),
    ("labkit.protocol.hardware", "labkit.devices.genicam"): (
        "Harvesters and a GenTL producer: only a GenICam rig needs them"
    ),
}


def _contract(repo_root: Path, contract_id: str) -> dict:
    config = tomllib.loads((repo_root / "pyproject.toml").read_text())["tool"]["importlinter"]
    (contract,) = [c for c in config["contracts"] if c["id"] == contract_id]
    return contract


def _module_name(path: Path, repo_root: Path) -> str:
    parts = path.relative_to(repo_root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _library_files(repo_root: Path) -> list[Path]:
    return sorted(f for package in ROOT_PACKAGES for f in (repo_root / package).rglob("*.py"))


def _imported_module(node: ast.ImportFrom, package: str) -> str:
    """The absolute name of the module a ``from … import`` in `package` imports from."""
    base = node.module or ""
    if node.level:
        anchor = package.rsplit(".", node.level - 1)[0]
        base = f"{anchor}.{base}" if base else anchor
    return base


def _imports_inside_functions(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, imported module) of first-party imports inside functions of `path`."""
    found: list[tuple[int, str]] = []
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]

    def visit(node: ast.AST, inside: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if inside and isinstance(child, ast.Import):
                found.extend((child.lineno, alias.name) for alias in child.names)
            elif inside and isinstance(child, ast.ImportFrom):
                found.append((child.lineno, _imported_module(child, package)))
            is_function = isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            visit(child, inside or is_function)

    visit(ast.parse(path.read_text(), filename=str(path)), False)
    return [(line, name) for line, name in found if name.split(".")[0] in ROOT_PACKAGES]


def test_every_part_of_the_code_has_a_layer(repo_root: Path) -> None:
    layers = _contract(repo_root, "layers")["layers"]
    named = {name.strip("() ") for layer in layers for name in layer.replace("|", ":").split(":")}
    parts = {"calibration", "reconstruction"}
    for path in (repo_root / "labkit").iterdir():
        if path.name.startswith(("_", ".")) and path.name != "__main__.py":
            continue
        if path.suffix == ".py" or (path / "__init__.py").is_file():
            parts.add(f"labkit.{path.stem}")
    missing = sorted(parts - named)
    assert not missing, (
        f"{missing} belong to no layer of pyproject.toml's import contract; add each where it "
        "belongs (docs/architecture.md)"
    )
    unknown = sorted(named - parts)
    assert not unknown, f"the layers name {unknown}, which are not in the code"


def test_imports_inside_functions_only_where_they_pay(repo_root: Path) -> None:
    seen, unexplained = set(), []
    for path in _library_files(repo_root):
        module = _module_name(path, repo_root)
        if module.startswith(DEFERRING_MODULES):
            continue
        for line, imported in _imports_inside_functions(path, module):
            key = (module, imported)
            seen.add(key)
            if key not in DEFERRED_IMPORTS:
                unexplained.append(f"{path.relative_to(repo_root)}:{line} imports {imported}")
    assert not unexplained, (
        "imports inside functions hide a module's dependencies; move these to the top of the "
        "module (if that makes a cycle, move the shared piece down a layer instead), or add "
        f"them to DEFERRED_IMPORTS with the reason: {unexplained}"
    )
    stale = sorted(set(DEFERRED_IMPORTS) - seen)
    assert not stale, f"DEFERRED_IMPORTS lists imports the code no longer makes: {stale}"


def test_the_inside_function_scan_sees_relative_and_nested_imports(tmp_path: Path) -> None:
    package = tmp_path / "calibration"
    package.mkdir()
    source = package / "example.py"
    source.write_text(
        "import numpy\n"
        "from calibration import warp\n"
        "def f():\n"
        "    from .bands import FilterBand\n"
        "    import labkit.io\n"
        "    def g():\n"
        "        from reconstruction import reconstruct\n"
        "    import scipy\n"
    )
    found = _imports_inside_functions(source, "calibration.example")
    assert found == [(4, "calibration.bands"), (5, "labkit.io"), (7, "reconstruction")]


def _private_imports(path: Path, module: str, repo_root: Path) -> list[tuple[int, str]]:
    """(line, name) of first-party private names `path` imports against the rule.

    A private name (a leading underscore) is part of its module's insides. Another module
    may import it only from a private module (``_name.py``, or a private package) of a
    package it belongs to itself: helpers shared by siblings live in such a module, not in
    one of the siblings.
    """
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom):
            base = _imported_module(node, package)
            names = [f"{base}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] not in ROOT_PACKAGES:
                continue
            private = [i for i, part in enumerate(parts) if part.startswith("_")]
            if not private or parts[private[0]] == "__future__":
                continue
            owner = ".".join(parts[: private[0]])
            inside_owner = f"{module}.".startswith(f"{owner}.")
            as_path = repo_root.joinpath(*parts)
            is_module = as_path.with_suffix(".py").is_file() or as_path.is_dir()
            if not inside_owner or (private[0] == len(parts) - 1 and not is_module):
                found.append((node.lineno, name))
    return found


def test_private_names_are_shared_only_through_private_modules(repo_root: Path) -> None:
    crossing = [
        f"{path.relative_to(repo_root)}:{line} imports {name}"
        for path in _library_files(repo_root)
        for line, name in _private_imports(path, _module_name(path, repo_root), repo_root)
    ]
    assert not crossing, (
        "these modules import private names of others; move what siblings share into a "
        "private module of their package (named for what it holds), or make it public: "
        f"{crossing}"
    )


def test_the_private_import_scan_sees_each_kind(tmp_path: Path) -> None:
    package = tmp_path / "calibration" / "disks"
    package.mkdir(parents=True)
    for name in ("fit", "_pool", "model"):
        (package / f"{name}.py").write_text("")
    source = package / "keypoints.py"
    source.write_text(
        "from calibration.disks._pool import _finish\n"
        "from calibration.disks import _pool\n"
        "from calibration.disks.fit import _start\n"
        "from .model import _DiskModel, DiskModel\n"
        "from calibration._hdr_inputs import load_scene_hdr\n"
        "from __future__ import annotations\n"
    )
    found = _private_imports(source, "calibration.disks.keypoints", tmp_path)
    assert found == [
        (3, "calibration.disks.fit._start"),
        (4, "calibration.disks.model._DiskModel"),
    ]
    outside = _private_imports(source, "labkit.cli.calibrate", tmp_path)
    assert (5, "calibration._hdr_inputs.load_scene_hdr") in outside


def test_the_import_contracts_are_kept(repo_root: Path) -> None:
    linter = Path(sys.executable).parent / "lint-imports"
    assert linter.exists(), f"{linter} is missing: `make test` installs import-linter"
    done = subprocess.run(
        [str(linter), "--no-cache", "--no-logo"],
        cwd=repo_root,
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
