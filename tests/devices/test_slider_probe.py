"""Tests of slider discovery: which protocol answers on a serial port (probe)."""

from __future__ import annotations

import pytest

from labkit.devices.slider_probe import probe
from labkit.errors import DeviceError
from labkit.sim.elliptec import ElliptecSimulator
from labkit.sim.fw102c import FW102CSimulator


def test_probe_identifies_the_fw102c() -> None:
    moves: list[int] = []
    with FW102CSimulator(time_scale=0, on_move=moves.append) as sim:
        assert probe(sim.port, timeout_s=0.3) == (
            "fw102c",
            "THORLABS FW102C/FW212C Filter Wheel version 1.07",
        )
        assert (sim.position, moves) == (1, [])


@pytest.mark.parametrize(("model", "address"), [("ELL9", "0"), ("ELL6", "5")])
def test_probe_identifies_the_elliptec(model: str, address: str) -> None:
    moves: list[int] = []
    with ElliptecSimulator(model, address=address, time_scale=0, on_move=moves.append) as sim:
        found = probe(sim.port, timeout_s=0.2, addresses="05")
        assert (sim.position, moves) == (1, [])
    assert found == (
        "elliptec",
        f"Thorlabs Elliptec {model} serial 11200456 at address {address} "
        "(2019, firmware 17, hardware 1)",
    )


def test_probe_silent_port_is_none(silent_port: str) -> None:
    assert probe(silent_port, timeout_s=0.2) is None


def test_probe_elliptec_at_an_address_not_asked_is_none() -> None:
    with ElliptecSimulator("ELL9", address=7, time_scale=0) as sim:
        assert probe(sim.port, timeout_s=0.2) is None


def test_probe_missing_port_raises(fake_ports: None) -> None:
    with pytest.raises(DeviceError, match="serial port /dev/ttyUSB7 does not exist"):
        probe("/dev/ttyUSB7")
