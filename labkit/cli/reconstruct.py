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
import itertools
import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labkit.cli._options import add_cfa_option, add_extrapolation_option
from labkit.errors import ConfigError, DataError

#: What ``--scheduler`` accepts besides ``tcp://host:port``.
SCHEDULERS = ("threads", "processes", "sync")
#: Texture below which a patch counts as flat (passed to reconstruct, counted in the summary).
FLAT_THRESHOLD = 0.01
#: How the command line spells the options of :class:`reconstruction.ReconstructOptions`.
CLI_NAMES = {
    "cfa": "--cfa",
    "response": "--response",
    "bands": "--bands",
    "dispersion": "--dispersion",
    "correction": "--correction",
    "extrapolation": "--extrapolation",
    "interpolation": "--interpolation",
    "prior": "--prior",
    "nonneg": "--nonneg",
    "spectral_smoothness": "--spectral-smoothness",
    "band_balance": "--band-balance",
    "weights": "--weights",
    "latent": "--latent",
    "reference": "--reference",
    "rtol": "--rtol",
    "exact": "--exact",
    "patch_px": "--patch-px",
    "pad_px": "--pad-px",
    "scheduler": "--scheduler",
}

#: The weight criteria the command line can use (``auto:msec`` needs the true image).
CLI_CRITERIA = ("dmc", "dmc-menon", "dmc-malvar", "mdc")


