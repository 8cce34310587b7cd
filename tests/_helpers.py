"""Helpers shared by tests (importable because pytest puts tests/ on sys.path)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from labkit.sim import SimulatedRig

#: A small, quick capture plan: 2 scenes × (unfiltered 2×3 + 2 filters 2×2×2) + darks = 38 frames.
QUICK_PLAN = {
    "sim.sensor.width": 96,
    "sim.sensor.height": 64,
    "sim.scenes.disks": {"type": "disks", "radius_px": 4, "pitch_px": 16},
    "plan.illuminations": ["unfiltered", "450", "600"],
    "plan.exposures_s": {"unfiltered": [0.003, 0.012], "filtered": [0.1, 0.5]},
    "plan.replicates": {"unfiltered": 3, "filtered": 2},
}
QUICK_PLAN_FRAMES = 2 * (2 * 3 + 2 * 2 * 2) + (2 * 3 + 2 * 2)


def quick_plan() -> dict:
    """A fresh copy of QUICK_PLAN (safe to modify)."""
    return copy.deepcopy(QUICK_PLAN)


def expected_counts(
    world: SimulatedRig, scene: str | None, illumination: str, exposure_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free counts of a frame and a mask of pixels untouched by saturation.

    The mask excludes pixels within 2 px of a saturated one (blooming reaches them).
    """
    from scipy import ndimage

    model = world.sensor.model
    irradiance = None if scene is None else world.irradiance(scene, illumination)
    electrons = world.sensor.mean_electrons(irradiance, exposure_s)
    saturated = electrons >= 0.9 * model.full_well_e
    clean = ~ndimage.binary_dilation(saturated, iterations=2)
    counts = np.minimum(electrons, model.full_well_e) * model.gain_factor(0.0)
    return np.minimum(counts + model.black_level_dn, model.adc_max), clean


def simulate_bracket(sensor, irradiance, exposures_s, *, replicates=5, darks=5, rng):
    """Frames of an exposure bracket straight from a simulated sensor (no camera, no disk).

    Returns (exposure inputs, {exposure: DarkFrame}, {exposure: mean true exposure s}); the
    true exposures include the shutter jitter of every replicate.
    """
    from labkit.hdr import DarkFrame, ExposureInput

    inputs, dark_frames, actual = [], {}, {}
    for t in exposures_s:
        frames, real = [], []
        for _ in range(replicates):
            counts, exposure = sensor.expose(irradiance, t, rng=rng)
            frames.append(counts)
            real.append(exposure)
        inputs.append(ExposureInput.from_arrays(t, frames))
        actual[t] = float(np.mean(real))
        dark = [sensor.expose(None, t, rng=rng)[0] for _ in range(darks)]
        dark_frames[t] = DarkFrame.from_frames(ExposureInput.from_arrays(t, dark))
    return inputs, dark_frames, actual


def sensor_levels(model):
    """SensorLevels of a simulated SensorModel at 0 dB (what the sim camera reports)."""
    from labkit.hdr import SensorLevels

    return SensorLevels(model.saturation_dn(), model.black_level_dn)


#: The thesis' fixed exposure lists (§4.2.2), s; the simulated rig file auto-brackets.
THESIS_EXPOSURES = {
    "unfiltered": [0.003, 0.006, 0.012],
    "filtered": [0.025, 0.05, 0.1, 0.25, 0.5, 2.0, 3.916],
}


def write_rig(folder: Path, base: Path, **changes: object) -> Path:
    """Write a variant of the rig file `base` into `folder`; `changes` maps dotted keys to values.

    Example: ``write_rig(tmp, sim_rig_path, **{"sim.sensor.width": 96, "plan.scenes": ["flat"]})``.
    """
    import yaml

    data = yaml.safe_load(base.read_text())
    for dotted, value in changes.items():
        node = data
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(int(key) if key.isdigit() else key, {})
        node[int(leaf) if leaf.isdigit() else leaf] = value
    path = folder / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def planted_dispersion_model(
    fields: dict,
    *,
    shape: tuple[int, int],
    direction: str,
    wavelength_span: tuple[float, float] | None = None,
):
    """A DispersionModel over planted test fields, calibrated over the whole image.

    ``{"spectral": field}`` gives a spectral model referenced to 600 nm whose region spans
    `wavelength_span`; channel fields (``"R"``, ``"B"``) give a colour model referenced to G.
    """
    from calibration.dispersion_model import CalibratedRegion, DispersionModel

    x, y = np.meshgrid([0.0, shape[1] - 1.0], [0.0, shape[0] - 1.0])
    spectral = "spectral" in fields
    wavelengths = np.array(wavelength_span) if spectral else None
    return DispersionModel(
        type="test",
        variables="xylambda" if spectral else "xy",
        direction=direction,
        reference=600.0 if spectral else "G",
        image_shape=shape,
        fields=fields,
        region=CalibratedRegion.from_points(x, y, wavelengths),
    )


def lens_model_file(path: Path, shape: tuple[int, int], direction: str = "from_reference"):
    """A small polynomial spectral model (≤ 1 px lateral colour) fitted to the simulated
    lens' exact displacements at 450–650 nm, referenced to 600 nm; saved to `path`."""
    from calibration.keypoints import DispersionKeypoints
    from calibration.polynomial import fit_polynomial_model
    from labkit.sim.lens import Lens

    lens = Lens(shape, max_shift_px=1.0)
    gy, gx = np.mgrid[4 : shape[0] - 4 : 8, 4 : shape[1] - 4 : 8].astype(float)
    parts = []
    for w in (450.0, 500.0, 550.0, 600.0, 650.0):
        dx, dy = lens.displacement(gx.ravel(), gy.ravel(), w)
        parts.append((gx.ravel(), gy.ravel(), dx, dy, np.full(gx.size, w)))
    x, y, dx, dy, w = (np.concatenate(c) for c in zip(*parts, strict=True))
    keypoints = DispersionKeypoints(
        x, y, dx, dy, reference=600.0, image_shape=shape, wavelength_nm=w
    )
    model = fit_polynomial_model(
        keypoints, direction=direction, max_degree_xy=2, max_degree_lambda=2, folds=2
    )
    return model.save(path)


def assert_verified_and_merged_alike(session, folder: Path, capsys, *, images: int) -> None:
    """`session` (a Bluesky capture in ``folder/bluesky``) verifies clean and complete, and
    ``labkit hdr`` merges it into the same `images` HDR images, bit for bit, as the
    ``labkit capture`` session in ``folder/engine``."""
    from labkit.cli import main
    from labkit.io import read_raw_exr

    capsys.readouterr()
    assert main(["session", "show", str(session.folder), "--verify"]) == 0
    shown = capsys.readouterr().out
    assert f"all {len(session.records)} frames match their sha256" in shown
    assert "status    complete" in shown and "(0 missing)" in shown
    for name in ("bluesky", "engine"):
        assert main(["hdr", str(folder / name), "--out", str(folder / f"hdr-{name}"),
                     "--no-preview"]) == 0  # fmt: skip
    merged = sorted((folder / "hdr-engine").rglob("*.exr"))
    assert len(merged) == images
    for path in merged:
        twin = folder / "hdr-bluesky" / path.relative_to(folder / "hdr-engine")
        np.testing.assert_array_equal(read_raw_exr(twin).raw, read_raw_exr(path).raw)
