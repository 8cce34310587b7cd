"""The bad-input and fault suite: every command under bad input, interruption, concurrency,
full and read-only disks, hostile data and degenerate images.

Each case is a :class:`Probe`: it runs one ``labkit`` command on a copy of a small
simulated pipeline (a captured session, its HDR folder, calibrations, a raw image and a
reconstruction) and judges the outcome from the outside:

- the exit status, and that no traceback was printed;
- the state of the outputs afterwards: the previous complete set, the new complete set or
  nothing, never a mix (a labkit run folder is checked against its run manifest);
- that no file outside the outputs changed (every other file's size and sha256).

The verdict of every case is recorded and tabulated per command at the end of the run
(``faults: cases per command and verdict``), and a case passes only when it is "ok".
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
import sys
import textwrap
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from _helpers import QUICK_PLAN, write_rig

from labkit.cli import EXPECTED, main
from labkit.io.output_folder import RUN_MANIFEST, verify_output_folder

#: What a probe may find, worst first; a case passes only with ``ok``.
VERDICTS = (
    "traceback",
    "write outside --out",
    "destroyed result",
    "mixed or partial result",
    "silent wrong result (exit 0)",
    "unclear error",
    "hang",
    "ok",
)

PIPELINE_PLAN = {**QUICK_PLAN, "plan.illuminations": ["unfiltered", "450", "550", "600"]}


def _labkit(*args: object) -> None:
    status = main([str(a) for a in args])
    assert status == 0, f"building the fault pipeline: labkit {' '.join(map(str, args))}"


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory: pytest.TempPathFactory, sim_rig_path: Path) -> Path:
    """A small simulated pipeline, built once: ``rig.yaml``, session ``S``, HDR folder ``H``,
    sensitivity ``C``, dispersion model ``M/model.yaml``, vignetting ``V/v.yaml``, a raw
    frame ``raw.tiff`` and its raw EXR ``raw.exr``, a reconstruction ``R`` and a
    synthesized folder ``Y``. Tests work on copies (see ``workspace``)."""
    root = tmp_path_factory.mktemp("fault-pipeline")
    rig = write_rig(root, sim_rig_path, **PIPELINE_PLAN)
    _labkit("capture", rig, "--session", root / "S", "--yes", "--fast", "--no-progress")
    _labkit("hdr", root / "S", "--out", root / "H", "--no-progress", "--quiet")
    _labkit("calibrate", "sensitivity", root / "H", "--out", root / "C")
    _labkit("calibrate", "dispersion", root / "H", "--reference", "600",
            "--out", root / "M" / "model.yaml")  # fmt: skip
    _labkit("calibrate", "vignetting", root / "H", "--illumination", "600",
            "--out", root / "V" / "v.yaml")  # fmt: skip
    _labkit("sim", "render", rig, "--scene", "colorchecker", "--illumination", "unfiltered",
            "--exposure", "0.003", "--out", root / "raw.tiff")  # fmt: skip
    shutil.copy(root / "H" / "colorchecker" / "unfiltered.exr", root / "raw.exr")
    _labkit("reconstruct", root / "raw.exr", "--rig", rig, "--latent", "colour",
            "--out", root / "R", "--quiet")  # fmt: skip
    _labkit("synthesize", root / "H", "--sensitivity", root / "C" / "sensitivity.csv",
            "--out", root / "Y")  # fmt: skip
    return root


@pytest.fixture
def workspace(pipeline: Path, tmp_path: Path) -> Path:
    """A private copy of the pipeline."""
    work = tmp_path / "w"
    shutil.copytree(pipeline, work, symlinks=True)
    return work


# -- judging an outcome ------------------------------------------------------------------------
def snapshot(root: Path, *, skip: Sequence[Path] = ()) -> dict[str, tuple[int, str]]:
    """Every file under `root` (hidden ones included) but those in or named `skip`:
    relative path → (size, sha256)."""
    skipped = [Path(os.path.realpath(s)) for s in skip]
    # an output's own lock file and staging folders (a killed run's) belong to it
    beside = [s.parent / f".{s.name}." for s in skipped]
    state: dict[str, tuple[int, str]] = {}
    for path in sorted(root.rglob("*")):
        real = Path(os.path.realpath(path))
        if path.is_dir() or any(real == s or s in real.parents for s in skipped):
            continue
        if any(str(real).startswith(str(b)) for b in beside):
            continue
        data = path.read_bytes() if path.is_file() else b""
        state[str(path.relative_to(root))] = (len(data), hashlib.sha256(data).hexdigest())
    return state


def tree(path: Path) -> dict[str, tuple[int, str]] | None:
    """The state of one output (a file or folder), ``None`` when absent."""
    if not path.exists():
        return None
    if path.is_file():
        data = path.read_bytes()
        return {".": (len(data), hashlib.sha256(data).hexdigest())}
    return snapshot(path)


def leftovers(folder: Path) -> list[str]:
    """Hidden staging folders, ``.part`` files and lock files anywhere under `folder`."""
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob(".*")
        if ".staging-" in p.name or p.name.endswith((".part", ".lock"))
    )


@dataclass
class Outcome:
    status: int
    out: str
    err: str
    verdict: str
    why: str = ""
    outputs: dict[str, dict | None] = field(default_factory=dict)


@dataclass
class Probe:
    """Runs one case and records its verdict (see the module docstring)."""

    workspace: Path
    capsys: pytest.CaptureFixture[str]
    request: pytest.FixtureRequest
    command: str = ""
    kind: str = ""

    def case(self, command: str, kind: str) -> Probe:
        """Name the case: the command (``hdr``, ``calibrate sensitivity``…) and the class."""
        self.command, self.kind = command, kind
        return self

    def run(
        self,
        args: Sequence[object],
        *,
        outputs: Sequence[Path] = (),
        expect: str = "error",
        mentions: Sequence[str] = (),
        extra_ok: Sequence[Path] = (),
    ) -> Outcome:
        """Run ``labkit *args`` in this process and judge it.

        `expect` is ``"error"`` (exit 2, one line naming each of `mentions`; every output as
        before) or ``"ok"`` (exit 0; each output a complete set). `extra_ok` are paths the
        command may legitimately change besides `outputs` (e.g. a session it resumes).
        """
        outputs = [Path(p) for p in outputs]
        watched = [*outputs, *extra_ok]
        before = snapshot(self.workspace, skip=watched)
        outputs_before = {str(p): tree(p) for p in outputs}
        self.capsys.readouterr()
        status = main([str(a) for a in args])
        printed = self.capsys.readouterr()
        after = snapshot(self.workspace, skip=watched)
        outcome = Outcome(status, printed.out, printed.err, "ok")
        outcome.outputs = {str(p): tree(p) for p in outputs}
        outcome.verdict, outcome.why = self._judge(
            outcome, before, after, outputs, outputs_before, expect, mentions
        )
        return self._record(outcome)

    def _judge(self, outcome, before, after, outputs, outputs_before, expect, mentions):
        text = outcome.out + outcome.err
        if "Traceback" in text or outcome.status not in (0, EXPECTED):
            return "traceback", f"status {outcome.status}: {outcome.err[-400:]}"
        changed = sorted(set(before.items()) ^ set(after.items()))
        changed = [c for c in changed if not c[0].endswith(".lock")]
        if changed:
            return "write outside --out", f"changed: {sorted({c[0] for c in changed})[:5]}"
        if expect == "error":
            if outcome.status == 0:
                return "silent wrong result (exit 0)", outcome.out[-400:]
            for path in outputs:
                if outcome.outputs[str(path)] != outputs_before[str(path)]:
                    lost = outputs_before[str(path)] is not None
                    verdict = "destroyed result" if lost else "mixed or partial result"
                    return verdict, f"{path} changed on a failed run"
            lines = [
                line
                for line in outcome.err.strip().splitlines()
                if not line.startswith(("usage:", " "))  # argparse prints its usage first
            ]
            missing = [m for m in mentions if m not in outcome.err]
            if len(lines) != 1 or missing:
                return "unclear error", f"{outcome.err!r} lacks {missing}"
        else:
            if outcome.status != 0:
                return "silent wrong result (exit 0)", f"expected success: {outcome.err}"
            for path in outputs[:1] + [p for p in outputs[1:] if p.exists()]:
                problem = complete_problem(path)
                if problem:
                    return "mixed or partial result", problem
        return "ok", ""

    def _record(self, outcome: Outcome) -> Outcome:
        assert self.command and self.kind, "name the case with probe.case(command, kind)"
        self.request.node.user_properties.append(
            ("fault", (self.command, self.kind, outcome.verdict))
        )
        return outcome

    def killed(self, args: Sequence[object], *, at: str, when: str = "after", n: int = 1) -> None:
        """Run ``labkit *args`` killed with SIGKILL at a chosen point (:func:`run_killed`);
        a run the kill did not reach fails the case."""
        result = run_killed(args, at=at, when=when, n=n)
        if result.returncode != -9:
            self.judge_external("traceback", f"not killed: {result.returncode} {result.stderr}")

    def killed_over(
        self,
        folder: Path,
        args: Sequence[object],
        *,
        at: str,
        when: str = "after",
        n: int = 1,
        is_new: Callable[[Path], bool],
    ) -> None:
        """:meth:`killed` for a run replacing the output `folder`, which must then hold the
        previous set (unchanged) or the new one (`is_new`), never a mix."""
        previous = snapshot(folder)
        self.killed(args, at=at, when=when, n=n)
        if snapshot(folder) != previous and not is_new(folder):
            self.judge_external("mixed or partial result", f"{folder} changed, not the new set")

    def judge_external(self, verdict: str, why: str = "") -> None:
        """Record a verdict reached outside :meth:`run` (subprocess cases)."""
        self.request.node.user_properties.append(("fault", (self.command, self.kind, verdict)))
        assert verdict == "ok", why


def complete_problem(path: Path) -> str:
    """Why `path` is not a complete output set, or ``""``."""
    if not path.exists():
        return f"{path} was not written"
    if path.is_dir() and (path / RUN_MANIFEST).is_file():
        try:
            verify_output_folder(path, what="output", rerun="rerun")
        except Exception as error:
            return str(error)
    left = [name for name in leftovers(path.parent) if name.startswith(f".{path.name}.")]
    if left:
        return f"left behind: {left}"
    return ""


@pytest.fixture
def probe(workspace: Path, capsys, request) -> Probe:
    return Probe(workspace, capsys, request)


def ok(outcome: Outcome) -> None:
    """Assert a probe's verdict (with its reason)."""
    assert outcome.verdict == "ok", f"{outcome.verdict}: {outcome.why}"


