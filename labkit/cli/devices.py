"""``labkit devices``: list the cameras each backend finds and the serial ports."""

from __future__ import annotations

import argparse
import os

from labkit.cli._commands import Commands


def register(commands: Commands) -> None:
    """Add ``labkit devices``."""
    parser = commands.add_parser(
        "devices",
        description="List GigE Vision cameras found by Aravis, GenTL cameras found through each "
        "--cti producer (default: the GENICAM_GENTL64_PATH folders), and serial ports. "
        "--probe asks each port which slider protocol answers (it sends bytes to the ports).",
    )
    parser.add_argument("--cti", action="append", default=[], help="GenTL producer (.cti)")
    parser.add_argument("--probe", action="store_true", help="probe serial ports for sliders")
    parser.set_defaults(handler=_devices)


def _cti_files(given: list[str]) -> list[str]:
    if given:
        return given
    found = []
    for folder in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if folder and os.path.isdir(folder):
            found += [os.path.join(folder, f) for f in os.listdir(folder) if f.endswith(".cti")]
    return sorted(found)


def _devices(args: argparse.Namespace) -> int:
    from labkit.errors import LabkitError

    print("aravis (GigE Vision):")
    try:
        from labkit.devices.aravis import list_devices as aravis_devices

        cameras = aravis_devices()
        for info in cameras:
            print(
                f"  {info.device_id}  {info.vendor} {info.model} serial {info.serial} "
                f"at {info.address}"
            )
        if not cameras:
            print("  (none found)")
    except LabkitError as error:
        print(f"  unavailable: {error}")
    print("genicam (GenTL):")
    ctis = _cti_files(args.cti)
    if not ctis:
        print("  no producer: pass --cti PATH or set GENICAM_GENTL64_PATH")
    for cti in ctis:
        try:
            from labkit.devices.genicam import list_devices as genicam_devices

            cameras = genicam_devices(cti)
            for info in cameras:
                print(
                    f"  {info.device_id}  {info.vendor} {info.model} serial {info.serial} ({cti})"
                )
            if not cameras:
                print(f"  (none found through {cti})")
        except LabkitError as error:
            print(f"  {cti}: {error}")
    print("serial ports:")
    from labkit.devices.serial_ports import list_serial_ports
    from labkit.devices.slider_probe import probe

    ports = list_serial_ports()
    for port in ports:
        line = f"  {port}"
        if args.probe:
            found = probe(port.device)
            line += f"  → {found[0]}: {found[1]}" if found else "  → no slider answered"
        print(line)
    if not ports:
        print("  (none found)")
    print("sim: the simulated rig (rigs/simulated.yaml) is always available")
    return 0
