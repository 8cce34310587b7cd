"""How raw frames from other software store their samples, and the levels that follow.

A FlyCapture TIFF of a camera set to ``BayerGB12`` may hold the 12 bits right-justified
in a 16-bit container (saturation 4095), left-justified (65520), or an 8-bit copy (255);
a float TIFF may hold counts or values normalised to [0, 1]. Merging exposures needs the
saturation level in the stored counts, so import decides it per file from the data, the
rig's pixel format and the user's overrides, and refuses what it cannot decide:

- ``uint8``: 8 bits, saturation 255, whatever the pixel format (a reduced copy).
- ``uint16`` under an N-bit pixel format (N < 16): right-justified if every file of the
  import stays within 2^N − 1, left-justified if every file's values are multiples of
  2^(16 − N); both possible (dark frames only) or neither is an error that names the fix.
  Right-justified data whose maximum piles up at 2^k − 1 for a k < N look like k-bit data
  in a 16-bit container and are refused too (``--bits`` says which).
- ``uint16`` under a 16-bit format: 16 bits, saturation 65535.
- float: whole numbers within 0…65535 are counts (then as ``uint16``); values within
  [0, 1] are normalised and stored as ``round(65535·v)``; anything else is refused.

Overrides: ``bits`` (right-justified data of that many bits), ``saturation`` (the level
itself, DN) and ``black_level`` (DN, default 0). Every file is checked against them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labkit.cfa import pixel_format_bits
from labkit.errors import DataError

#: Fewest pixels at the maximum that make a pile-up (clipping) rather than a stray value.
PILE_UP_PIXELS = 10


@dataclass(frozen=True)
class SampleFacts:
    """What the data of one file say about its encoding.

    Attributes
    ----------
    container : str
        NumPy dtype name of the file's samples (``uint8``, ``uint16``, ``float32`` …).
    kind : str
        ``"uint8"``, ``"uint16"`` (16-bit counts, whole-number floats included) or
        ``"normalised"`` (floats within [0, 1]).
    maximum : int
        Largest stored value (counts; for normalised floats, after scaling to 65535).
    at_maximum : int
        Pixels at `maximum`.
    step_bits : int
        Trailing zero bits shared by every value (16 when all are zero).
    """

    container: str
    kind: str
    maximum: int
    at_maximum: int
    step_bits: int


@dataclass(frozen=True)
class SampleFormat:
    """The encoding decided for a file, and its levels in the stored counts.

    Attributes
    ----------
    bits : int
        Significant bits of the data.
    justification : str
        ``"native"`` (the data fill the container), ``"right"``, ``"left"``,
        ``"normalised"`` (floats in [0, 1]) or ``"given"`` (``--saturation``).
    saturation_dn, black_level_dn : float
        Levels in the stored counts, DN.
    reason : str
        How it was decided, for the manifest and error messages.
    """

    bits: int
    justification: str
    saturation_dn: float
    black_level_dn: float
    reason: str

    def manifest_facts(self) -> dict[str, object]:
        """Fields for a frame's manifest record."""
        return {
            "sample_bits": self.bits,
            "justification": self.justification,
            "levels_from": self.reason,
        }


def sample_facts(image: np.ndarray, *, name: str) -> SampleFacts:
    """The encoding facts of a 2-D mosaic (the second half of :func:`stored_samples`)."""
    return stored_samples(image, name=name)[1]


