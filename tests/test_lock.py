"""`requirements.lock` pins every dependency that `make test` installs."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path


def normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_requirement_of_the_installed_extras_is_pinned(repo_root: Path) -> None:
    project = tomllib.loads((repo_root / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    wanted = [*project["dependencies"], *extras["gige"], *extras["genicam"], *extras["dev"]]
    lock = (repo_root / "requirements.lock").read_text()
    pinned = {normalised(m) for m in re.findall(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==", lock, re.M)}
    missing = [r for r in wanted if normalised(re.match(r"[A-Za-z0-9._-]+", r)[0]) not in pinned]
    assert not missing, f"not pinned in requirements.lock (run `make lock`): {missing}"
