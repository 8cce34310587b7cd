"""`labkit bench hdr`: merging a full-size exposure bracket, both weightings, against truth.

Target (issue 4): a 2448×2048 12-bit session of one illumination with 8 exposures × 5
replicates and matching darks (80 frames) merges in ≤ 10 s on 2 cores with a peak
resident memory ≤ 1 GiB. Each merge runs in a fresh process so its peak resident set
(``VmHWM``: numpy, the interpreter and the frame buffers) is measured honestly.
The merged images are compared with the simulator's noise-free signal and with the
Cramér–Rao bound of the captured data (Poisson–Gaussian, darks included), and plotted
as merge time against error (thesis vs noise-aware weights).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from labkit.bench.harness import Measurement, Plot
from labkit.bench.plots import plot_time_vs_error
from labkit.protocol import Engine
from labkit.protocol.hardware import open_hardware
from labkit.rig import Rig, load_rig
from labkit.session import Session

TARGET_S = 10.0
TARGET_RSS_MIB = 1024.0
EXPOSURES_S = [0.0005 * 2**k for k in range(8)]  # 0.5 … 64 ms
REPLICATES = 5
SCENE = "colorchecker"
TIME_ERROR_PNG = "hdr_time_vs_error.png"

_CHILD = """
import json, resource, sys, time
from labkit.hdr import run_hdr
start = time.perf_counter()
run_hdr(sys.argv[1], sys.argv[2], method=sys.argv[3], previews=False)
seconds = time.perf_counter() - start
try:  # VmHWM is this process' own peak; ru_maxrss would inherit the forking parent's
    with open("/proc/self/status") as status:
        rss = next(int(l.split()[1]) for l in status if l.startswith("VmHWM")) / 1024
