"""``labkit reconstruct RAW (--rig RIG | --response CSV) --out DIR``: thesis problem (3.1).

RAW is any raw Bayer mosaic :func:`labkit.io.read_mosaic` reads: a raw EXR (from
``labkit hdr`` or other software), a single-channel TIFF/PNG mosaic or a camera raw file.

A thin layer over :func:`reconstruction.reconstruct`: every option is checked (and every
input read) before any work starts or anything is written, then the spectral image, its
raw colour, an sRGB preview and the log are written into DIR as one set (DIR is replaced as
a whole; an interrupted run leaves the previous DIR as it was).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labkit.cli._commands import Commands
from labkit.cli._options import add_cfa_option
from labkit.errors import ConfigError, DataError
from reconstruction.option_table import NONE_TEXT, OPTION_TABLE, OptionSpec, flags

#: What ``--scheduler`` accepts besides ``tcp://host:port``.
SCHEDULERS = ("threads", "processes", "sync")
#: How the command line spells the options of :class:`reconstruction.ReconstructOptions`:
#: the declared ones (:mod:`reconstruction.option_table`) and those read from files.
CLI_NAMES = flags(
    {"cfa": "--cfa", "response": "--response", "dispersion": "--dispersion",
     "scheduler": "--scheduler"}
)  # fmt: skip

#: The weight criteria the command line can use (``auto:msec`` needs the true image).
CLI_CRITERIA = ("dmc", "dmc-menon", "dmc-malvar", "mdc")


def register(commands: Commands) -> None:
    """Add ``labkit reconstruct``."""
    parser = commands.add_parser(
        "reconstruct",
        description="Reconstruct a spectral image straight from a raw Bayer mosaic by solving "
        "a regularised inverse problem (the camera, its colour filters and the lens' "
        "dispersion as one linear model), patch by patch on Dask. "
        "RAW is a raw EXR (from `labkit hdr`, or from other software: channel 'raw' or the "
        "only channel), a single-channel uint8/uint16/float TIFF or PNG mosaic (integers "
        "scaled by the container's maximum), or a camera raw file read by LibRaw (DNG, NEF, "
        "CR2, CR3, ARW, ORF, RW2, PEF, …; black level subtracted, scaled to the white level; "
        "Bayer sensors only). The camera response comes from --rig or --response, the CFA "
        "layout from the file, else --cfa, else the rig; --dispersion "
        "adds the lens' lateral chromatic aberration (a to_reference model). Writes "
        "DIR/spectral.exr (one band per --bands centre, in the raw image's units per nm), "
        "DIR/raw_colour.exr (the aberration-free image in raw camera colour), "
        "DIR/preview.png (CIE 1931 2° → sRGB, 99.5th percentile of luminance shown as "
        "white) and DIR/log.json (weights, iterations, times, what each patch skipped, the "
        "arguments). With --latent colour the latent image is raw colour (direct colour "
        "estimation) and "
        "no spectral.exr is written. Bad input is refused before anything is written.",
    )
    parser.add_argument(
        "raw",
        type=Path,
        help="raw Bayer mosaic: raw EXR (e.g. from `labkit hdr`), single-channel TIFF/PNG "
        "(with --cfa) or camera raw file (DNG, NEF, CR2, ARW, …)",
    )
    add_cfa_option(parser, default="the rig's with --rig")
    parser.add_argument(
        "--rig", type=Path, default=None, help="rig YAML: camera response and CFA layout"
    )
    parser.add_argument(
        "--response",
        default=None,
        metavar="FILE.csv",
        help="camera response CSV (wavelength_nm,R,G,B), a colour-science dataset name, or "
        "the sensitivity.yaml/.csv of `labkit calibrate sensitivity` (the thesis' sensor map: "
        "the bands default to its bands), instead of --rig (the CFA layout then comes from "
        "the raw file or --cfa)",
    )
    parser.add_argument(
        "--dispersion",
        type=Path,
        default=None,
        metavar="MODEL.yaml",
        help="to_reference dispersion model of this camera and image size (spectral for "
        "--latent spectral, colour-channel for --latent colour); default: no Φ",
    )
    for spec in OPTION_TABLE:
        _add_declared(parser, spec)
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="threads|processes|sync|tcp://HOST:PORT|tls://HOST:PORT",
        help="Dask scheduler for the patches: local threads (default), a pool of local "
        "processes, one per core (started once per command), "
        "synchronous, or a dask.distributed scheduler's address (tcp:// is neither "
        "authenticated nor encrypted: use it on a trusted network only; tls:// uses the "
        "certificates of Dask's configuration, distributed.comm.tls.*)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output folder: new, empty, or from an earlier labkit run (replaced as a whole)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar (it is off anyway off a terminal)"
    )
    parser.set_defaults(handler=_reconstruct)


def _add_declared(parser: argparse.ArgumentParser, spec: OptionSpec) -> None:
    """The flag of a declared option (:mod:`reconstruction.option_table`): its text is kept
    as given (None when left out) and parsed in :func:`_prepare`, against the same bounds as
    the Python API's."""
    from dataclasses import MISSING, fields

    from reconstruction import ReconstructOptions

    default = spec.default_help
    if not default:
        field = next(f for f in fields(ReconstructOptions) if f.name == spec.name)
        value = field.default if field.default is not MISSING else None
        if spec.kind == "flag":
            default = spec.flag if value else f"--no-{spec.flag[2:]}"
        else:
            default = _shown(value)
    text = f"{spec.help} (default: {default})"
    if spec.kind == "flag":
        parser.add_argument(
            spec.flag, action=argparse.BooleanOptionalAction, default=None, help=text
        )
    else:
        parser.add_argument(spec.flag, default=None, metavar=spec.metavar, help=text)


