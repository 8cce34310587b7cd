"""Build a session from frames saved by other software (e.g. FlyCapture), or from a
camera's own raw files (DNG, NEF, CR2, CR3, ARW, …, read by LibRaw).

File names are matched against patterns with named fields, e.g.
``d1_{scene}_{illumination}_{exposure}_{date}-{replicate}.tif`` for
``d1_disks32cmV2_450nm_100ms_2019-02-08-174831-0004.tif``. Fields: ``scene``,
``illumination`` (a rig slot name, or its filter's centre such as ``450nm``; ``dark``
for dark frames), ``exposure`` (with a unit: ``us``, ``ms`` or ``s``) and ``replicate``
(an integer); any other ``{name}`` matches anything, ``*`` too. A pattern without
``{illumination}`` describes dark frames, which every scene of the session shares. A
camera raw file records its exposure time, so its pattern may leave out ``{exposure}``;
where the name gives one too, the two must agree.

A TIFF frame's bit depth, justification, saturation and black level are decided from its
data and the rig's pixel format (:mod:`labkit.session.sample_format`); a camera raw
file's come from the file (its black level per CFA position and white level), checked
against its data. Either way they are recorded in the frame's manifest record, so that
``labkit hdr`` knows the levels of the stored counts. A raw file's CFA layout must be the
rig's.
"""

from __future__ import annotations

import os
import re
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from labkit.errors import ConfigError, DataError
from labkit.frame import DARK, Frame, FrameKey, path_name_problem
from labkit.io.mosaic import (
    CAMERA_RAW_SUFFIXES,
    CameraRawCounts,
    read_camera_raw_counts,
    read_camera_raw_exposure,
)
from labkit.io.output_folder import check_output_folder, staged_output_folder
from labkit.rig import Rig
from labkit.session.sample_format import (
    SampleFacts,
    SampleFormat,
    decide_formats,
    stored_samples,
)
from labkit.session.store import Session

_FIELD = re.compile(r"\{(\w+)\}")
_FIELD_REGEX = {
    "replicate": r"(?P<replicate>\d+)",
    "exposure": r"(?P<exposure>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?\s*(?:us|µs|ms|s))",
}
_BARE_EXPOSURE = r"(?P<exposure>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)"  # no unit: a hint only
_UNITS = {"us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}
_OPEN_WORDS = {"unfiltered", "open", "none", "white", "nofilter", "no-filter", "rgb"}
TIFF_SUFFIXES = (".tif", ".tiff")
#: Files ``session import`` reads: TIFF frames and camera raw files.
IMPORT_SUFFIXES = TIFF_SUFFIXES + CAMERA_RAW_SUFFIXES
#: A raw file's recorded exposure and the one its name gives may differ this much (relative):
#: cameras record nominal shutter speeds (1/250 s), names round them (4ms).
EXPOSURE_AGREEMENT = 0.02


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
    return re.compile("".join(parts) + r"\Z")


def _unitless_exposure(files: Sequence[Path], patterns: Sequence[str]) -> tuple[str, str] | None:
    """(file name, exposure text) of the first file that a pattern would match if
    {exposure} took a number without unit, or None."""
    for pattern in patterns:
        try:
            regex = re.compile(
                compile_pattern(pattern).pattern.replace(_FIELD_REGEX["exposure"], _BARE_EXPOSURE)
            )
        except ConfigError:
            continue
        for path in files:
            match = regex.match(path.name)
            if match:
                return path.name, match.group("exposure")
    return None


def _literal(text: str) -> str:
    return ".*?".join(re.escape(piece) for piece in text.split("*"))


def parse_exposure(text: str) -> float:
    """``100ms`` → 0.1 (s)."""
    match = re.fullmatch(r"(\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(us|µs|ms|s)", text.strip())
    if not match:
        raise DataError(f"exposure {text!r} needs a unit: us, ms or s (e.g. 100ms)")
    return float(match.group(1)) * _UNITS[match.group(2)]


def _size(shape: tuple[int, ...]) -> str:
    return "×".join(str(n) for n in shape)


def illumination_resolver(rig: Rig, mapping: Mapping[str, str] | None = None):
    """A function mapping a file's illumination text to a rig slot name (or ``dark``)."""
    names = rig.slider.illumination_names()
    mapping = dict(mapping or {})
    for text, slot in mapping.items():
        if slot not in names and slot != DARK:
            raise ConfigError(
                f"--map {text}={slot}: {slot!r} is not a slot of the rig (slots: {names})"
            )
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
    folders: Path | Sequence[Path],
    patterns: Sequence[str],
    rig: Rig,
    mapping: Mapping[str, str] | None = None,
) -> tuple[list[ImportedFile], list[Path]]:
    """Match the TIFF and camera raw files of `folders`; returns (matched with keys,
    unmatched)."""
    folders = [folders] if isinstance(folders, Path) else list(folders)
    regexes = [compile_pattern(p) for p in patterns]
    resolve = illumination_resolver(rig, mapping)
    groups: dict[tuple, list[tuple[int, str, Path]]] = defaultdict(list)
    claimed: dict[tuple, Path] = {}  # (scene, illumination, exposure, replicate) given in names
    unmatched: list[Path] = []
    files = sorted(
        p for folder in folders for p in folder.iterdir() if p.suffix.lower() in IMPORT_SUFFIXES
    )
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
        elif why := path_name_problem(scene):
            raise DataError(
                f"{path.name}: the pattern gives scene {scene!r}, which cannot name a folder "
                f"({why}); rename the file or use a --pattern that gives a plain name"
            )
        exposure = _exposure_of(path, fields.get("exposure"))
        replicate = int(fields.get("replicate") or 0)
        if fields.get("replicate") is not None:  # a name that gives its replicate: one file each
            key = (scene, illumination, exposure, replicate)
            if key in claimed:
                what = f"{scene}/{illumination}" if scene else "dark"
                raise DataError(
                    f"{claimed[key]} and {path} are both {what} at {fields['exposure']} "
                    f"replicate {replicate}; one frame cannot be imported twice: remove one "
                    "of them (or the --from folder that repeats the other)"
                )
            claimed[key] = path
        groups[scene, illumination, exposure].append((replicate, path.name, path))
    matched = [
        ImportedFile(path, FrameKey(scene, illumination, exposure, index), source)
        for (scene, illumination, exposure), members in groups.items()
        for index, (source, _, path) in enumerate(sorted(members))
    ]
    return matched, unmatched