except (OSError, StopIteration):
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"seconds": seconds, "max_rss_mib": rss}))
"""


def hdr_bench_rig(rig: Rig) -> Rig:
    """The rig with a one-illumination plan: 8 exposures × 5 replicates + darks."""
    return rig.with_changes(
        {
            "plan": {
                "scenes": [SCENE],
                "illuminations": ["unfiltered"],
                "exposures_s": {"unfiltered": EXPOSURES_S},
                "replicates": {"unfiltered": REPLICATES},
                "dark_frames": True,
            }
        }
    )


def bench_hdr(
    rig_path: str | Path, *, repeats: int = 2, out: Path | None = None
) -> tuple[list[Measurement], list[str | Plot]]:
    """Capture the bench session (untimed), then merge it with each method in a subprocess.

    Parameters
    ----------
    rig_path : str or Path
        Rig YAML of the simulated rig.
    repeats : int
        Merges per method (median time reported).
    out : Path, optional
        Report folder: the time-against-error plot is written there.

    Returns
    -------
    cases : list of Measurement
    notes : list of str and Plot
    """
    from labkit.hdr.truth import effective_exposures, merge_truth
    from labkit.io import read_raw_exr
    from labkit.sim import SimulatedRig

    rig = hdr_bench_rig(load_rig(rig_path))
    work = Path(tempfile.mkdtemp(prefix="labkit-bench-hdr-", dir=os.environ.get("TMPDIR")))
    cases: list[Measurement] = []
    notes: list[str | Plot] = []
    try:
        folder = work / "session"
        session = Session.create(folder, rig)
        start = time.perf_counter()
        with open_hardware(rig, fast=True) as hw:
            Engine(rig, hw.camera, hw.slider, hw.stage, session).run()
        session = Session.open(folder)
        frames = len(session.records)
        shape = tuple(next(iter(session.records.values()))["shape"])
        notes.append(
            f"hdr: bench session of {frames} frames {shape[1]}×{shape[0]} "
            f"(captured in {time.perf_counter() - start:.0f} s, not timed)"
        )
        records = list(session.records.values())
        world = SimulatedRig(rig)
        truth = merge_truth(
            world.sensor,
            world.irradiance(SCENE, "unfiltered") * world.sensor.prnu_map,
            effective_exposures(records),
            replicates=REPLICATES,
            darks=REPLICATES,
            saturation_range=records[0]["saturation_dn"] - records[0]["black_level"],
        )
        region = truth.region
        crb = truth.relative_rms_bound()
        for method in ("thesis", "noise"):
            merged = work / method
            runs = [_child(folder, merged, method) for _ in range(max(repeats, 1))]
            times = [r["seconds"] for r in runs]
            rss = max(r["max_rss_mib"] for r in runs)
            seconds = statistics.median(times)
            image = read_raw_exr(merged / SCENE / "unfiltered.exr")
            relative = image.raw[region] / truth.signal[region] - 1
            rms = float(np.sqrt(np.mean(relative**2)))
            factors = image.labkit["exposures"]
            case = Measurement(
                f"hdr merge, {method} weights ({frames} frames)",
                seconds,
                times,
                rss,
                TARGET_S,
                seconds <= TARGET_S and rss <= TARGET_RSS_MIB,
                {
                    "method": method,
                    "peak_rss_mib": rss,
                    "target_rss_mib": TARGET_RSS_MIB,
                    "relative_rms_error": rms,
                    "cramer_rao_relative_rms": crb,
                    "rms_over_crb": rms / crb,
                    "median_relative_error": float(np.median(relative)),
                    "non_finite_pixels": int(np.count_nonzero(~np.isfinite(image.raw))),
                    "properly_exposed_fraction": float(region.mean()),
                    "max_factor_disagreement_vs_nominal": max(
                        abs(f["disagreement"]) for f in factors
                    ),
                },
            )
            cases.append(case)
        notes.append(_verification_note(session, cases[0].seconds))
        notes.append(
            "hdr: memory is the merging process' peak resident set (VmHWM), interpreter "
            "and libraries included; errors are over properly exposed pixels against the "
            "simulator's noise-free signal"
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if out is not None:
        notes.append(time_error_plot(cases, Path(out)))
    return cases, notes


def time_error_plot(cases: list[Measurement], out: Path) -> Plot:
    """Merge time against relative RMS error, thesis vs noise-aware weights, with the bound."""
    plot_time_vs_error(
        {
            f"{case.extra['method']} weights": [
                (case.seconds, case.extra["relative_rms_error"], "")
            ]
            for case in cases
        },
        out / TIME_ERROR_PNG,
        title="labkit hdr: merge time against error (full-size bracket)",
        error_label="relative RMS error vs noise-free signal",
        reference=("Cramér–Rao bound", cases[0].extra["cramer_rao_relative_rms"]),
    )
    return Plot("HDR merge: time against error, thesis vs noise-aware weights", TIME_ERROR_PNG)


def _verification_note(session: Session, merge_s: float) -> str:
    """What checking every frame's recorded sha256 costs, against a merge's time.

    The merge reads each frame once and hashes the bytes it read: the cost is the hashing
    (the read is the merge's own), timed here over the same frames, best of three.
    """
    import hashlib

    blobs = [(session.folder / r["file"]).read_bytes() for r in session.records.values()]
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for blob in blobs:
            hashlib.sha256(blob).hexdigest()
        best = min(best, time.perf_counter() - start)
    mb = sum(len(b) for b in blobs) / 1e6
    return (
        f"hdr: checking each frame's sha256 as it is read costs {best:.2f} s for "
        f"{len(blobs)} frames ({mb:.0f} MB), {100 * best / merge_s:.1f} % of the thesis "
        f"merge's {merge_s:.2f} s"
    )


def _child(session: Path, out: Path, method: str) -> dict[str, Any]:
    result = subprocess.run(
        [sys.executable, "-c", _CHILD, str(session), str(out), method],
        capture_output=True,
        text=True,
        check=False,
    )
    if result.returncode != 0:
        raise RuntimeError(f"hdr bench child failed:\n{result.stderr}")
    return json.loads(result.stdout.strip().splitlines()[-1])
