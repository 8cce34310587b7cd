"""The main entry points are importable from the package tops, and ``import labkit`` stays
cheap: its names load their modules on first use."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import labkit


def test_every_top_level_name_is_its_modules_object() -> None:
    assert len(labkit.__all__) >= 20 and labkit.__all__ == sorted(labkit.__all__)
    for name in labkit.__all__:
        value = getattr(labkit, name)
        module = importlib.import_module(labkit._EXPORTS[name])
        assert value is getattr(module, name), name
        assert name in dir(labkit)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        labkit.nothing  # noqa: B018


def test_import_labkit_loads_nothing_heavy() -> None:
    heavy = ("numpy", "scipy", "labkit.hdr")
    code = f"import sys, labkit; print(sorted(m for m in {heavy!r} if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_the_jobs_run_from_the_package_tops() -> None:
    """One name per job, from where the docs import it."""
    from calibration import calibrate_dispersion, channel_sensitivity, load_dispersion_model
    from labkit import Engine, SimulatedRig, load_rig, run_hdr
    from reconstruction import ReconstructOptions, evaluate, reconstruct

    assert all(
        callable(f) for f in (calibrate_dispersion, channel_sensitivity, load_dispersion_model)
    )
    assert all(callable(f) for f in (Engine, SimulatedRig, load_rig, run_hdr))
    assert all(callable(f) for f in (ReconstructOptions, evaluate, reconstruct))