def stored_samples(image: np.ndarray, *, name: str) -> tuple[np.ndarray, SampleFacts]:
    """The samples as the session stores them, and their encoding facts.

    uint8/uint16 samples are kept as they are, floats become uint16 (see the module
    docstring); raises DataError for what cannot be a raw frame.

    Parameters
    ----------
    image : ndarray (rows, cols)
        The file's samples as read.
    name : str
        The file, for error messages.
    """
    if image.ndim != 2:
        raise DataError(
            f"{name}: expected a 2-D raw mosaic, got shape {image.shape}"
            + (" (a colour or demosaiced image?)" if image.ndim == 3 else "")
        )
    if image.dtype in (np.uint8, np.uint16):
        values = image
        kind = "uint8" if image.dtype == np.uint8 else "uint16"
    elif np.issubdtype(image.dtype, np.floating):
        values, kind = _float_counts(image, name)
    else:
        raise DataError(
            f"{name}: samples of type {image.dtype} are not supported; save the mosaic as "
            "8- or 16-bit unsigned integers (or float)"
        )
    maximum = int(values.max(initial=0))
    combined = int(np.bitwise_or.reduce(values.ravel().astype(np.uint16)))
    step_bits = 16 if combined == 0 else (combined & -combined).bit_length() - 1
    facts = SampleFacts(
        str(image.dtype), kind, maximum, int(np.count_nonzero(values == maximum)), step_bits
    )
    return values, facts


def _float_counts(image: np.ndarray, name: str) -> tuple[np.ndarray, str]:
    if not np.isfinite(image).all():
        raise DataError(f"{name}: the float mosaic holds NaN or Inf values")
    low, high = float(image.min(initial=0.0)), float(image.max(initial=0.0))
    if low < 0:
        raise DataError(f"{name}: the float mosaic holds negative values (down to {low:g})")
    whole = np.array_equal(image, np.round(image))
    if high <= 1.0 and not whole:
        return np.round(image.astype(np.float64) * 65535).astype(np.uint16), "normalised"
    if high <= 65535 and whole:
        return image.astype(np.uint16), "uint16"
    raise DataError(
        f"{name}: float values up to {high:g} are neither counts (whole numbers up to 65535) "
        "nor normalised to [0, 1]; convert the file to 16-bit counts"
    )


def decide_formats(
    facts: Mapping[Path, SampleFacts],
    *,
    pixel_format: str,
    bits: int | None = None,
    saturation: float | None = None,
    black_level: float | None = None,
) -> dict[Path, SampleFormat]:
    """Decide every file's encoding and levels (see the module docstring).

    Parameters
    ----------
    facts : mapping of path to SampleFacts
        All files of one import (justification is decided for them together).
    pixel_format : str
        The rig camera's GenICam pixel format (e.g. ``BayerGB12``).
    bits : int, optional
        Right-justified data of this many bits (saturation 2^bits − 1).
    saturation : float, optional
        The saturation level, DN in the stored counts.
    black_level : float, optional
        The black level, DN (default 0).

    Raises
    ------
    DataError
        A file contradicts the pixel format or an override, or the data leave the
        justification open.
    """
    if bits is not None and saturation is not None:
        raise DataError("give --bits or --saturation, not both")
    black = 0.0 if black_level is None else float(black_level)
    if not np.isfinite(black) or black < 0:
        raise DataError(f"--black-level {black_level} must be a non-negative number of DN")
    if bits is not None:
        formats = _given_bits(facts, int(bits), black)
    elif saturation is not None:
        formats = _given_saturation(facts, float(saturation), black)
    else:
        format_bits = pixel_format_bits(pixel_format)
        formats = {}
        uint16 = {path: f for path, f in facts.items() if f.kind == "uint16"}
        if uint16:
            formats.update(_justify(uint16, format_bits, pixel_format, black))
        for path, f in facts.items():
            if f.kind == "uint8":
                formats[path] = SampleFormat(8, "native", 255.0, black, "8-bit file")
            elif f.kind == "normalised":
                formats[path] = SampleFormat(
                    16, "normalised", 65535.0, black, "float file normalised to [0, 1]"
                )
    for path, chosen in formats.items():
        if chosen.black_level_dn >= chosen.saturation_dn:
            raise DataError(
                f"{path}: black level {chosen.black_level_dn:g} DN is not below the "
                f"saturation level {chosen.saturation_dn:g} DN; check --black-level"
            )
    return formats


