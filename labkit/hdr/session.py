"""``labkit hdr``: every (scene, illumination) of a capture session → an HDR raw EXR.

Reads the session manifest, groups frames by scene × illumination × exposure, checks
that they can be merged (same size and CFA, darks for every exposure), and merges each
group with :func:`labkit.hdr.merge.merge_exposures`. Dark frames are shared between
scenes, so each exposure's mean dark is computed once and kept only while a later
image still needs it.

Outputs (``OUT/``): ``<scene>/<illumination>.exr`` (float32 ``raw`` [+ ``variance``]),
``<scene>/<illumination>.png`` (preview) and ``hdr.yaml`` (index: scaling factors against
the exposure-time ratios, noise model, warnings), written as one set with a run manifest
(:mod:`labkit.io.output_folder`). Every frame is checked against the sha256 and size its
manifest record holds as it is read.
"""

from __future__ import annotations

import datetime as dt
import json
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
import yaml

import labkit
from labkit.blas_threads import fixed_blas_threads
from labkit.cfa import layout_from_pixel_format, pixel_format_bits
from labkit.errors import DataError, DataWarning
from labkit.frame import DARK, exposure_label
from labkit.hdr.levels import DarkFrame, SensorLevels
from labkit.hdr.merge import HDRResult, merge_exposures
from labkit.hdr.stack import ExposureInput, FrameSource
from labkit.io.atomic import write_text_atomic
from labkit.io.digest import read_verified
from labkit.io.exr import RawImage, write_raw_exr
from labkit.io.output_folder import staged_output_folder
from labkit.io.preview import raw_preview, write_png
from labkit.io.tiff import json_default, read_raw_tiff
from labkit.session import MANIFEST_FILE, Session

INDEX_FILE = "hdr.yaml"


@dataclass
class HDRJob:
    """The frames of one (scene, illumination) to merge."""

    scene: str
    illumination: str
    wavelength_nm: float | None
    exposures: list[ExposureInput]

    @property
    def frame_count(self) -> int:
        """Frames to read (without darks)."""
        return sum(len(e.frames) for e in self.exposures)

    @property
    def name(self) -> str:
        """``scene/illumination``."""
        return f"{self.scene}/{self.illumination}"


@dataclass
class HDRPlan:
    """What :func:`plan_hdr` found in a session."""

    session: Path
    jobs: list[HDRJob]
    darks: dict[float, ExposureInput]
    cfa: str
    shape: tuple[int, int]
    levels: SensorLevels
    no_dark: bool
    warnings: list[str] = field(default_factory=list)
    """Problems that do not stop the merge (a torn last manifest record)."""

    @property
    def frame_count(self) -> int:
        """Frames the merge will read, darks included."""
        needed = {e.exposure_s for job in self.jobs for e in job.exposures}
        darks = sum(len(self.darks[t].frames) for t in needed if t in self.darks)
        return sum(job.frame_count for job in self.jobs) + (0 if self.no_dark else darks)


@dataclass
class HDROutput:
    """One merged image and where it went."""

    job: HDRJob
    result: HDRResult
    exr: Path
    preview: Path | None
    session: Path | None = None


@dataclass
class HDRRun:
    """Everything :func:`run_hdr` wrote."""

    out: Path
    method: str
    outputs: list[HDROutput] = field(default_factory=list)

    @property
    def index(self) -> Path:
        """The ``hdr.yaml`` index."""
        return self.out / INDEX_FILE


