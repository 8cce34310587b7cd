"""Simulated filtered captures → labkit hdr → Algorithm 12 recovers the rig's sensitivities."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _helpers import write_rig

from calibration import channel_sensitivity, load_filtered_hdr, nominal_channel_sensitivity
from labkit.hdr import run_hdr
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import load_rig
from labkit.session import Session

BANDS = ["400", "450", "500", "550", "600", "650", "700"]


def test_sensitivities_from_captured_sessions_match_the_rig(tmp_path: Path, sim_rig_path: Path):
    rig_file = write_rig(
        tmp_path,
        sim_rig_path,
        **{
            "sim.sensor.width": 96,
            "sim.sensor.height": 64,
            "sim.scenes.flat": {"type": "flat"},
            "plan.scenes": ["flat"],
            "plan.illuminations": BANDS,
            # long enough that the dim 400 nm band is properly exposed too
            "plan.exposures_s": {"unfiltered": [0.003], "filtered": [0.025, 0.1, 0.4, 1.6, 4.0]},
            "plan.replicates": {"unfiltered": 1, "filtered": 5},
        },
    )
    rig = load_rig(rig_file)
    session, _ = Session.open_for(tmp_path / "session", rig)
    with open_hardware(rig, fast=True) as hw:
        Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
    run_hdr(tmp_path / "session", tmp_path / "hdr", previews=False)
    images = [image for group in load_filtered_hdr(tmp_path / "hdr").values() for image in group]
    measured = channel_sensitivity(images)
    nominal = nominal_channel_sensitivity(rig)
    assert list(measured.wavelengths_nm) == [float(b) for b in BANDS]
    for k, wavelength in enumerate(measured.wavelengths_nm):
        j = nominal.index_of(wavelength)
        assert measured.reliable_r[k] and measured.reliable_b[k], wavelength
        for got, want in (
            (measured.r_over_g[k], nominal.r_over_g[j]),
            (measured.b_over_g[k], nominal.b_over_g[j]),
        ):
            assert np.isfinite(got)
            assert abs(got / want - 1) < 0.02, (wavelength, got, want)
