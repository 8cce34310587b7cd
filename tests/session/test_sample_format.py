"""Deciding bit depth, justification and levels of frames from other software."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labkit.errors import DataError
from labkit.session.sample_format import decide_formats, sample_facts, stored_samples

RIG12 = "BayerGB12"


def _decide(images: dict[str, np.ndarray], pixel_format: str = RIG12, **overrides):
    facts = {Path(name): sample_facts(image, name=name) for name, image in images.items()}
    return {
        p.name: f for p, f in decide_formats(facts, pixel_format=pixel_format, **overrides).items()
    }


def _ramp(top: int, dtype=np.uint16) -> np.ndarray:
    return np.linspace(0, top, 64 * 64).round().astype(dtype).reshape(64, 64)


def test_eight_bit_files_saturate_at_255_whatever_the_pixel_format() -> None:
    chosen = _decide({"a.tif": _ramp(255, np.uint8)})["a.tif"]
    assert (chosen.bits, chosen.justification, chosen.saturation_dn) == (8, "native", 255.0)
    assert chosen.black_level_dn == 0.0


def test_right_and_left_justified_twelve_bits_are_told_apart() -> None:
    right = _decide({"r.tif": _ramp(4095), "dark.tif": _ramp(30)})
    assert {f.saturation_dn for f in right.values()} == {4095.0}
    assert {f.justification for f in right.values()} == {"right"}
    left = _decide({"l.tif": _ramp(4095) << 4, "dark.tif": _ramp(30) << 4})
    assert {f.saturation_dn for f in left.values()} == {65520.0}
    assert {f.justification for f in left.values()} == {"left"}


def test_the_lit_frames_settle_what_a_dark_frame_leaves_open() -> None:
    dark = (_ramp(30) << 4).astype(np.uint16)  # multiples of 16 and below 4096: either
    with pytest.raises(DataError, match=r"--bits 12 .* --saturation 65520"):
        _decide({"dark.tif": dark})
    assert _decide({"dark.tif": dark, "lit.tif": _ramp(4095) << 4})["dark.tif"].justification == (
        "left"
    )


def test_sixteen_bit_data_contradict_a_twelve_bit_format_until_bits_are_given() -> None:
    sixteen = (_ramp(255) * 257).astype(np.uint16)
    with pytest.raises(DataError, match=r"s16\.tif.*not .*12-bit data \(BayerGB12\).*--bits 16"):
        _decide({"s16.tif": sixteen})
    chosen = _decide({"s16.tif": sixteen}, bits=16)["s16.tif"]
    assert (chosen.saturation_dn, chosen.justification) == (65535.0, "native")
    assert _decide({"s16.tif": sixteen}, pixel_format="BayerGB16")["s16.tif"].saturation_dn == 65535


def test_eight_bit_data_in_a_sixteen_bit_container_are_refused_by_their_pile_up() -> None:
    image = np.minimum(_ramp(400), 255).astype(np.uint16)  # clipped at 255 in many pixels
    with pytest.raises(DataError, match=r"pile up at 255 \(2\^8 − 1\).*--bits 8"):
        _decide({"p.tif": image})
    assert _decide({"p.tif": image}, bits=8)["p.tif"].saturation_dn == 255.0
    stray = _ramp(200).astype(np.uint16)
    stray[0, 0] = 255  # one pixel at 255 is not a pile-up
    assert _decide({"s.tif": stray})["s.tif"].saturation_dn == 4095.0


def test_overrides_are_checked_against_every_file() -> None:
    with pytest.raises(DataError, match=r"a\.tif: values up to 4095 exceed 10-bit data"):
        _decide({"a.tif": _ramp(4095)}, bits=10)
    with pytest.raises(DataError, match=r"8-bit file cannot hold 12-bit"):
        _decide({"a.tif": _ramp(255, np.uint8)}, bits=12)
    with pytest.raises(DataError, match=r"exceed --saturation 4000"):
        _decide({"a.tif": _ramp(4095)}, saturation=4000)
    chosen = _decide({"a.tif": _ramp(4095)}, saturation=4095, black_level=64)["a.tif"]
    assert (chosen.saturation_dn, chosen.black_level_dn, chosen.justification) == (
        4095.0,
        64.0,
        "given",
    )
    with pytest.raises(DataError, match=r"black level 300 DN is not below .* 255 DN"):
        _decide({"a.tif": _ramp(255, np.uint8)}, black_level=300)
    with pytest.raises(DataError, match="not both"):
        _decide({"a.tif": _ramp(255, np.uint8)}, bits=8, saturation=255)


def test_float_files_hold_counts_or_normalised_values() -> None:
    counts = _ramp(4095).astype(np.float32)
    facts = sample_facts(counts, name="c.tif")
    assert facts.kind == "uint16" and stored_samples(counts, name="c.tif")[0].dtype == np.uint16
    assert _decide({"c.tif": counts})["c.tif"].saturation_dn == 4095.0
    normalised = (_ramp(1000).astype(np.float32) / 1000.0) * np.float32(0.7)
    chosen = _decide({"n.tif": normalised})["n.tif"]
    assert (chosen.justification, chosen.saturation_dn) == ("normalised", 65535.0)
    stored, _ = stored_samples(normalised, name="n.tif")
    np.testing.assert_allclose(stored / 65535.0, normalised, atol=0.5 / 65535)
    for bad, match in [
        (normalised * 3, "neither counts"),
        (-normalised, "negative"),
        (np.full((4, 4), np.nan, np.float32), "NaN"),
    ]:
        with pytest.raises(DataError, match=match):
            sample_facts(bad, name="bad.tif")


def test_what_cannot_be_a_raw_mosaic_is_named() -> None:
    with pytest.raises(DataError, match=r"rgb\.tif.*2-D raw mosaic.*demosaiced"):
        sample_facts(np.zeros((4, 4, 3), np.uint8), name="rgb.tif")
    with pytest.raises(DataError, match=r"i32\.tif.*int32"):
        sample_facts(np.zeros((4, 4), np.int32), name="i32.tif")