def _exposure_of(path: Path, text: str | None) -> float:
    """The exposure a file name gives, else the one a camera raw file records."""
    if text is not None:
        return parse_exposure(text)
    if path.suffix.lower() in CAMERA_RAW_SUFFIXES:
        recorded = read_camera_raw_exposure(path)
        if recorded is not None:
            return recorded
        why = "its metadata records none"
    else:
        why = "a TIFF frame records none"
    raise DataError(
        f"{path.name}: the pattern gives no {{exposure}} and {why}; name the files with it "
        "and put {exposure} in --pattern (e.g. _{exposure}_ for _100ms_)"
    )


def import_session(
    folder: str | Path,
    source: str | Path | Sequence[str | Path],
    patterns: Sequence[str],
    rig: Rig,
    *,
    mapping: Mapping[str, str] | None = None,
    bits: int | None = None,
    saturation: float | None = None,
    black_level: float | None = None,
    progress=None,
) -> tuple[Session, list[Path]]:
    """Create a session in `folder` from the TIFF frames or camera raw files in `source`
    (one or more folders).

    Parameters
    ----------
    folder : path
        The new session folder.
    source : path or sequence of paths
        Folders of TIFF or camera raw files (e.g. the frames and a folder of darks).
    patterns : sequence of str
        File-name patterns (see the module docstring); the first that matches wins.
    rig : Rig
        The rig the frames came from (slots, camera pixel format).
    mapping : mapping, optional
        Illumination texts of the file names → rig slot names.
    bits, saturation, black_level : optional
        Overrides of the levels decided from a TIFF's data: right-justified data of `bits`
        bits, or the saturation level (DN); the black level (DN, default 0). Camera raw
        files carry their own levels.
    progress : callable, optional
        Called with 1 after each stored frame.

    Returns
    -------
    (Session, list of Path)
        The session and the files that matched no pattern.

    Raises
    ------
    DataError
        No file matches, a file is not a 2-D mosaic, the files' levels cannot be
        decided (:func:`labkit.session.sample_format.decide_formats`), or a camera raw
        file's levels, CFA layout or exposure contradict its data, the rig or its name.
        Nothing is written:
        the session is built in a staging folder and put in place when complete, so an
        import that fails (a full disk, Ctrl-C) leaves no half-built session behind.
    """
    sources = _checked_sources(source)
    matched, unmatched = match_files(sources, patterns, rig, mapping)
    if not matched:
        _refuse_no_match(sources, patterns, unmatched)
    images, facts, raw_formats, source_facts = _read_all(matched, rig)
    formats: dict[Path, SampleFormat] = dict(raw_formats)
    if facts:
        formats |= decide_formats(
            facts,
            pixel_format=rig.camera.pixel_format,
            bits=bits,
            saturation=saturation,
            black_level=black_level,
        )
    origin = [str(s.resolve()) for s in sources]
    check_output_folder(  # an earlier import is replaced as a whole; a capture is refused
        folder, option="session folder", command="labkit session import", inputs=sources
    )
    with staged_output_folder(
        folder, command="labkit session import", option="session", inputs=sources
    ) as stage:
        session = Session.create(
            stage,
            rig,
            imported_from=origin[0] if len(origin) == 1 else origin,
            import_patterns=list(patterns),
        )
        _store_all(session, matched, images, source_facts, formats, rig, progress)
        session.set_status("imported")
    return Session.open(folder), unmatched