def _given_bits(facts: Mapping[Path, SampleFacts], bits: int, black: float) -> dict:
    if not 1 <= bits <= 16:
        raise DataError(f"--bits {bits}: give 1 … 16")
    saturation = float(2**bits - 1)
    formats = {}
    for path, f in facts.items():
        container = 8 if f.kind == "uint8" else 16
        if bits > container:
            raise DataError(f"{path}: an 8-bit file cannot hold {bits}-bit data; check --bits")
        if f.maximum > saturation:
            raise DataError(
                f"{path}: values up to {f.maximum} exceed {bits}-bit data ({saturation:g}); "
                "check --bits, or give --saturation DN for left-justified data"
            )
        justification = "native" if bits == container else "right"
        formats[path] = SampleFormat(bits, justification, saturation, black, f"--bits {bits}")
    return formats


def _given_saturation(facts: Mapping[Path, SampleFacts], saturation: float, black: float):
    if not np.isfinite(saturation) or saturation <= 0:
        raise DataError(f"--saturation {saturation:g} must be a positive number of DN")
    formats = {}
    for path, f in facts.items():
        if f.maximum > saturation:
            raise DataError(
                f"{path}: values up to {f.maximum} exceed --saturation {saturation:g}; "
                "check the level"
            )
        bits = int(np.ceil(np.log2(saturation + 1)))
        formats[path] = SampleFormat(
            bits, "given", saturation, black, f"--saturation {saturation:g}"
        )
    return formats


def _justify(
    facts: Mapping[Path, SampleFacts], format_bits: int, pixel_format: str, black: float
) -> dict[Path, SampleFormat]:
    if format_bits >= 16:
        return {path: SampleFormat(16, "native", 65535.0, black, "16-bit file") for path in facts}
    top = 2**format_bits - 1
    shift = 16 - format_bits
    right = [path for path, f in facts.items() if f.maximum <= top]
    left = [path for path, f in facts.items() if f.step_bits >= shift]
    if len(right) == len(facts) and len(left) == len(facts):
        raise DataError(
            f"cannot tell how {len(facts)} 16-bit file(s) (e.g. {next(iter(facts))}) hold the "
            f"{format_bits}-bit data of {pixel_format}: every value is a multiple of "
            f"{2**shift} and at most {top}; pass --bits {format_bits} if they are "
            f"right-justified, or --saturation {top << shift} if left-justified"
        )
    if len(right) == len(facts):
        _refuse_pile_up(facts, format_bits, pixel_format)
        reason = f"16-bit file, {format_bits}-bit data of {pixel_format} right-justified"
        return {p: SampleFormat(format_bits, "right", float(top), black, reason) for p in facts}
    if len(left) == len(facts):
        reason = f"16-bit file, {format_bits}-bit data of {pixel_format} left-justified"
        saturation = float(top << shift)
        return {p: SampleFormat(format_bits, "left", saturation, black, reason) for p in facts}
    path, f = next((p, f) for p, f in facts.items() if p not in right and p not in left)
    raise DataError(
        f"{path}: values up to {f.maximum} that are not all multiples of {2**shift} are not "
        f"{format_bits}-bit data ({pixel_format}) right- or left-justified in 16 bits; pass "
        "--bits 16 if the files hold 16-bit data, or correct the rig's pixel_format"
    )


def _refuse_pile_up(facts: Mapping[Path, SampleFacts], format_bits: int, pixel_format: str):
    maximum = max(f.maximum for f in facts.values())
    bits = (maximum + 1).bit_length() - 1
    if maximum != 2**bits - 1 or not 8 <= bits < format_bits:
        return
    path, f = max(facts.items(), key=lambda item: item[1].at_maximum)
    if f.at_maximum >= PILE_UP_PIXELS:
        raise DataError(
            f"{path}: {f.at_maximum} pixels pile up at {maximum} (2^{bits} − 1) and no file "
            f"goes higher, below the {format_bits}-bit range of {pixel_format}: the files look "
            f"like {bits}-bit data in 16-bit containers; pass --bits {bits}, or --bits "
            f"{format_bits} if the sensor clips there"
        )