# -- subprocess runs: kill -9 at a chosen point, a second writer -------------------------------
#: Where a run writing a staged output folder can be killed (labkit.io.output_folder).
FOLDER_KILL_POINTS = {
    "before the run manifest": ("labkit.io.output_folder:_manifest", "before", 1),
    "before the swap": ("labkit.io.output_folder:_put_in_place", "before", 1),
    "right after the swap": ("labkit.io.output_folder:_put_in_place", "after", 1),
}

_KILLER = textwrap.dedent(
    """
    import importlib, os, signal, sys
    module, attribute, when, n = sys.argv[1:5]
    target = importlib.import_module(module)
    *owners, attribute = attribute.split(".")  # "Class.method" patches the class
    for owner in owners:
        target = getattr(target, owner)
    original = getattr(target, attribute)
    calls = [0]
    def killer(*args, **kwargs):
        calls[0] += 1
        if when == "before" and calls[0] >= int(n):
            os.kill(os.getpid(), signal.SIGKILL)
        result = original(*args, **kwargs)
        if when == "after" and calls[0] >= int(n):
            os.kill(os.getpid(), signal.SIGKILL)
        return result
    setattr(target, attribute, killer)
    from labkit.cli import main
    sys.exit(main(sys.argv[5:]))
    """
)