def _checked_sources(source: str | Path | Sequence[str | Path]) -> list[Path]:
    """The source folders; an error for none, one that is not a folder, or one given twice."""
    sources = [Path(source)] if isinstance(source, str | Path) else [Path(s) for s in source]
    if not sources:
        raise DataError("give at least one folder of frames to import")
    seen: dict[Path, Path] = {}
    for folder_in in sources:
        if not folder_in.is_dir():
            raise DataError(f"import source {folder_in} is not a folder")
        first = seen.get(folder_in.resolve())
        if first is not None:
            same = f"--from {folder_in} is given twice"
            if first != folder_in:
                same = f"--from {first} and --from {folder_in} are the same folder"
            raise DataError(f"{same}; give each folder once")
        seen[folder_in.resolve()] = folder_in
    return sources


def _refuse_no_match(sources: list[Path], patterns: Sequence[str], unmatched: list[Path]) -> None:
    """The error for sources none of whose files match the patterns, with the likely cause."""
    example = unmatched[0].name if unmatched else "(no .tif or camera raw files)"
    where = ", ".join(str(s) for s in sources)
    unitless = _unitless_exposure(unmatched, patterns)
    if unitless:
        name, value = unitless
        raise DataError(
            f"no file in {where} matches {list(patterns)}: in {name}, {{exposure}} "
            f"{value!r} has no unit; name the files with one (e.g. {value}ms), as "
            "{exposure} needs us, ms or s"
        )
    raise DataError(
        f"no file in {where} matches {list(patterns)} (e.g. {example}); check --pattern"
    )


def _read_all(
    matched: list[ImportedFile], rig: Rig
) -> tuple[
    dict[Path, np.ndarray],
    dict[Path, SampleFacts],
    dict[Path, SampleFormat],
    dict[Path, dict[str, Any]],
]:
    """Every matched file read before anything is written (a bad file must not leave a
    half-built session): the images, the TIFFs' sample facts, the camera raw files' levels
    and what each frame's record says of its file; an error for frames of different sizes."""
    images = {}
    facts: dict[Path, SampleFacts] = {}
    raw_formats: dict[Path, SampleFormat] = {}
    source_facts: dict[Path, dict[str, Any]] = {}
    for item in matched:
        if item.path.suffix.lower() in CAMERA_RAW_SUFFIXES:
            found = read_camera_raw_counts(item.path)
            _check_camera_raw(item, found, rig)
            images[item.path], raw_formats[item.path], source_facts[item.path] = _raw_levels(
                found, item.path
            )
            continue
        try:
            image = tifffile.imread(item.path)
        except Exception as error:  # tifffile raises many types on bad files
            raise DataError(f"{item.path} is not a readable TIFF ({error})") from None
        images[item.path], facts[item.path] = stored_samples(image, name=str(item.path))
        source_facts[item.path] = {"source_dtype": facts[item.path].container}
    shapes: dict[tuple[int, ...], list[Path]] = {}
    for path, image in images.items():
        shapes.setdefault(image.shape, []).append(path)
    if len(shapes) > 1:
        common = max(shapes, key=lambda shape: len(shapes[shape]))
        odd = next(paths[0] for shape, paths in shapes.items() if shape != common)
        raise DataError(
            f"{odd} is {_size(images[odd].shape)} but most frames are {_size(common)}; the "
            "frames of one session come from one sensor: move the odd files out of --from"
        )
    return images, facts, raw_formats, source_facts