@dataclass
class _Job:
    """Everything read and checked before any work starts."""

    raw: Any  # labkit.io.RawImage
    response_source: str | None
    options: Any  # reconstruction.ReconstructOptions


def _reconstruct(args: argparse.Namespace) -> int:
    from labkit.io.output_folder import writer_lock

    job = _prepare(args)
    with writer_lock(args.out, command="labkit reconstruct"):  # refuse a second writer now
        return _run(args, job)


def _run(args: argparse.Namespace, job: _Job) -> int:
    import time

    started = time.perf_counter()
    bar = _ProgressBar(enabled=not args.quiet and sys.stderr.isatty())
    weights = job.options.weights
    if bar.enabled and isinstance(weights, str) and weights.startswith("auto:"):
        print(f"choosing weights ({weights})…", file=sys.stderr)
    try:
        from reconstruction import reconstruct
        from reconstruction.reconstruct import DomainWarning

        with warnings.catch_warnings():  # the summary prints them from the log
            warnings.simplefilter("ignore", DomainWarning)
            result = reconstruct(job.raw.raw, job.options, progress=bar.update)
    except OSError as error:
        from reconstruction.solve.patches import REMOTE_SCHEMES

        if not (args.scheduler or "").startswith(REMOTE_SCHEMES):
            raise
        raise DataError(_unreachable(args.scheduler, error)) from None
    finally:
        bar.close()
    seconds = time.perf_counter() - started
    paths = _write_outputs(args, job, result)
    _print_summary(args, result, paths, seconds)
    return 0


