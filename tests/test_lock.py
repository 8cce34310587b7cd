"""`requirements.lock` pins every dependency that `make test` installs."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest


def normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def package(requirement: str) -> str:
    """The normalised package name of a requirement such as ``"numpy>=1.26"``."""
    return normalised(re.match(r"[A-Za-z0-9._-]+", requirement)[0])


def test_every_requirement_of_the_installed_extras_is_pinned(repo_root: Path) -> None:
    project = tomllib.loads((repo_root / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    installed = re.search(r'-e "\.\[([a-z,]+)\]"', (repo_root / "Makefile").read_text())
    assert installed, "the Makefile's install line was not found"
    names = installed[1].split(",")
    assert set(names) == set(extras), f"make installs {names}, pyproject has {sorted(extras)}"
    wanted = [*project["dependencies"], *(r for name in names for r in extras[name])]
    lock = (repo_root / "requirements.lock").read_text()
    pinned = {normalised(m) for m in re.findall(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==", lock, re.M)}
    missing = [r for r in wanted if package(r) not in pinned]
    assert not missing, f"not pinned in requirements.lock (run `make lock`): {missing}"


@pytest.mark.parametrize("extra", ["docs", "bluesky", "tiled", "xarray"])
def test_the_core_install_stays_lean(repo_root: Path, extra: str) -> None:
    """Sphinx, Bluesky (ophyd, ophyd-async), Tiled and xarray are extras: `pip install
    labkit` does not pull them in."""
    project = tomllib.loads((repo_root / "pyproject.toml").read_text())["project"]
    core = {package(r) for r in project["dependencies"]}
    optional = {package(r) for r in project["optional-dependencies"][extra]}
    assert optional and not optional & core, f"{extra}: {sorted(optional & core)} are core"


BLOCK_EXTRAS = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"sphinx", "bluesky", "ophyd", "ophyd_async", "event_model",
                                  "tiled", "bluesky_tiled_plugins", "xarray", "pandas"}:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)")
sys.meta_path.insert(0, Block())
"""


def test_labkit_works_without_its_extras(repo_root: Path, tmp_path: Path) -> None:
    """With Sphinx, Bluesky, ophyd, ophyd-async, Tiled and xarray unimportable, the library
    and every command still load, and a spectral image is written and read; only to_xarray
    needs its extra."""
    code = BLOCK_EXTRAS + (
        "import numpy as np, labkit.cli, reconstruction, calibration\n"
        "from labkit.errors import ConfigError\n"
        "from labkit.io import SpectralImage, read_spectral_exr, write_spectral_exr\n"
        "labkit.cli.build_parser()\n"
        "image = SpectralImage(np.ones((4, 4, 3)), np.array([450.0, 550.0, 650.0]))\n"
        f"write_spectral_exr({str(tmp_path / 'x.exr')!r}, image)\n"
        f"back = read_spectral_exr({str(tmp_path / 'x.exr')!r})\n"
        "try:\n    back.to_xarray()\nexcept ConfigError as error:\n    print(error)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=repo_root, check=False
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "xarray is not installed" in result.stdout