def _store_all(
    session: Session,
    matched: list[ImportedFile],
    images: dict[Path, Any],
    source_facts: dict[Path, dict[str, Any]],
    formats: dict[Path, Any],
    rig: Rig,
    progress: Any,
) -> None:
    """Store every matched frame in the (staged) session."""
    for item in matched:
        chosen = formats[item.path]
        frame = Frame(
            image=images[item.path],
            frame_id=item.source_replicate,
            exposure_s=item.key.exposure_s,
            exposure_readback_s=item.key.exposure_s,
            gain_db=rig.camera.gain_db,
            pixel_format=rig.camera.pixel_format,
            device_timestamp_ns=0,
            host_timestamp_s=os.stat(item.path).st_mtime,
            extra={"saturation_dn": chosen.saturation_dn, "black_level": chosen.black_level_dn},
        )
        session.store(
            item.key,
            frame,
            source_file=item.path.name,
            **source_facts[item.path],
            **chosen.manifest_facts(),
        )
        if progress:
            progress(1)


def _check_camera_raw(item: ImportedFile, found: CameraRawCounts, rig: Rig) -> None:
    """A raw file's CFA layout must be the rig's; its recorded exposure, where the name
    gives one too, the name's."""
    if found.cfa != rig.cfa:
        raise DataError(
            f"{item.path}: its CFA layout is {found.cfa} but the rig's camera "
            f"({rig.camera.pixel_format}) is {rig.cfa}; give the rig of the camera that took "
            "it (--rig), with camera.pixel_format of its layout"
        )
    recorded, named = found.exposure_s, item.key.exposure_s
    if recorded is not None and abs(recorded / named - 1) > EXPOSURE_AGREEMENT:
        raise DataError(
            f"{item.path}: its name gives {named:g} s but the file records {recorded:g} s; "
            "rename the file, or leave {exposure} out of --pattern to use the recorded time"
        )


def _raw_levels(
    found: CameraRawCounts, path: Path
) -> tuple[np.ndarray, SampleFormat, dict[str, Any]]:
    """Counts with one black level for every CFA position, their format, and the facts
    the manifest records about the file.

    The merge subtracts one black level (or the dark frames); where the file records
    different ones per CFA position, each position's counts are lowered by its excess over
    the smallest (whole DN, lossless), and saturation is the lowest position's. The levels
    are checked against the data: no count above the white level, and the black level
    not above a large part of the data (a dark frame's counts scatter about it).
    """
    counts, black, white = found.counts, found.black_levels, found.white_level
    if int(counts.max()) > white:
        raise DataError(
            f"{path}: counts reach {int(counts.max())} DN, above the file's white level "
            f"{white:g}; its levels are wrong: convert it again with the camera maker's "
            "software, or import TIFFs with --saturation"
        )
    span = white - black.max()
    below = 0
    for row in (0, 1):
        for col in (0, 1):
            plane = counts[row::2, col::2]
            below += int(np.count_nonzero(plane < black[row, col] - 0.05 * span))
    if below > 0.01 * counts.size:
        raise DataError(
            f"{path}: {below} of its {counts.size} counts lie well below its black levels "
            f"{black.tolist()} DN; the file's levels disagree with its data"
        )
    floor = float(black.min())
    excess = np.rint(black - floor).astype(np.int64)
    if excess.any():
        counts = counts.astype(np.int64)
        for row in (0, 1):
            for col in (0, 1):
                counts[row::2, col::2] -= excess[row, col]
        counts = np.clip(counts, 0, None).astype(np.uint16)
    saturation = float(white - excess.max())
    bits = max(1, int(np.ceil(np.log2(white + 1))))
    chosen = SampleFormat(
        bits=bits,
        justification="native",
        saturation_dn=saturation,
        black_level_dn=floor,
        reason="camera raw file: black and white levels recorded in the file (LibRaw)",
    )
    record = {
        "source_format": "camera raw",
        "source_black_levels": black.tolist(),
        "source_white_level": white,
        "source_exposure_s": found.exposure_s,
        **{key: value for key, value in found.source.items() if key.startswith("camera_")},
    }
    return counts, chosen, record