# -- checking -------------------------------------------------------------------------
def _prepare(args: argparse.Namespace) -> _Job:
    """Read the inputs and build the validated options; raises before anything is written."""
    from labkit.io import read_mosaic
    from reconstruction import ReconstructOptions
    from reconstruction.options import OptionError
    from reconstruction.reconstruct import check_raw

    scheduler = _scheduler(args.scheduler)
    given = _declared(args)
    latent = given.get("latent", "spectral")
    _check_out(args.out, inputs=[args.raw, args.dispersion, args.rig])
    if args.rig is not None and args.response is not None:
        raise ConfigError(
            "give either --rig (camera response and CFA from the rig file) or --response "
            "(a response CSV), not both"
        )
    if latent == "spectral" and args.rig is None and args.response is None:
        raise ConfigError(
            "a spectral reconstruction needs the camera response: give --rig RIG.yaml or "
            "--response FILE.csv (wavelength_nm,R,G,B)"
        )
    if "weights" in given:
        _check_weights(given["weights"])

    if args.raw.is_dir():
        raise DataError(
            f"raw image {args.raw} is a folder; give one raw Bayer mosaic file in it (raw "
            "EXR, single-channel TIFF/PNG or camera raw file), e.g. an image of `labkit hdr`'s "
            "DIR/<scene>/<illumination>.exr"
        )
    if not args.raw.is_file():
        raise DataError(
            f"raw image {args.raw} does not exist; give a raw Bayer mosaic (raw EXR, "
            "single-channel TIFF/PNG or camera raw file)"
        )
    from labkit.io.light import check_light
    from labkit.io.output_folder import verify_output_file

    verify_output_file(args.raw, what="raw image")
    rig = None
    if args.rig is not None:
        from labkit.rig import load_rig

        rig = load_rig(args.rig)
        if args.cfa is not None and args.cfa != rig.cfa:
            raise ConfigError(
                f"CFA layouts disagree: --cfa says {args.cfa}, {args.rig} says {rig.cfa} "
                f"(camera.pixel_format {rig.camera.pixel_format}); use the rig the image was "
                "taken with"
            )
    if args.cfa is None and rig is not None:  # the rig's layout for files that name none
        raw = read_mosaic(args.raw, cfa=rig.cfa, cfa_from=str(args.rig))
    else:
        raw = read_mosaic(args.raw, cfa=args.cfa)
    check_raw(raw.raw, where=f"raw image {args.raw}")
    check_light(raw.raw, name=f"raw image {args.raw}", fix="give a raw image of a lit scene")

    response, source = None, None
    if rig is not None:
        source = rig.response_source()
        response = _response(source, f"{args.rig}: camera.response")
    elif args.response is not None:
        source = args.response
        response = _response(source, "--response")
    names = dict(CLI_NAMES)
    if latent == "spectral" and "bands" not in given and _is_sensor_map(source):
        given["bands"] = [float(w) for w in response.wavelengths]  # the map's own bands
        names["bands"] = f"the bands of {source}"
    elif source is not None:
        names["response"] = f"camera response {source}"
    try:
        options = ReconstructOptions(
            cfa=raw.cfa,
            response=response if latent == "spectral" else None,
            dispersion=args.dispersion,
            scheduler=scheduler,
            **given,
        )
    except OptionError as error:
        raise ConfigError(error.message(names)) from None
    if args.dispersion is not None:
        try:
            options.check_image(raw.raw.shape, where=f"--dispersion {args.dispersion}")
        except OptionError as error:
            raise ConfigError(error.message(names)) from None
    return _Job(raw=raw, response_source=source, options=options)


def _declared(args: argparse.Namespace) -> dict[str, Any]:
    """The declared options given on the command line, parsed and checked against the
    option table (:mod:`reconstruction.option_table`); those left out are absent, so that
    :class:`~reconstruction.ReconstructOptions` applies its defaults."""
    from reconstruction.option_table import PARSERS, OptionValueError

    given: dict[str, Any] = {}
    for spec in OPTION_TABLE:
        value = getattr(args, spec.name)
        if value is None:
            continue
        try:
            if spec.kind == "flag":
                given[spec.name] = spec.check(value)
            else:
                given[spec.name] = PARSERS.get(spec.name, spec.parse)(value)
        except OptionValueError as error:
            raise ConfigError(error.template.replace("{option}", spec.flag)) from None
    return given


def _scheduler(value: str | None) -> str | None:
    from reconstruction.solve.patches import probe_scheduler, scheduler_address

    if value is None or value in SCHEDULERS:
        return value
    try:
        scheduler_address(value)
    except ConfigError:
        raise ConfigError(
            f"--scheduler is {value!r}; use {', '.join(SCHEDULERS)}, tcp://HOST:PORT or "
            "tls://HOST:PORT (a dask.distributed scheduler)"
        ) from None
    probe_scheduler(value)
    return value


def _unreachable(scheduler: str, error: OSError) -> str:
    return (
        f"--scheduler {scheduler}: cannot reach the Dask scheduler ({error}); start one "
        "(`dask scheduler`) or use --scheduler threads"
    )


def _check_weights(text: str) -> None:
    """The criteria the command line offers (``auto:msec`` needs the Python API's truth)."""
    kind, _, rest = text.partition(":")
    if kind == "auto" and rest == "msec":
        raise ConfigError(
            f"--weights {text} needs the true spectral image, which only the Python API takes "
            "(reconstruct(..., truth=...)); use auto:dmc, auto:dmc-menon, auto:mdc or fixed:W"
        )
    if kind == "auto" and rest not in CLI_CRITERIA:
        raise ConfigError(
            f"--weights {text}: unknown criterion {rest!r}; use "
            f"{', '.join('auto:' + c for c in CLI_CRITERIA)} or fixed:W"
        )


def _check_out(out: Path, *, inputs: list[Path | None]) -> None:
    """The output folder can be written (:func:`check_output_folder`) without removing one
    of the run's `inputs`; nothing is created."""
    from labkit.io.output_folder import check_output_folder

    given = [path for path in inputs if path is not None]
    check_output_folder(out, command="labkit reconstruct", inputs=given)


def _response(source: str, where: str) -> Any:
    from calibration.sensitivity import load_response

    try:
        return load_response(source)
    except DataError as error:
        raise DataError(f"{where}: {error}") from None