def plan_hdr(
    session_dir: str | Path,
    *,
    scenes: Sequence[str] | None = None,
    illuminations: Sequence[str] | None = None,
    no_dark: bool = False,
    allow_empty: bool = False,
) -> HDRPlan:
    """Group a session's frames into merge jobs and check them.

    With `allow_empty`, a session with no lit frame matching `scenes` / `illuminations`
    gives a plan without jobs instead of an error (one of several sessions merged together).

    Raises
    ------
    DataError
        No frames; frames of different sizes or CFA layouts; missing dark frames
        (unless `no_dark`).
    """
    session = Session.open(session_dir)
    folder = session.folder
    records = list(session.records.values())
    retake = _retake_advice(session)
    if not records:
        raise DataError(_no_frames(session, retake))
    first = records[0]
    shape = tuple(first["shape"])
    cfa = layout_from_pixel_format(first["pixel_format"])
    for record in records:
        if tuple(record["shape"]) != shape:
            for named in (first, record):  # a record that disagrees with its file is the cause
                _check_record_shape(folder, named, retake)
            raise DataError(
                f"session {folder}: frame {record['key']} ({record['file']}) is "
                f"{record['shape'][0]}×{record['shape'][1]} but frame {first['key']} is "
                f"{shape[0]}×{shape[1]}; frames of different sizes cannot be merged"
            )
        layout = layout_from_pixel_format(record["pixel_format"])
        if layout != cfa:
            raise DataError(
                f"session {folder}: frame {record['key']} has CFA {layout} "
                f"({record['pixel_format']}) but frame {first['key']} has {cfa}; "
                "one HDR image needs one CFA layout"
            )

    lit: dict[tuple[str, str], dict[float, list[dict]]] = defaultdict(lambda: defaultdict(list))
    dark_records: dict[float, list[dict]] = defaultdict(list)
    for record in records:
        if record["dark"]:
            dark_records[float(record["exposure_s"])].append(record)
        else:
            lit[(record["scene"], record["illumination"])][float(record["exposure_s"])].append(
                record
            )
    levels = _levels(records, folder, imported=session.status == "imported", retake=retake)
    _check_capacity(_stored_dtype(folder, first), levels, f"frame {first['key']}")
    rig = session.rig
    jobs = []
    for (scene, illumination), by_exposure in sorted(lit.items()):
        if scenes and scene not in scenes:
            continue
        if illuminations and illumination not in illuminations:
            continue
        exposures = [
            ExposureInput(t, [_source(folder, r, levels, retake) for r in _by_replicate(rs)])
            for t, rs in sorted(by_exposure.items())
        ]
        band = rig.filter_for(illumination) if illumination != DARK else None
        jobs.append(HDRJob(scene, illumination, band.centre_nm if band else None, exposures))
    if not jobs and not allow_empty:
        wanted = ", ".join([*(scenes or []), *(illuminations or [])])
        raise DataError(
            f"session {folder} has no lit frames" + (f" for {wanted}" if wanted else "")
        )
    darks = {
        t: ExposureInput(t, [_source(folder, r, levels, retake) for r in _by_replicate(rs)])
        for t, rs in dark_records.items()
    }
    if not no_dark:
        missing = sorted(
            {e.exposure_s for job in jobs for e in job.exposures if e.exposure_s not in darks}
        )
        if missing:
            labels = ", ".join(exposure_label(t) for t in missing)
            raise DataError(
                f"session {folder} has no dark frames at {labels}; resume the capture to take "
                "them (`labkit capture` with the same rig and --session), or pass --no-dark "
                "to subtract only the black level (dark current then stays in the image)"
            )
    notes = []
    if session.torn_records:
        notes.append(
            f"{folder / MANIFEST_FILE} ends with a torn record (a capture interrupted while "
            f"writing it): that frame is missing from the merge; {retake} to re-take it"
        )
    return HDRPlan(folder, jobs, darks, cfa, shape, levels, no_dark, notes)


def _retake_advice(session: Session) -> str:
    """How to get missing or damaged frames of `session` back."""
    if session.status == "imported":
        return "import the frames again (`labkit session import`)"
    return f"resume the capture (`labkit capture RIG --session {session.folder}`)"


def _no_frames(session: Session, retake: str) -> str:
    """Why a session without records has no frames to merge, and what to do."""
    folder = session.folder
    manifest = folder / MANIFEST_FILE
    on_disk = (
        sum(1 for p in (folder / "frames").rglob("*.tif*") if p.is_file())
        if (folder / "frames").is_dir()
        else 0
    )
    if session.torn_records:
        state = "holds only a torn record"
    elif not manifest.exists():
        state = "is missing"
    elif on_disk:
        state = "lists no frames"
    else:
        return f"session {folder} holds no frames; {retake} to take them"
    files = f" but {folder / 'frames'} holds {on_disk} frame file(s)" if on_disk else ""
    restore = f"restore {MANIFEST_FILE} from a backup, or " if on_disk else ""
    return f"{manifest} {state}{files}; {restore}{retake} to re-take the frames"


