"""Shared fixtures: the simulated rig file, a small simulated rig and a seeded RNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _helpers import QUICK_PLAN, THESIS_EXPOSURES, write_rig

from labkit.rig import load_rig
from labkit.sim import SimulatedRig

REPO_ROOT = Path(__file__).parents[1]

#: Sensor size (rows, cols) of the shared small simulated rig: small enough to render in a
#: fraction of a second, large enough for a ColorChecker and a few calibration disks.
SMALL_SHAPE = (128, 160)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (the folder holding ``rigs/`` and ``labkit/``)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def sim_rig_path() -> Path:
    """Path of ``rigs/simulated.yaml``."""
    path = REPO_ROOT / "rigs" / "simulated.yaml"
    assert path.is_file(), f"{path} is missing"
    return path


@pytest.fixture(scope="session")
def small_sim_rig(sim_rig_path: Path) -> SimulatedRig:
    """The simulated thesis rig with a small (128 × 160) sensor, shared by the session.

    Tests may read from it and render with it (renders are cached per scene and
    illumination), but must not mutate it.
    """
    return SimulatedRig(load_rig(sim_rig_path), shape=SMALL_SHAPE)


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh, seeded random generator per test."""
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def small_rig_file(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path) -> Path:
    """A copy of the simulated rig with a 96 × 64 sensor, for command-line tests."""
    import yaml

    data = yaml.safe_load(sim_rig_path.read_text())
    data["sim"]["sensor"].update(width=96, height=64)
    data["sim"]["scenes"]["disks"].update(radius_px=4, pitch_px=16)
    path = tmp_path_factory.mktemp("rig") / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture
def quick_rig_file(tmp_path: Path, sim_rig_path: Path) -> Path:
    """The simulated rig with a 64 × 96 sensor and a 38-frame plan (see QUICK_PLAN)."""
    return write_rig(tmp_path, sim_rig_path, **QUICK_PLAN)


@pytest.fixture(scope="session")
def thesis_rig_path(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path) -> Path:
    """The simulated rig with the thesis' fixed exposure lists instead of auto-bracketing."""
    folder = tmp_path_factory.mktemp("thesis-rig")
    return write_rig(folder, sim_rig_path, **{"plan.exposures_s": THESIS_EXPOSURES})


@pytest.fixture
def make_rig(tmp_path: Path, sim_rig_path: Path):
    """Factory: ``make_rig(**{"dotted.key": value})`` writes a variant of the simulated rig."""
    counter = iter(range(1000))

    def make(**changes: object) -> Path:
        folder = tmp_path / f"rig{next(counter)}"
        folder.mkdir()
        return write_rig(folder, sim_rig_path, **changes)

    return make
