"""Tests of the Elliptec ELL6/ELL9 slider driver against the Elliptec simulator on a pty."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import serial

from labkit.devices.elliptec import (
    Elliptec,
    ElliptecInfo,
    decode_position,
    encode_position,
    identify_elliptec,
    nearest_slot,
    parse_info,
    status_text,
)
from labkit.devices.slider import FilterSlider
from labkit.errors import ConfigError, DeviceError
from labkit.sim.elliptec import ElliptecSimulator

RETRIES = 3


def open_slider(port: str, *, address: int | str = 0, slots: int | None = None) -> Elliptec:
    """The driver with short timeouts (the simulator answers within milliseconds)."""
    return Elliptec(
        port, address=address, slots=slots, timeout_s=0.3, move_timeout_s=0.4, retries=RETRIES
    )


ELL9_IDENTITY = (
    "Thorlabs Elliptec ELL9 serial 11200456 at address 0 (2019, firmware 17, hardware 1)"
)


@pytest.fixture
def moves() -> list[int]:
    return []


@pytest.fixture
def sim(moves: list[int]) -> Iterator[ElliptecSimulator]:
    with ElliptecSimulator("ELL9", time_scale=0, seed=5, on_move=moves.append) as simulator:
        yield simulator


@pytest.fixture
def slider(sim: ElliptecSimulator) -> Iterator[Elliptec]:
    with open_slider(sim.port) as driver:
        sim.clear_transcript()
        yield driver


def commands_sent(sim: ElliptecSimulator) -> list[bytes]:
    return [entry.data for entry in sim.transcript() if entry.direction == "rx"]


def last_tx(sim: ElliptecSimulator) -> bytes:
    return [entry.data for entry in sim.transcript() if entry.direction == "tx"][-1]


# -- encoding ---------------------------------------------------------------------------------


def test_parse_info_of_a_real_ell6k_reply() -> None:
    info = parse_info("0IN061060005120170801001F00000000\r\n")
    assert info == ElliptecInfo(
        address="0",
        model_code=6,
        serial_number="10600051",
        year=2017,
        firmware="08",
        hardware=0x01,
        travel=31,
        pulses_per_unit=0,
    )
    assert info.model == "ELL6"
    assert not info.imperial
    assert str(info) == (
        "Thorlabs Elliptec ELL6 serial 10600051 at address 0 (2017, firmware 08, hardware 1)"
    )


def test_parse_info_rotation_mount_and_imperial_flag() -> None:
    info = parse_info("AIN0E1140051720150181001F00000001")
    assert (info.address, info.model, info.year, info.firmware) == ("A", "ELL14", 2015, "01")
    assert info.imperial
    assert (info.travel, info.pulses_per_unit) == (31, 1)


@pytest.mark.parametrize(
    "reply",
    [
        "0PO00000000",
        "0IN061060005120170801001F0000000",  # one character short
        "0IN0610600051201X0801001F00000000",  # year not numeric
        "gIN061060005120170801001F00000000",  # bad address
        "",
    ],
)
def test_parse_info_rejects_other_replies(reply: str) -> None:
    with pytest.raises(ValueError, match="not an Elliptec `in` reply"):
        parse_info(reply)


@pytest.mark.parametrize(
    ("pulses", "hex_text"),
    [(0, "00000000"), (31, "0000001F"), (62, "0000003E"), (93, "0000005D"), (-1, "FFFFFFFF")],
)
def test_position_hex_round_trip(pulses: int, hex_text: str) -> None:
    assert encode_position(pulses) == hex_text
    assert decode_position(hex_text) == pulses


@pytest.mark.parametrize("text", ["1F", "0000001G", "000000001F", "-0000001"])
def test_decode_position_rejects_bad_hex(text: str) -> None:
    with pytest.raises(ValueError):
        decode_position(text)


@pytest.mark.parametrize(
    ("pulses", "slot"),
    [(0, 1), (-3, 1), (15, 1), (16, 2), (33, 2), (45, 2), (47, 3), (64, 3), (96, 4), (500, 4)],
)
def test_nearest_slot(pulses: int, slot: int) -> None:
    assert nearest_slot(pulses, (0, 31, 62, 93)) == slot


def test_status_text() -> None:
    assert status_text(0) == "OK, no error"
    assert status_text(2) == "mechanical time out"
    assert status_text(9) == "busy"
    assert status_text(0x0C) == "out of range"
    assert status_text(0x42) == "reserved status code"


# -- opening ----------------------------------------------------------------------------------


def test_identity_and_slot_count(sim: ElliptecSimulator, slider: Elliptec) -> None:
    assert slider.identity == ELL9_IDENTITY
    assert slider.info.model == "ELL9"
    assert slider.slot_count == 4
    assert slider.slot_positions == (0, 31, 62, 93)
    assert slider.driver == "elliptec"
    assert slider.port == sim.port
    assert isinstance(slider, FilterSlider)


def test_ell6_has_two_slots() -> None:
    with ElliptecSimulator("ELL6", time_scale=0) as sim, open_slider(sim.port) as slider:
        assert slider.slot_count == 2
        slider.move(2)
        assert sim.position == 2
        with pytest.raises(DeviceError, match=r"slot 3 is out of range 1\.\.2 for the ELL6"):
            slider.move(3)


def test_slots_more_than_the_slider_has_is_refused(sim: ElliptecSimulator) -> None:
    with pytest.raises(DeviceError, match="slot 5 is needed but the ELL9 has 4 slots"):
        open_slider(sim.port, slots=5)


def test_other_address() -> None:
    with ElliptecSimulator("ELL9", address=3, time_scale=0) as sim:
        with open_slider(sim.port, address="3") as slider:
            assert slider.identity.startswith("Thorlabs Elliptec ELL9 serial 11200456 at address 3")
            slider.move(2)
            assert sim.position == 2
        with pytest.raises(DeviceError) as caught:
            open_slider(sim.port, address=0)
    assert f"filter slider on {sim.port}: `0in` — no valid reply after 3 attempts" in str(
        caught.value
    )
    assert "its address is 0" in str(caught.value)


def test_not_a_slider_is_refused(sim: ElliptecSimulator) -> None:
    sim.handler.type_code = 0x0E  # now it claims to be an ELL14 rotation mount
    with pytest.raises(DeviceError, match="is an ELL14, not an ELL6/ELL9 multi-position slider"):
        open_slider(sim.port)


def test_missing_port_names_it() -> None:
    with pytest.raises(DeviceError, match=r"serial port /dev/ttyLABKIT7 does not exist"):
        Elliptec("/dev/ttyLABKIT7")


@pytest.mark.parametrize(
    "kwargs", [{"address": 16}, {"address": "G"}, {"retries": 0}, {"timeout_s": -1.0}]
)
def test_bad_options_are_config_errors(sim: ElliptecSimulator, kwargs: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        Elliptec(sim.port, **kwargs)  # type: ignore[arg-type]


def test_close_is_idempotent(sim: ElliptecSimulator) -> None:
    slider = open_slider(sim.port)
    slider.close()
    slider.close()
    with pytest.raises(DeviceError, match="is closed"):
        slider.move(2)
    with open_slider(sim.port) as again:
        assert again.position() == 1


# -- moving -----------------------------------------------------------------------------------


def test_move_then_read_back(sim: ElliptecSimulator, slider: Elliptec, moves: list[int]) -> None:
    slider.move(3)
    assert (sim.position, sim.pulses) == (3, 62)
    assert moves == [3]
    assert slider.position() == 3
    assert commands_sent(sim) == [b"0ma0000003E", b"0gp", b"0gp"]
    slider.move(4)
    slider.move(1)
    assert moves == [3, 4, 1]


def test_positions_a_few_pulses_off_map_to_the_nearest_slot(moves: list[int]) -> None:
    with ElliptecSimulator(
        slot_positions=(0, 32, 64, 96), time_scale=0, on_move=moves.append
    ) as sim:
        with open_slider(sim.port) as slider:
            for slot in (2, 4, 3):
                slider.move(slot)
                assert sim.position == slot
                assert slider.position() == slot
    assert moves == [2, 4, 3]


@pytest.mark.parametrize(
    ("kind", "expected_moves"),
    [
        ("no_reply", [4]),
        ("garbled", [4, 4]),  # executed, but the reply was corrupted: moved again
        ("stuck", [4]),
        ("busy", [4]),
        ("mechanical_timeout", [4]),
    ],
)
def test_single_fault_is_retried(
    sim: ElliptecSimulator,
    slider: Elliptec,
    moves: list[int],
    kind: str,
    expected_moves: list[int],
) -> None:
    sim.inject_fault(kind)
    slider.move(4)
    assert sim.position == 4
    assert moves == expected_moves
    assert sim.pending_faults() == {}
    assert commands_sent(sim).count(b"0ma0000005D") == 2


def test_garbled_query_is_retried(sim: ElliptecSimulator, slider: Elliptec) -> None:
    sim.inject_fault("garbled")
    assert slider.position() == 1
    assert commands_sent(sim) == [b"0gp", b"0gp"]


def test_persistent_stuck_names_port_command_and_last_reply(
    sim: ElliptecSimulator, slider: Elliptec
) -> None:
    sim.inject_fault("stuck", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        slider.move(2)
    assert str(caught.value) == (
        f"filter slider on {sim.port}: `0ma0000001F` — position reads back slot 1 (0 pulses) "
        "after 3 attempts (last reply '0PO00000000\\r\\n'); check that the slider is not blocked"
    )


def test_persistent_mechanical_timeout_gives_status_in_words(
    sim: ElliptecSimulator, slider: Elliptec
) -> None:
    sim.inject_fault("mechanical_timeout", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        slider.move(3)
    message = str(caught.value)
    assert sim.port in message
    assert "device status 02 (mechanical time out) after 3 attempts" in message
    assert "(last reply '0GS02\\r\\n')" in message
    assert sim.position == 1


def test_persistent_garbled_names_last_reply(sim: ElliptecSimulator, slider: Elliptec) -> None:
    sim.inject_fault("garbled", count=RETRIES + 1)
    with pytest.raises(DeviceError) as caught:
        slider.move(2)
    message = str(caught.value)
    assert f"filter slider on {sim.port}: `0ma0000001F` — no valid reply after 3 attempts" in (
        message
    )
    assert repr(last_tx(sim).decode("latin-1")) in message
    assert "\n" not in message


def test_persistent_no_reply(sim: ElliptecSimulator, slider: Elliptec) -> None:
    sim.inject_fault("no_reply", count=RETRIES + 1)
    with pytest.raises(DeviceError, match=r"last reply none within 0\.4 s"):
        slider.move(2)
    assert sim.position == 1


def test_non_transient_status_fails_at_once(moves: list[int]) -> None:
    # detents 10 pulses apart: the driver's slot 4 (93 pulses) lies beyond this travel
    with ElliptecSimulator(slot_positions=(0, 10, 20, 30), time_scale=0) as sim:
        with open_slider(sim.port) as slider:
            sim.clear_transcript()
            with pytest.raises(DeviceError) as caught:
                slider.move(4)
            assert commands_sent(sim) == [b"0ma0000005D"]
    assert "device status 0C (out of range) (reply '0GS0C\\r\\n')" in str(caught.value)


@pytest.mark.parametrize("slot", [0, 5, -2, True, "2", 1.0])
def test_slot_out_of_range_sends_nothing(
    sim: ElliptecSimulator, slider: Elliptec, moves: list[int], slot: object
) -> None:
    with pytest.raises(DeviceError, match=sim.port):
        slider.move(slot)  # type: ignore[arg-type]
    assert sim.transcript() == []
    assert moves == []


# -- discovery helper -------------------------------------------------------------------------


def test_identify_elliptec_scans_addresses() -> None:
    with ElliptecSimulator("ELL6", address="C", time_scale=0) as sim:
        with serial.Serial(sim.port, 9600, timeout=0.2) as ser:
            assert identify_elliptec(ser, addresses="0") is None
            identity = identify_elliptec(ser, addresses="0BC")
    assert identity is not None
    assert identity.startswith("Thorlabs Elliptec ELL6 serial 11200456 at address C")