def _check_record_shape(folder: Path, record: dict, retake: str) -> None:
    """Raise DataError when a record's shape disagrees with the frame file it names."""
    try:
        with tifffile.TiffFile(folder / record["file"]) as tif:
            stored = tuple(tif.pages[0].shape)
    except Exception:  # unreadable: reported with the fix when the merge reads it
        return
    if stored != tuple(record["shape"]):
        raise DataError(
            f"session {folder}: frame {record['key']}: {MANIFEST_FILE} says it is "
            f"{record['shape'][0]}×{record['shape'][1]} but its file {record['file']} is "
            f"{'×'.join(map(str, stored))}; {MANIFEST_FILE} is damaged or was edited: restore "
            f"it from a backup, or delete that frame's line and {retake} to re-take it"
        )


@fixed_blas_threads
def run_hdr(
    session_dir: str | Path | Sequence[str | Path],
    out_dir: str | Path,
    *,
    method: str = "thesis",
    no_dark: bool = False,
    scenes: Sequence[str] | None = None,
    illuminations: Sequence[str] | None = None,
    previews: bool = True,
    on_frame: Callable[[], None] | None = None,
    on_image: Callable[[HDROutput], None] | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> HDRRun:
    """Merge every (scene, illumination) of one or more sessions into ``out_dir``.

    Parameters
    ----------
    session_dir : path or sequence of paths
        Capture sessions (``labkit capture --session``), e.g. a calibration session and a
        session of scenes; each image's darks come from its own session, and a
        (scene, illumination) may come from only one of them.
    out_dir : path
        Output folder: absent, empty, or written by an earlier labkit run, which this run
        replaces as a whole (:func:`labkit.io.output_folder.staged_output_folder`): a run
        that fails or is interrupted leaves the previous folder as it was.
    method : {"thesis", "noise"}
        Blending weights, see :mod:`labkit.hdr.merge`.
    no_dark : bool
        Allow exposures without dark frames: subtract the black level instead.
    scenes, illuminations : sequence of str or None
        Merge only these (default: all).
    previews : bool
        Also write a PNG preview per image.
    on_frame, on_image : callable or None
        Progress callbacks: after each frame read, after each image written.
    on_warning : callable or None
        Receives each problem that does not stop the merge (a session's torn last
        manifest record); by default it is issued as a :class:`~labkit.errors.DataWarning`.
        The index lists them too.
    """
    plans = plan_sessions(session_dir, scenes=scenes, illuminations=illuminations, no_dark=no_dark)
    for plan in plans:
        for warning in plan.warnings:
            if on_warning is None:
                warnings.warn(warning, DataWarning, stacklevel=2)
            else:
                on_warning(warning)
    out = Path(out_dir)
    run = HDRRun(out, method)
    details = {"sessions": [str(plan.session) for plan in plans], "method": method}
    sessions = [plan.session for plan in plans]
    with staged_output_folder(out, command="labkit hdr", details=details, inputs=sessions) as stage:
        for plan in plans:
            _merge_plan(plan, stage, run, previews=previews, on_frame=on_frame, on_image=on_image)
        index = json.loads(json.dumps(_index(plans, run), default=json_default))  # plain types
        write_text_atomic(stage / INDEX_FILE, yaml.safe_dump(index, sort_keys=False))
    return run


def plan_sessions(
    session_dirs: str | Path | Sequence[str | Path],
    *,
    scenes: Sequence[str] | None = None,
    illuminations: Sequence[str] | None = None,
    no_dark: bool = False,
) -> list[HDRPlan]:
    """:func:`plan_hdr` of one or more sessions, checked to merge into one folder.

    Raises
    ------
    DataError
        As :func:`plan_hdr`; no session has a lit frame to merge; two sessions hold the
        same (scene, illumination); the same session is given twice.
    """
    folders = [session_dirs] if isinstance(session_dirs, str | Path) else list(session_dirs)
    if not folders:
        raise DataError("no session to merge; give at least one session folder")
    seen: set[Path] = set()
    for folder in map(Path, folders):
        if folder.resolve() in seen:
            raise DataError(f"session {folder} is given twice; give each session once")
        seen.add(folder.resolve())
    many = len(folders) > 1
    plans = [
        plan_hdr(
            folder,
            scenes=scenes,
            illuminations=illuminations,
            no_dark=no_dark,
            allow_empty=many,
        )
        for folder in folders
    ]
    owner: dict[tuple[str, str], Path] = {}
    for plan in plans:
        if (plan.shape, plan.cfa) != (plans[0].shape, plans[0].cfa):
            raise DataError(
                f"session {plan.session} has {plan.shape[0]}×{plan.shape[1]} {plan.cfa} frames "
                f"but session {plans[0].session} has {plans[0].shape[0]}×{plans[0].shape[1]} "
                f"{plans[0].cfa}; merge sessions of one camera mode into one folder"
            )
        for job in plan.jobs:
            key = (job.scene, job.illumination)
            if key in owner:
                raise DataError(
                    f"{job.name} is in both session {owner[key]} and session {plan.session}; "
                    "one HDR folder holds one image of each scene × illumination: merge them "
                    "into separate --out folders, or pick one with --scene / --illumination"
                )
            owner[key] = plan.session
    if not owner:
        wanted = ", ".join([*(scenes or []), *(illuminations or [])])
        raise DataError(
            f"sessions {', '.join(map(str, folders))} have no lit frames"
            + (f" for {wanted}" if wanted else "")
        )
    return [plan for plan in plans if plan.jobs]


def _merge_plan(
    plan: HDRPlan,
    stage: Path,
    run: HDRRun,
    *,
    previews: bool,
    on_frame: Callable[[], None] | None,
    on_image: Callable[[HDROutput], None] | None,
) -> None:
    """Merge the jobs of one session's plan into the staging folder."""
    out, method, no_dark = run.out, run.method, plan.no_dark
    library = _DarkLibrary(plan, on_frame)
    for job in plan.jobs:
        result = merge_exposures(
            job.exposures,
            library.get,
            cfa=plan.cfa,
            levels=plan.levels,
            method=method,
            on_frame=on_frame,
        )
        if no_dark:
            result.warnings.append("no dark frames subtracted (--no-dark): only the black level")
        name = Path(job.scene) / f"{job.illumination}.exr"
        write_raw_exr(
            stage / name,
            RawImage(
                raw=result.raw,
                cfa=plan.cfa,
                exposure_s=result.reference_exposure_s,
                illumination=job.illumination,
                wavelength_nm=job.wavelength_nm,
                variance=result.variance,
                labkit=_provenance(plan, job, result),
            ),
        )
        preview = None
        if previews:
            preview = out / name.with_suffix(".png")
            write_png(
                stage / name.with_suffix(".png"),
                raw_preview(result.raw, plan.cfa, white_balance=job.wavelength_nm is None),
            )
        output = HDROutput(job, result, out / name, preview, plan.session)
        run.outputs.append(output)
        if on_image is not None:
            on_image(output)


def image_summary(result: HDRResult) -> str:
    """One line for one merged image: its exposures, and how far the fitted scaling factors
    lie from the exposure-time ratios."""
    times = sorted(e.exposure_s for e in result.exposures)
    span = exposure_label(times[0])
    if len(times) > 1:
        span += f"–{exposure_label(times[-1])}"
    text = f"{len(times)} exposure{'s' if len(times) > 1 else ''} {span}"
    if result.pairs:
        worst = max(abs(e.disagreement) for e in result.exposures)
        text += f", factors within {worst:.1%} of the exposure-time ratios"
        nominal = sum(pair.fallback is not None for pair in result.pairs)
        if nominal:
            text += f" ({nominal} of {len(result.pairs)} taken from them)"
    return text


def factor_table(result: HDRResult) -> str:
    """The Table 4.1 comparison as Markdown: fitted factors against exposure-time ratios."""
    lines = [
        "| exposure | t_ref/t | fitted | R | G | B | difference |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for e in result.exposures:
        channels = " | ".join(
            "–" if e.per_channel[c] is None else f"{e.per_channel[c]:.4f}" for c in "RGB"
        )
        lines.append(
            f"| {exposure_label(e.exposure_s)} | {e.nominal:.4f} | {e.factor:.4f} | {channels} "
            f"| {e.disagreement:+.2%} |"
        )
    return "\n".join(lines)


class _DarkLibrary:
    """Mean darks per exposure, computed on first use and dropped after their last use."""

    def __init__(self, plan: HDRPlan, on_frame: Callable[[], None] | None) -> None:
        self.plan = plan
        self.on_frame = on_frame
        self.uses = Counter(e.exposure_s for job in plan.jobs for e in job.exposures)
        self.cache: dict[float, DarkFrame] = {}

    def get(self, exposure_s: float) -> DarkFrame:
        if self.plan.no_dark or exposure_s not in self.plan.darks:
            dark = DarkFrame.black_level(exposure_s, self.plan.levels.black_level_dn)
        elif exposure_s in self.cache:
            dark = self.cache[exposure_s]
        else:
            dark = DarkFrame.from_frames(
                self.plan.darks[exposure_s], shape=self.plan.shape, on_frame=self.on_frame
            )
            self.cache[exposure_s] = dark
        self.uses[exposure_s] -= 1
        if self.uses[exposure_s] <= 0:
            self.cache.pop(exposure_s, None)
        return dark


def _by_replicate(records: list[dict]) -> list[dict]:
    return sorted(records, key=lambda r: int(r["replicate"]))


def _source(folder: Path, record: dict, levels: SensorLevels, retake: str) -> FrameSource:
    path = folder / record["file"]
    name = f"frame {record['key']} ({path})"
    fix = f"`labkit session show {folder} --verify` lists damaged frames; {retake} to re-take them"

    def load() -> np.ndarray:
        try:
            data = read_verified(path, sha256=record["sha256"], size=record.get("bytes"), name=name)
        except DataError as error:
            raise DataError(f"{error}; {fix}") from None
        try:
            image = read_raw_tiff(path, data=data)[0]
        except DataError as error:
            raise DataError(f"{name}: {error}; {fix}") from None
        if image.shape != tuple(record["shape"]):
            raise DataError(
                f"{name} is {image.shape[0]}×{image.shape[1]} but its record says "
                f"{record['shape'][0]}×{record['shape'][1]}; {fix}"
            )
        return _checked(image, levels, name)

    return FrameSource(name, load)


def _levels(records: list[dict], folder: Path, *, imported: bool, retake: str) -> SensorLevels:
    """The one saturation and black level of the frames to merge, from the manifest.

    A record without levels (a capture backend that does not report them) takes the
    saturation of its pixel format's bit depth and black level 0. Frames whose levels
    differ cannot share darks or factors, so that is an error, as is a pixel format
    without a bit depth; each frame's counts are checked against the levels when read.
    """
    found: dict[tuple[float, float], dict] = {}
    counts: Counter[tuple[float, float]] = Counter()
    for record in records:
        saturation = record.get("saturation_dn")
        if saturation is None:
            try:
                saturation = 2 ** pixel_format_bits(record["pixel_format"]) - 1
            except DataError as error:
                raise DataError(
                    f"session {folder}: frame {record['key']} records no saturation level and "
                    f"{error}; import the frames again with `labkit session import --bits N` "
                    "or `--saturation DN`"
                ) from None
        black = record.get("black_level")
        level = (float(saturation), float(black or 0.0))
        found.setdefault(level, record)
        counts[level] += 1
    if len(found) > 1:
        common = max(counts, key=counts.__getitem__)
        odd = next(level for level in found if level != common)
        record = found[odd]
        black = f"black level {odd[1]:g} DN"
        if record.get("black_level") is None:
            black = "no black level (null, read as 0 DN)"
        if imported or "levels_from" in record:
            fix = (
                "frames and darks of different bit depths cannot be merged: import them "
                "again with one --bits or --saturation"
            )
        else:
            fix = (
                f"one capture records one set of levels, so {MANIFEST_FILE} is damaged or was "
                f"edited: restore it from a backup, or delete that frame's line and {retake} "
                "to re-take it"
            )
        raise DataError(
            f"session {folder}: frame {record['key']} has saturation {odd[0]:g} DN and {black} "
            f"but {counts[common]} other frame(s) have saturation {common[0]:g} DN and black "
            f"level {common[1]:g} DN; {fix}"
        )
    (saturation, black), _ = found.popitem()
    try:
        return SensorLevels(saturation, black)
    except DataError as error:
        raise DataError(f"session {folder}: {error}") from None


def _check_capacity(dtype: np.dtype, levels: SensorLevels, name: str) -> None:
    capacity = np.iinfo(dtype).max if dtype.kind in "ui" else np.inf
    if levels.saturation_dn > capacity:
        raise DataError(
            f"{name} is {dtype} (at most {capacity} DN) but the session's saturation "
            f"level is {levels.saturation_dn:g} DN: no pixel could ever saturate, so every "
            "level-based decision of the merge would be wrong; import the frames again with "
            "`labkit session import` (which records each frame's levels)"
        )


def _stored_dtype(folder: Path, record: dict) -> np.dtype:
    try:
        with tifffile.TiffFile(folder / record["file"]) as tif:
            return tif.pages[0].dtype
    except Exception:  # unreadable: reported with the fix when the merge reads it
        return np.dtype(np.uint16)


def _checked(image: np.ndarray, levels: SensorLevels, name: str) -> np.ndarray:
    """`image`, unless its counts contradict the levels the merge would assume."""
    _check_capacity(image.dtype, levels, name)
    peak = image.max(initial=0)
    if peak > levels.saturation_dn:
        raise DataError(
            f"{name} has values up to {peak} DN, above the session's saturation level "
            f"{levels.saturation_dn:g} DN; import the frames again with the right --bits or "
            "--saturation"
        )
    return image


def _provenance(plan: HDRPlan, job: HDRJob, result: HDRResult) -> dict[str, Any]:
    return {
        "scene": job.scene,
        "illumination": job.illumination,
        "session": str(plan.session),
        "software": f"labkit {labkit.__version__}",
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "dark_subtraction": "black level only" if plan.no_dark else "mean dark frames",
        **result.provenance(),
    }


def _index(plans: list[HDRPlan], run: HDRRun) -> dict[str, Any]:
    first = plans[0]
    return {
        "format": 1,
        "session": str(first.session) if len(plans) == 1 else None,
        "sessions": [str(plan.session) for plan in plans],
        "method": run.method,
        "cfa": first.cfa,
        "shape": list(first.shape),
        "software": f"labkit {labkit.__version__}",
        "warnings": [warning for plan in plans for warning in plan.warnings],
        "images": [
            {
                "scene": o.job.scene,
                "illumination": o.job.illumination,
                "session": str(o.session),
                "wavelength_nm": o.job.wavelength_nm,
                "file": str(o.exr.relative_to(run.out)),
                "reference_exposure_s": o.result.reference_exposure_s,
                "exposures": [
                    {
                        "exposure_s": e.exposure_s,
                        "replicates": e.replicates,
                        "darks": e.darks,
                        "nominal_factor": round(e.nominal, 8),
                        "factor": round(e.factor, 8),
                        "disagreement_percent": round(100 * e.disagreement, 4),
                    }
                    for e in o.result.exposures
                ],
                "noise": None if o.result.noise is None else o.result.noise.as_dict(),
                "pairs": [
                    {
                        "longer_s": pair.longer_s,
                        "shorter_s": pair.shorter_s,
                        "pixels": pair.pairs,
                        "fitted": pair.fallback is None,
                    }
                    for pair in o.result.pairs
                ],
                "saturated_pixels": o.result.saturated_pixels,
                "dark_pixels": o.result.dark_pixels,
                "warnings": o.result.warnings,
                "notes": o.result.notes,
            }
            for o in run.outputs
        ],
    }
