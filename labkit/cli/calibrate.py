"""``labkit calibrate …``: calibrations computed from HDR images.

``labkit calibrate sensitivity HDR_DIR --out DIR``
    relative channel sensitivity per filter band (thesis Algorithm 12), compared with
    what the rig's camera response predicts.
``labkit calibrate vignetting HDR_DIR --scene disks --illumination 600 --out V.yaml``
    a polynomial model of intensity fall-off (thesis §3.2.2).
``labkit calibrate dispersion HDR_DIR --scene disks --reference 600 --out MODEL.yaml``
    a polynomial or thin-plate spline model of lateral chromatic aberration (§3.2).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from labkit.cli._commands import Commands
from labkit.cli._options import fraction, non_negative_int


def register(commands: Commands) -> None:
    """Add ``labkit calibrate …``."""
    parser = commands.add_parser(
        "calibrate",
        description="Calibrations computed from the HDR images written by `labkit hdr`.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    sensitivity = actions.add_parser(
        "sensitivity",
        help="R/G and B/G sensitivity ratios per filter band",
        description="Fit the ratios between neighbouring Green–Red and Green–Blue pixels in "
        "textureless, unsaturated regions of every filtered-light HDR image (first principal "
        "component, all scenes of a band pooled). Writes DIR/sensitivity.csv, "
        "DIR/sensitivity.yaml and DIR/sensitivity.png (measured vs the rig's camera response), "
        "and prints a table. Ratios resting on too few pairs or on a channel without signal "
        "are marked unreliable.",
    )
    sensitivity.add_argument(
        "hdr", type=Path, help="HDR folder from `labkit hdr` (DIR/<scene>/<illumination>.exr)"
    )
    sensitivity.add_argument("--out", type=Path, required=True, help="output folder")
    sensitivity.add_argument(
        "--scene",
        action="append",
        metavar="NAME",
        help="use only this scene (repeatable; default: every scene)",
    )
    sensitivity.add_argument(
        "--rig",
        default=None,
        help="rig YAML whose camera response, filters and light give the nominal ratios "
        "(default: the rig of the session the HDR images were merged from, else the "
        "simulated rig)",
    )
    sensitivity.add_argument(
        "--saturation",
        type=fraction,
        default=0.95,
        help="ignore pixels at or above this fraction of saturation, in (0, 1] (default 0.95)",
    )
    sensitivity.set_defaults(handler=_sensitivity)
    _register_vignetting(actions)
    _register_dispersion(actions)


def _register_vignetting(actions: argparse._SubParsersAction) -> None:
    parser = actions.add_parser(
        "vignetting",
        help="intensity fall-off model",
        description="Fit a bivariate polynomial (degree 0–5 by 10-fold cross-validation, "
        "normalised coordinates and intensities) to the Green pixels of one HDR image inside "
        "a mask: a user mask, or the paper background of the disk pattern when no mask is "
        "given (else the whole image). Writes the model (YAML) and a PNG of the fitted "
        "fall-off next to it.",
    )
    parser.add_argument("hdr", type=Path, help="HDR folder from `labkit hdr`")
    parser.add_argument("--scene", default="disks", help="scene to use (default: disks)")
    parser.add_argument(
        "--illumination", default="600", help="illumination (image) to fit (default: 600)"
    )
    parser.add_argument(
        "--mask",
        type=Path,
        default=None,
        help="mask image (PNG/TIFF/.npy, same size as the raw image; non-zero = uniform region)",
    )
    parser.add_argument("--max-degree", type=int, default=5, help="highest degree (default 5)")
    parser.add_argument("--out", type=Path, required=True, help="model YAML to write")
    parser.set_defaults(handler=_vignetting)


def _register_dispersion(actions: argparse._SubParsersAction) -> None:
    parser = actions.add_parser(
        "dispersion",
        help="lateral chromatic aberration model",
        description="Find keypoints (disk centres or patch-wise registration) in the HDR "
        "images of one scene and fit a dispersion model: a trivariate model in (x, y, λ) "
        "between filter bands, or with --reference G bivariate models of the Red and Blue "
        "channels relative to Green in the unfiltered image. Keypoints are labelled with "
        "each band's effective wavelength (filter × light × camera, from the rig) and bands "
        "dominated by out-of-band leakage are left out. Writes MODEL.yaml, "
        "MODEL.keypoints.csv, MODEL.png (dispersion per band like the thesis' Figure 5.3) "
        "and MODEL.residuals.png.",
    )
    parser.add_argument("hdr", type=Path, help="HDR folder from `labkit hdr`")
    parser.add_argument("--scene", default="disks", help="scene to use (default: disks)")
    parser.add_argument(
        "--reference",
        default="600",
        help="reference band: illumination name or nominal wavelength (nm), or G for a "
        "colour-channel model (default: 600)",
    )
    parser.add_argument("--model", choices=["polynomial", "spline"], default="polynomial")
    parser.add_argument("--keypoints", choices=["disks", "registration"], default="disks")
    parser.add_argument(
        "--direction",
        choices=["from_reference", "to_reference"],
        default="from_reference",
        help="from_reference maps reference positions to band positions (warping); "
        "to_reference maps band positions back (image formation); default from_reference",
    )
    parser.add_argument(
        "--wavelengths",
        choices=["effective", "nominal"],
        default="effective",
        help="label bands by their effective wavelength (needs the rig) or by the filters' "
        "nominal centres (default: effective)",
    )
    parser.add_argument(
        "--rig",
        type=Path,
        default=None,
        help="rig YAML for effective wavelengths (default: the rig of the session the HDR "
        "images were merged from)",
    )
    parser.add_argument(
        "--min-purity",
        type=fraction,
        default=None,
        help="leave out bands with less in-band signal than this fraction (default 0.8); "
        "the fraction is measured from the images (their brightness against the leakage the "
        "rig predicts), so a stand-in camera response cannot drop a band the camera sees well",
    )
    parser.add_argument(
        "--vignetting",
        choices=["none", "auto"],
        default="none",
        help="auto: correct each image for vignetting before finding keypoints",
    )
    parser.add_argument("--workers", type=int, default=None, help="processes for disk fits")
    parser.add_argument(
        "--seed", type=non_negative_int, default=2019, help="cross-validation seed, ≥ 0"
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument(
        "--target",
        type=Path,
        default=None,
        help="the chart.yaml of `labkit target`: say whether the shot's disks measure the "
        "radius and pitch the chart was made for (else the camera stands at another "
        "distance than the chart's)",
    )
    parser.add_argument("--out", type=Path, required=True, help="model YAML to write")
    parser.set_defaults(handler=_dispersion)


def _sensitivity(args: argparse.Namespace) -> int:
    from calibration import (
        channel_sensitivity,
        load_filtered_hdr,
        nominal_channel_sensitivity,
        plot_channel_sensitivity,
    )
    from labkit.io.output_folder import check_output_folder, staged_output_folder

    check_output_folder(args.out, command="labkit calibrate sensitivity", inputs=[args.hdr])
    scenes = load_filtered_hdr(args.hdr, scenes=args.scene)
    images = [image for group in scenes.values() for image in group]
    rig = _images_rig(args.rig, images, default=True, response=True)
    measured = channel_sensitivity(images, saturation=args.saturation)
    nominal = nominal_channel_sensitivity(rig)
    names = [f"sensitivity.{suffix}" for suffix in ("csv", "yaml", "png")]
    with staged_output_folder(
        args.out, command="labkit calibrate sensitivity", inputs=[args.hdr]
    ) as stage:
        measured.to_csv(stage / names[0])
        measured.to_yaml(stage / names[1])
        plot_channel_sensitivity(measured, nominal, stage / names[2])
    paths = [args.out / name for name in names]
    print(f"{len(images)} image(s) of {len(scenes)} scene(s) {sorted(scenes)}; "
          f"nominal ratios from {rig.source or rig.name}")  # fmt: skip
    print(sensitivity_table(measured, nominal))
    print("wrote " + ", ".join(str(path) for path in paths))
    return 0


def sensitivity_table(measured, nominal) -> str:
    """Measured vs nominal ratios per band, and the relative Green level, as aligned text."""
    header = (
        f"{'band':>8}  {'R/G':>9} {'nominal':>9} {'diff':>8}  "
        f"{'B/G':>9} {'nominal':>9} {'diff':>8}  {'level':>9}  reliable"
    )
    lines = [header]
    for i, wavelength in enumerate(measured.wavelengths_nm):
        entry = None if nominal is None else nominal.index_of(wavelength)
        cells = []
        for key in ("r", "b"):
            value = float(getattr(measured, f"{key}_over_g")[i])
            expected = math.nan
            if entry is not None:
                expected = float(getattr(nominal, f"{key}_over_g")[entry])
            diff = 100 * (value / expected - 1) if expected > 0 else math.nan
            cells.append(f"{_number(value)} {_number(expected)} {_percent(diff)}")
        reasons = [reason for reason in (measured.reason_r[i], measured.reason_b[i]) if reason]
        reliable = "yes"
        if not measured.reliable[i]:
            reliable = f"no ({'; '.join(reasons)})" if reasons else "no"
        level = _number(float(measured.relative_green_level[i]))
        lines.append(f"{wavelength:>5.1f} nm  {cells[0]}  {cells[1]}  {level}  {reliable}")
    return "\n".join(lines)


def _number(value: float) -> str:
    return f"{'—':>9}" if not math.isfinite(value) else f"{value:>9.4g}"


def _percent(value: float) -> str:
    return f"{'—':>8}" if not math.isfinite(value) else f"{value:>+7.1f}%"


def _vignetting(args: argparse.Namespace) -> int:
    from calibration import load_scene_hdr, source_of
    from calibration.disks import background_mask
    from calibration.plots import plot_vignetting
    from calibration.vignetting import fit_vignetting
    from labkit.errors import DataError
    from labkit.io.output_folder import check_output_files, staged_output_files

    plot = args.out.with_suffix(".png")
    check_output_files([args.out, plot])
    images = {image.illumination: image for image in load_scene_hdr(args.hdr, args.scene)}
    if args.illumination not in images:
        raise DataError(
            f"scene {args.scene!r} in {args.hdr} has no {args.illumination!r} image; "
            f"available: {sorted(images)}"
        )
    image = images[args.illumination]
    name = source_of(image)
    if args.mask is not None:
        mask, origin = read_mask(args.mask), f"mask {args.mask}"
        if mask.shape != image.raw.shape:
            rows, cols = image.raw.shape
            raise DataError(
                f"--mask {args.mask} has shape {mask.shape} but the image it masks, {name}, "
                f"has shape {image.raw.shape} (rows, cols); give a mask of the raw image's "
                f"size, {cols}×{rows} px"
            )
    else:
        try:
            mask, origin = background_mask(image.raw, cfa=image.cfa), "disk-pattern background"
        except DataError:
            mask, origin = None, "whole image"
    model = fit_vignetting(
        image.raw, cfa=image.cfa, mask=mask, max_degree=args.max_degree, name=name
    )
    with staged_output_files([args.out, plot], command="labkit calibrate vignetting") as staged:
        model.save(staged[0])
        plot_vignetting(model, staged[1])
    print(f"{name}: fitted on the {origin}; degree {model.degree} by 10-fold cross-validation")
    print(f"wrote {args.out} and {plot}")
    return 0


def read_mask(path: Path):
    """A boolean mask from a PNG/TIFF/.npy file (non-zero = True)."""
    from labkit.errors import DataError
    from labkit.io.plane import read_plane

    data = read_plane(path, what="mask")
    if data.ndim == 3:
        data = data[..., :3].max(axis=2)
    if data.ndim != 2:
        raise DataError(f"mask {path} must be a 2-D image, got shape {data.shape}")
    return data != 0


def _check_against_chart(target: Path, images: list, reference: str) -> None:
    """Print how the reference image's disks measure against the chart's design, and a
    warning that says what to do where they are off."""
    from calibration.disks.chart import check_shot, load_chart_yaml

    design = load_chart_yaml(target)
    wanted = "unfiltered" if reference.upper() in ("R", "G", "B") else reference
    image = next((i for i in images if i.illumination == wanted), images[0])
    check = check_shot(image.raw, design, cfa=image.cfa, name=f"{image.illumination} image")
    print(check.describe())
    if check.problem:
        print(f"warning: {check.problem}")


def _dispersion(args: argparse.Namespace) -> int:
    import numpy as np

    from calibration import load_scene_hdr
    from calibration.dispersion_calibration import (
        MIN_PURITY,
        band_table,
        calibrate_dispersion,
        summary,
    )
    from calibration.plots import plot_keypoint_residuals, plot_model
    from labkit.io.output_folder import check_output_files, staged_output_files

    outputs = [args.out, *(args.out.with_suffix(s) for s in _DISPERSION_COMPANIONS)]
    check_output_files(outputs)
    images = load_scene_hdr(args.hdr, args.scene)
    colour = args.reference.upper() in ("R", "G", "B")
    bands = None
    if not colour and args.wavelengths == "effective":
        bands = _rig_bands(args.rig, images)
    result = calibrate_dispersion(
        images,
        reference=args.reference,
        model=args.model,
        keypoints=args.keypoints,
        direction=args.direction,
        bands=bands,
        min_purity=MIN_PURITY if args.min_purity is None else args.min_purity,
        vignetting=args.vignetting,
        rng=np.random.default_rng(args.seed),
        workers=args.workers,
        progress=lambda message: print(message, flush=True),
    )
    print(band_table(result))
    for warning in result.warnings:
        print(f"warning: {warning}")
    if args.target is not None:
        _check_against_chart(args.target, images, args.reference)
    with staged_output_files(outputs, command="labkit calibrate dispersion") as staged:
        result.model.save(staged[0])
        result.keypoints.to_csv(staged[1])
        if not args.no_plots:  # an earlier run's plots are removed
            plot_model(result.model, staged[2])
            plot_keypoint_residuals(result.model, result.keypoints, staged[3])
    written = [path for path in outputs if path.exists()]
    print(f"{len(result.keypoints)} keypoints; model: " + ", ".join(
        f"{key} {value:.3g}" if isinstance(value, float) else f"{key} {value}"
        for key, value in summary(result).items()
    ))  # fmt: skip
    print("wrote " + ", ".join(str(path) for path in written))
    return 0


_DISPERSION_COMPANIONS = (".keypoints.csv", ".png", ".residuals.png")
"""What `labkit calibrate dispersion --out MODEL.yaml` writes beside the model."""


def _rig_bands(rig_path: Path | None, images) -> dict:
    """Effective band wavelengths, measured from the images with the rig's filters and light."""
    from calibration.bands import filter_bands

    rig = _images_rig(rig_path, images, hint="pass --rig RIG.yaml or --wavelengths nominal")
    return filter_bands(rig, images=images)