def register(commands: argparse._SubParsersAction) -> None:
    """Add ``labkit reconstruct``."""
    parser = commands.add_parser(
        "reconstruct",
        help="spectral image from one Bayer raw image, free of lateral chromatic aberration",
        description="Reconstruct a spectral image straight from a raw Bayer mosaic by solving "
        "thesis problem (3.1), A = M·Ω·Φ·B with a regularising prior, patch by patch on Dask. "
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
        "arguments). With --latent colour the latent image is raw colour (thesis (3.27)) and "
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
        "--bands",
        default=None,
        metavar="NM,NM,…",
        help="equally spaced band centres, nm, e.g. 400,450,500,550,600,650,700 "
        "(default: chosen from the camera response's bandlimit, thesis §3.3.2)",
    )
    parser.add_argument(
        "--dispersion",
        type=Path,
        default=None,
        metavar="MODEL.yaml",
        help="to_reference dispersion model of this camera and image size (spectral for "
        "--latent spectral, colour-channel for --latent colour); default: no Φ",
    )
    parser.add_argument(
        "--correction",
        default="model",
        metavar="model|warp",
        help="model: Φ inside the problem (3.1) (default); warp: thesis §3.9.2, solve "
        "without Φ and warp the result onto the reference band (either model direction)",
    )
    add_extrapolation_option(parser, model="the dispersion model")
    parser.add_argument(
        "--interpolation",
        default="cubic",
        metavar="cubic|bilinear",
        help="sampling weights of Φ: Keys' cubic convolution (default), which avoids "
        "bilinear's blur and the overshoot it causes at edges, or bilinear (thesis §3.2.5), "
        "faster (figures in the README)",
    )
    parser.add_argument(
        "--prior",
        default="EdgeL2",
        help="EdgeL2 (default): the L2 prior weighted by the raw image's own edges, which "
        "fills unsampled pixels along edges rather than across them, at L2's cost; a prior "
        "of thesis Table 3.1: L1, L2, Lap1, Lap2, L1L1, L2L2, L1SpatialLap2 or "
        "L1SpectralLap2; or VTV, vectorial total variation (edges shared by all bands; "
        "sharpest edges, about 3× the time)",
    )
    parser.add_argument(
        "--nonneg",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="constrain the latent image to be non-negative (default: --nonneg)",
    )
    parser.add_argument(
        "--spectral-smoothness",
        default=None,
        metavar="SIGMA",
        help="weight σ of the spectral roughness term, which picks the smoothest of the "
        "spectra the data and the prior cannot tell apart without pulling each patch's "
        "mean colour (beyond the thesis), in normalised units; 0 is the thesis' problem, "
        "for narrow-band light (bandpass filters, lasers, LEDs), whose spectra it biases "
        "(default 1e-3 with --latent spectral, 0 with --latent colour and for an image "
        "whose mean colour no smooth spectrum gives, which is printed and logged)",
    )
    parser.add_argument(
        "--band-balance",
        default=None,
        metavar="GAMMA",
        help="γ in [0, 1] of the L2 and EdgeL2 priors' band balance (beyond the thesis): each "
        "band's spatial smoothing is weighed by its share of the camera's response to the "
        "power γ, so that bands the camera barely senses keep their edges; 0 smooths every "
        "band alike, as the thesis (default 0.5 for EdgeL2 with spectral smoothness σ > 0, "
        "else 0; refused at --spectral-smoothness 0)",
    )
    parser.add_argument(
        "--weights",
        default="auto:dmc",
        metavar="auto:dmc|auto:dmc-menon|auto:dmc-malvar|auto:mdc|fixed:W[,W…]",
        help="regularisation weights: chosen by Algorithm 3 on the most textured patch with "
        "the demosaicing criterion against bilinear demosaicing (dmc, the thesis') or "
        "against Menon's or Malvar's demosaic (dmc-menon, dmc-malvar: sharper weights for "
        "--prior VTV; not for narrow-band light), or the minimum-distance criterion (mdc); "
        "or fixed, one per prior term, in normalised units (default auto:dmc)",
    )
    parser.add_argument(
        "--latent",
        default="spectral",
        metavar="spectral|colour",
        help="spectral: problem (3.1); colour: direct raw-colour estimation (3.27) "
        "(default spectral)",
    )
    parser.add_argument(
        "--reference",
        default="none",
        metavar="mean-colour|none",
        help="mean-colour: reconstruct relative to a smooth spectrum fitted to the image's "
        "mean colour (thesis §6.3) (default none)",
    )
    parser.add_argument(
        "--rtol",
        default=None,
        metavar="TOL",
        help="ADMM relative tolerance per patch (default 1e-5, within 1e-4 of the optimum; "
        "1e-4 with --spectral-smoothness 0)",
    )
    parser.add_argument(
        "--exact",
        action="store_true",
        help="with --nonneg and an L2-type prior, solve every patch exactly (projected-Newton "
        "active-set method) instead of by ADMM alone; with --spectral-smoothness 0 ADMM stops "
        "0.05–10 %% above the optimum at small weights, at several times the cost. (With the "
        "default σ, patches with few values at zero are solved exactly anyway, faster than "
        "ADMM, and the rest by ADMM to within 1e-4.)",
    )
    parser.add_argument(
        "--patch-px",
        default="48",
        metavar="N",
        help="patch size, px, even ≥ 8 (default 48: small patches suit the FFT "
        "preconditioner of the dispersion-aware solve)",
    )
    parser.add_argument(
        "--pad-px",
        default=None,
        metavar="N",
        help="overlap on each side of a patch, px, even ≥ 2; at least twice the largest "
        "dispersion (default: the smallest even value ≥ 8 that is)",
    )
    parser.add_argument(
        "--scheduler",
        default="threads",
        metavar="threads|processes|sync|tcp://HOST:PORT|tls://HOST:PORT",
        help="Dask scheduler for the patches: local threads (default), local processes, "
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
    if bar.enabled and args.weights.startswith("auto:"):
        print(f"choosing weights ({args.weights}, Algorithm 3)…", file=sys.stderr)
    try:
        from reconstruction import reconstruct
        from reconstruction.reconstruct import DomainWarning, NarrowBandWarning

        with warnings.catch_warnings():  # the summary prints them from the log
            warnings.simplefilter("ignore", NarrowBandWarning)
            warnings.simplefilter("ignore", DomainWarning)
            result = reconstruct(job.raw.raw, job.options, progress=bar.update)
    except OSError as error:
        from reconstruction.patches import REMOTE_SCHEMES

        if not args.scheduler.startswith(REMOTE_SCHEMES):
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
    rtol = None if args.rtol is None else _positive_float(args.rtol, "--rtol")
    smoothness = None
    if args.spectral_smoothness is not None:
        smoothness = _positive_float(args.spectral_smoothness, "--spectral-smoothness", zero=True)
    balance = None
    if args.band_balance is not None:
        balance = _positive_float(args.band_balance, "--band-balance", zero=True, most=1.0)
    patch_px = _even_int(args.patch_px, "--patch-px", 8)
    pad_px = None if args.pad_px is None else _even_int(args.pad_px, "--pad-px", 2)
    _check_out(args.out, inputs=[args.raw, args.dispersion, args.rig])
    if args.rig is not None and args.response is not None:
        raise ConfigError(
            "give either --rig (camera response and CFA from the rig file) or --response "
            "(a response CSV), not both"
        )
    if args.latent == "spectral" and args.rig is None and args.response is None:
        raise ConfigError(
            "a spectral reconstruction needs the camera response: give --rig RIG.yaml or "
            "--response FILE.csv (wavelength_nm,R,G,B)"
        )
    bands = None if args.bands is None else _bands(args.bands)
    _check_weights(args.weights)

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
    if args.latent == "spectral" and bands is None and _is_sensor_map(source):
        bands = [float(w) for w in response.wavelengths]  # the map's own bands
        names["bands"] = f"the bands of {source}"
    elif source is not None:
        names["response"] = f"camera response {source}"
    try:
        options = ReconstructOptions(
            cfa=raw.cfa,
            response=response if args.latent == "spectral" else None,
            bands=bands,
            dispersion=args.dispersion,
            correction=args.correction,
            extrapolation=args.extrapolation,
            interpolation=args.interpolation,
            prior=args.prior,
            nonneg=args.nonneg,
            spectral_smoothness=smoothness,
            band_balance=balance,
            weights=args.weights,
            latent=args.latent,
            reference=None if args.reference == "none" else args.reference,
            rtol=rtol,
            exact=True if args.exact else None,
            patch_px=patch_px,
            pad_px=pad_px,
            flat_threshold=FLAT_THRESHOLD,
            scheduler=scheduler,
        )
    except OptionError as error:
        raise ConfigError(error.message(names)) from None
    if args.dispersion is not None:
        try:
            options.check_image(raw.raw.shape, where=f"--dispersion {args.dispersion}")
        except OptionError as error:
            raise ConfigError(error.message(names)) from None
    return _Job(raw=raw, response_source=source, options=options)


def _scheduler(value: str) -> str:
    from reconstruction.patches import probe_scheduler, scheduler_address

    if value in SCHEDULERS:
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


def _positive_float(
    text: str, option: str, *, zero: bool = False, most: float | None = None
) -> float:
    """A finite number > 0 (≥ 0 with `zero`, ≤ `most` if given) from an option's text, or
    a ConfigError."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    bad = not math.isfinite(value) or value < 0 or (value == 0 and not zero)
    if bad or (most is not None and value > most):
        if most is not None:
            low = "[0" if zero else "(0"
            expected = f"a number in {low}, {most:g}] such as {most / 2:g}"
        elif zero:
            expected = "a number ≥ 0 such as 1e-3"
        else:
            expected = "a positive number such as 1e-4"
        raise ConfigError(f"{option} is {text!r}; expected {expected}")
    return value


def _even_int(text: str, option: str, least: int) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < least or value % 2:
        raise ConfigError(f"{option} is {text!r}; expected an even whole number ≥ {least}")
    return value


def _bands(text: str) -> list[float]:
    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) for v in values):
        raise ConfigError(
            f"--bands {text!r}: expected comma-separated wavelengths in nm, "
            "e.g. 400,450,500,550,600,650,700"
        )
    if len(values) < 2 or any(b <= a for a, b in itertools.pairwise(values)):
        raise ConfigError(
            f"--bands {text!r}: give ≥ 2 band centres in increasing order, "
            "e.g. 400,450,500,550,600,650,700"
        )
    return values


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
    sign = "non-negative" if args.nonneg else "signed"
    balance = f" (band balance γ = {log['band_balance']:g})" if log.get("band_balance") else ""
    print(f"reconstructed {rows}×{cols} px → {what}; prior {args.prior}{balance}, {sign}")
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
    elif args.correction == "warp":
        phi = f"solved without Φ, then warped ({log['warp_seconds']:.1f} s, §3.9.2)"
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
    if log.get("spectral_smoothness_chosen"):
        print(f"spectral smoothness: {log['spectral_smoothness_chosen']}")
    for notice in log["warnings"]:
        print(f"warning: {notice}")
    print(f"time: {seconds:.1f} s (weights {weights['seconds']:.1f} s, patches "
          f"{log['solve_seconds']:.1f} s)")  # fmt: skip
    print("wrote " + ", ".join(str(path) for path in paths.values()))