def run_killed(
    args: Sequence[object], *, at: str, when: str = "after", n: int = 1, timeout: float = 120
) -> subprocess.CompletedProcess:
    """Run ``labkit *args`` in a subprocess killed with SIGKILL ``when`` ("before"/"after")
    the `n`-th call of `at` (``"module:function"``, patched in the module that calls it)."""
    module, attribute = at.split(":")
    return subprocess.run(
        [sys.executable, "-c", _KILLER, module, attribute, when, str(n), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=Path(__file__).parents[2],
    )


_HOLDER = textwrap.dedent(
    """
    import sys, time
    from labkit.io.output_folder import writer_lock
    with writer_lock(sys.argv[1], command="labkit test-holder"):
        print("held", flush=True)
        time.sleep(120)
    """
)


@contextlib.contextmanager
def another_writer(target: Path) -> Iterator[subprocess.Popen]:
    """Another process holding `target`'s writer lock for the block."""
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(target)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        holder.kill()
        holder.wait()


# -- full and read-only file systems -----------------------------------------------------------
def _mount(*args: str) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    result = subprocess.run(["mount", *args], capture_output=True)
    return result.returncode == 0


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real 1 MiB tmpfs (skipped where this machine may not mount one; the simulated-ENOSPC
    cases cover such machines)."""
    mount = tmp_path / "small-disk"
    mount.mkdir()
    if not _mount("-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)):
        pytest.skip("cannot mount a tmpfs here (needs root and mount rights)")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@contextlib.contextmanager
def read_only(folder: Path) -> Iterator[None]:
    """Make `folder` read-only for the block: a read-only bind mount where this machine
    allows it (root ignores permission bits), else ``chmod a-w`` (non-root)."""
    if os.geteuid() != 0:
        modes = {p: p.stat().st_mode for p in [folder, *folder.rglob("*")] if p.is_dir()}
        for p in modes:
            p.chmod(modes[p] & ~0o222)
        try:
            yield
        finally:
            for p, mode in modes.items():
                p.chmod(mode)
        return
    if not (_mount("--bind", str(folder), str(folder))):
        pytest.skip("cannot bind-mount read-only here")
    try:
        if not _mount("-o", "remount,bind,ro", str(folder)):
            pytest.skip("cannot remount read-only here")
        yield
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


# -- the verdict table -------------------------------------------------------------------------
def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    table: Counter[tuple[str, str]] = Counter()
    kinds: dict[str, set[str]] = {}
    for reports in terminalreporter.stats.values():
        for report in reports:
            if getattr(report, "when", None) != "call":
                continue
            found = [v for name, v in getattr(report, "user_properties", ()) if name == "fault"]
            if not found:
                continue
            command, kind, _ = found[0]  # one case per test: its worst verdict
            verdict = min((v[2] for v in found), key=VERDICTS.index)
            if report.failed and verdict == "ok":
                verdict = "unclear error"  # an assertion of the test itself failed
            table[command, verdict] += 1
            kinds.setdefault(command, set()).add(kind)
    if not table:
        return
    verdicts = [v for v in VERDICTS if any(v == k[1] for k in table)]
    terminalreporter.write_sep("-", "faults: cases per command and verdict")
    terminalreporter.write_line(
        f"{'command':<24}{'cases':>6}  " + "  ".join(f"{v}" for v in verdicts) + "  classes"
    )
    for command in sorted(kinds):
        counts = [table[command, v] for v in verdicts]
        cells = "  ".join(f"{c:>{len(v)}}" for c, v in zip(counts, verdicts, strict=True))
        terminalreporter.write_line(
            f"{command:<24}{sum(counts):>6}  {cells}  {', '.join(sorted(kinds[command]))}"
        )
    total = [sum(table[c, v] for c in kinds) for v in verdicts]
    cells = "  ".join(f"{c:>{len(v)}}" for c, v in zip(total, verdicts, strict=True))
    terminalreporter.write_line(f"{'all':<24}{sum(total):>6}  {cells}")