def _images_rig(
    rig_path: Path | None,
    images,
    *,
    default: bool = False,
    response: bool = False,
    hint: str = "pass --rig RIG.yaml",
):
    """The rig of --rig, else that of the session the HDR images were merged from.

    With `default`, images that name no readable session get the simulated rig. With
    `response`, the caller reads the camera response: a response file that a session's rig
    snapshot names is followed only inside the session's folder.
    """
    from labkit.errors import DataError
    from labkit.rig import default_rig_path, load_rig
    from labkit.session import SESSION_FILE, Session

    if rig_path is not None:
        return load_rig(rig_path)
    sessions = {image.labkit.get("session") for image in images} - {None}
    for session in sorted(sessions):
        if not (Path(session) / SESSION_FILE).is_file():
            continue  # moved or deleted since the merge: look further
        rig = Session.open(session).rig  # a damaged session is an error, not the default rig
        if response:
            _check_snapshot_response(rig, Path(session))
        return rig
    if default:
        return load_rig(default_rig_path())
    raise DataError(
        "this needs the rig, but the HDR images name no readable session "
        f"({', '.join(sorted(sessions)) or 'none recorded'}); {hint}"
    )


def _check_snapshot_response(rig, session: Path) -> None:
    """Refuse a session's rig snapshot whose response file lies outside the session: a
    session's contents are data, and a path in them is not followed out of its folder."""
    from labkit.errors import DataError

    file = rig.response_file()
    if file is not None and not file.resolve().is_relative_to(session.resolve()):
        value = rig.camera.response
        raise DataError(
            f"{rig.source}: rig.camera.response {value!r} lies outside the session {session}, "
            "and a session's contents are not followed outside its folder; pass --rig "
            "RIG.yaml, the rig file the session was captured with"
        )