def _is_sensor_map(source: str | None) -> bool:
    from calibration.sensitivity import is_sensitivity_file

    return source is not None and is_sensitivity_file(source)


# -- running ----------------------------------------------------------------------------
class _ProgressBar:
    """tqdm bar over patches, created at the first patch (weight selection prints none)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bar = None

    def update(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="patch", desc="reconstruct", dynamic_ncols=True)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# -- writing ----------------------------------------------------------------------------
def _write_outputs(args: argparse.Namespace, job: _Job, result: Any) -> dict[str, Path]:
    """Write the outputs through :meth:`Reconstruction.save`; returns their paths by name."""
    provenance = {
        "command": "labkit reconstruct",
        "input": str(args.raw),
        "raw": {
            "cfa": job.raw.cfa,
            "shape": list(job.raw.raw.shape),
            "exposure_s": job.raw.exposure_s,
            "illumination": job.raw.illumination,
            "wavelength_nm": job.raw.wavelength_nm,
            "labkit": job.raw.labkit,
        },
        "rig": None if args.rig is None else str(args.rig),
        "response": job.response_source,
        "dispersion_model": None if args.dispersion is None else str(args.dispersion),
    }
    arguments = {k: v for k, v in vars(args).items() if k not in ("handler", "command")}
    options = {k: v for k, v in job.options.as_dict().items() if k != "weights"}
    return result.save(
        args.out,
        provenance=provenance,
        log={"arguments": arguments, "options": options},
    )


def _shown(value: Any) -> str:
    if value is None:
        return NONE_TEXT
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
    return str(value)


def _print_summary(
    args: argparse.Namespace, result: Any, paths: dict[str, Path], seconds: float
) -> None:
    log = result.log
    rows, cols = result.raw_colour.shape[:2]
    if result.wavelengths_nm is not None:
        w = result.wavelengths_nm
        what = f"{len(w)} bands {w[0]:g}–{w[-1]:g} nm"
    else:
        what = "raw colour (latent colour)"
    sign = "non-negative" if log["nonneg"] else "signed"
    balance = f" (band balance γ = {log['band_balance']:g})" if log.get("band_balance") else ""
    print(f"reconstructed {rows}×{cols} px → {what}; prior {log['prior']}{balance}, {sign}")
    weights = log["weights"]
    values = ", ".join(f"{v:.4g}" for v in weights["values"])
    if weights["criterion"] == "fixed":
        print(f"weights: {values} (fixed)")
    else:
        print(
            f"weights: {values} (auto:{weights['criterion']}, {weights['solves']} solves, "
            f"{weights['seconds']:.1f} s)"
        )
    patches = log["patches"]
    flat = patches["flat"]
    if args.dispersion is None:
        phi = "no dispersion model"
    elif log["dispersion"]["correction"] == "warp":
        phi = f"solved without the dispersion, then warped ({log['warp_seconds']:.1f} s)"
    else:
        skipped = patches["phi_skipped_negligible"] + patches["phi_skipped_flat"]
        phi = (
            f"Φ used on {patches['phi_used']}, skipped on {skipped} "
            f"({patches['phi_skipped_negligible']} negligible dispersion, "
            f"{patches['phi_skipped_flat']} flat)"
        )
    print(
        f"patches: {patches['count']}, {flat} flat; {phi}; iterations median "
        f"{patches['iterations_median']:g}, max {patches['iterations_max']}"
    )
    unconverged = patches["count"] - patches["converged"]
    if unconverged:
        print(
            f"warning: {unconverged} patch(es) stopped at the iteration limit before reaching "
            "--rtol"
        )
    light = (log.get("dispersion") or {}).get("band_light_nm")
    if light:
        pairs = ", ".join(
            f"{b:g} → {w:.1f}" for b, w in zip(log["bands_nm"], light["values"], strict=True)
        )
        print(f"Φ at the filters' effective wavelengths (nm): {pairs}")
    made = [(name, c) for name, c in log["choices"].items() if c["source"] != "given"]
    if made:
        print("choices labkit made (give the option to override):")
        for name, c in made:
            print(f"  {CLI_NAMES.get(name, name)} {_shown(c['value'])}: {c['reason']}")
    for notice in log["warnings"]:
        print(f"warning: {notice}")
    print(f"time: {seconds:.1f} s (weights {weights['seconds']:.1f} s, patches "
          f"{log['solve_seconds']:.1f} s)")  # fmt: skip
    print("wrote " + ", ".join(str(path) for path in paths.values()))
