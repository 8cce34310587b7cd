"""Build a session from frames saved by other software (e.g. FlyCapture).

File names are matched against patterns with named fields, e.g.
``d1_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif`` for
``d1_disks32cmV2_450nm_100ms_2019-02-08-174831-0004.tif``. Fields: ``scene``,
``illumination`` (a rig slot name, or its filter's centre such as ``450nm``; ``dark``
for dark frames), ``exposure`` (with a unit: ``us``, ``ms`` or ``s``) and ``replicate``
(an integer); any other ``{name}`` matches anything, ``*`` too. A pattern without
``{illumination}`` describes dark frames.
"""

from __future__ import annotations

import os
import re
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tifffile

from labkit.errors import ConfigError, DataError
from labkit.frame import DARK, Frame, FrameKey
from labkit.rig import Rig
from labkit.session.store import Session

_FIELD = re.compile(r"\{(\w+)\}")
_FIELD_REGEX = {
    "replicate": r"(?P<replicate>\d+)",
    "exposure": r"(?P<exposure>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?\s*(?:us|µs|ms|s))",
}
_UNITS = {"us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}
_OPEN_WORDS = {"unfiltered", "open", "none", "white", "nofilter", "no-filter", "rgb"}


@dataclass(frozen=True)
class ImportedFile:
    """A source file and the key it is stored under."""

    path: Path
    key: FrameKey
    source_replicate: int


def compile_pattern(pattern: str) -> re.Pattern[str]:
    """A file-name pattern with ``{field}`` placeholders as an anchored regex."""
    parts: list[str] = []
    seen: set[str] = set()
    position = 0
    for match in _FIELD.finditer(pattern):
        parts.append(_literal(pattern[position : match.start()]))
        name = match.group(1)
        if name in seen:
            raise ConfigError(f"pattern {pattern!r} names {{{name}}} twice")
        seen.add(name)
        parts.append(_FIELD_REGEX.get(name, rf"(?P<{name}>.+?)"))
        position = match.end()
    parts.append(_literal(pattern[position:]))
    if "exposure" not in seen:
        raise ConfigError(f"pattern {pattern!r} needs an {{exposure}} field, e.g. _{{exposure}}_")
    return re.compile("".join(parts) + r"\Z")


def _literal(text: str) -> str:
    return ".*?".join(re.escape(piece) for piece in text.split("*"))


def parse_exposure(text: str) -> float:
    """``100ms`` → 0.1 (s)."""
    match = re.fullmatch(r"(\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(us|µs|ms|s)", text.strip())
    if not match:
        raise DataError(f"exposure {text!r} needs a unit: us, ms or s (e.g. 100ms)")
    return float(match.group(1)) * _UNITS[match.group(2)]


def illumination_resolver(rig: Rig, mapping: Mapping[str, str] | None = None):
    """A function mapping a file's illumination text to a rig slot name (or ``dark``)."""
    names = rig.slider.illumination_names()
    mapping = dict(mapping or {})
    by_centre = {
        round(p.filter.centre_nm): p.name for p in rig.slider.positions.values() if p.filter
    }
    open_slots = [p.name for p in rig.slider.positions.values() if p.filter is None]

    def resolve(text: str) -> str:
        if text in mapping:
            return mapping[text]
        if text in names or text == DARK:
            return text
        bare = text.lower().removesuffix("nm")
        if bare in names:
            return bare
        if bare.replace(".", "", 1).isdigit() and round(float(bare)) in by_centre:
            return by_centre[round(float(bare))]
        if text.lower() in _OPEN_WORDS and open_slots:
            return open_slots[0]
        raise DataError(
            f"illumination {text!r} is not a slot of the rig (slots: {names}); "
            f"add --map {text}=NAME"
        )

    return resolve


def match_files(
    folder: Path, patterns: Sequence[str], rig: Rig, mapping: Mapping[str, str] | None = None
) -> tuple[list[ImportedFile], list[Path]]:
    """Match the TIFF files of `folder`; returns (matched with keys, unmatched)."""
    regexes = [compile_pattern(p) for p in patterns]
    resolve = illumination_resolver(rig, mapping)
    groups: dict[tuple, list[tuple[int, str, Path]]] = defaultdict(list)
    unmatched: list[Path] = []
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".tif", ".tiff"))
    for path in files:
        for regex in regexes:
            match = regex.match(path.name)
            if match:
                break
        else:
            unmatched.append(path)
            continue
        fields = match.groupdict()
        illumination = resolve(fields["illumination"]) if "illumination" in fields else DARK
        scene = fields.get("scene")
        if illumination == DARK or scene == DARK:
            scene, illumination = None, DARK
        elif not scene:
            raise DataError(f"{path.name}: the pattern gives no {{scene}} for a lit frame")
        exposure = parse_exposure(fields["exposure"])
        replicate = int(fields.get("replicate") or 0)
        groups[scene, illumination, exposure].append((replicate, path.name, path))
    matched = [
        ImportedFile(path, FrameKey(scene, illumination, exposure, index), source)
        for (scene, illumination, exposure), members in groups.items()
        for index, (source, _, path) in enumerate(sorted(members))
    ]
    return matched, unmatched


def import_session(
    folder: str | Path,
    source: str | Path,
    patterns: Sequence[str],
    rig: Rig,
    *,
    mapping: Mapping[str, str] | None = None,
    progress=None,
) -> tuple[Session, list[Path]]:
    """Create a session in `folder` from the TIFF frames in `source`.

    Returns the session and the files that matched no pattern. Nothing is written when
    no file matches or a file is not a 2-D uint8/uint16 image.
    """
    source = Path(source)
    if not source.is_dir():
        raise DataError(f"import source {source} is not a folder")
    matched, unmatched = match_files(source, patterns, rig, mapping)
    if not matched:
        example = unmatched[0].name if unmatched else "(no .tif files)"
        raise DataError(
            f"no file in {source} matches {list(patterns)} (e.g. {example}); check --pattern"
        )
    images = []
    for item in matched:  # read all first: a bad file must not leave a half-built session
        try:
            image = tifffile.imread(item.path)
        except Exception as error:  # tifffile raises many types on bad files
            raise DataError(f"{item.path} is not a readable TIFF ({error})") from None
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            raise DataError(
                f"{item.path}: expected a 2-D uint8/uint16 raw mosaic, got {image.dtype} "
                f"{image.shape}"
            )
        images.append(image)
    session = Session.create(
        folder, rig, imported_from=str(source.resolve()), import_patterns=list(patterns)
    )
    for item, image in zip(matched, images, strict=True):
        frame = Frame(
            image=image,
            frame_id=item.source_replicate,
            exposure_s=item.key.exposure_s,
            exposure_readback_s=item.key.exposure_s,
            gain_db=rig.camera.gain_db,
            pixel_format=rig.camera.pixel_format,
            device_timestamp_ns=0,
            host_timestamp_s=os.stat(item.path).st_mtime,
        )
        session.store(item.key, frame, source_file=item.path.name)
        if progress:
            progress(1)
    session.set_status("imported")
    return session, unmatched
