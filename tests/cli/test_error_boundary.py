"""`labkit` never prints a traceback: expected failures exit 2 with one line, unexpected
ones exit 3 with one line and the traceback in a log file."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys

import pytest

import labkit.cli.rig as rig_cli
from labkit.cli import EXPECTED, UNEXPECTED, main


def _raise(error: BaseException):
    def handler(*args, **kwargs):
        raise error

    return handler


def test_an_unexpected_error_is_one_line_and_a_log_file(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("LABKIT_LOG_DIR", str(tmp_path / "logs"))
    monkeypatch.setattr(rig_cli, "load_rig", _raise(TypeError("a planted bug")))
    status = main(["rig", "check", str(tmp_path / "rig.yaml")])
    err = capsys.readouterr().err
    assert status == UNEXPECTED == 3
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "internal error (TypeError: a planted bug)" in err
    (log,) = (tmp_path / "logs").iterdir()
    assert str(log) in err
    text = log.read_text()
    assert "Traceback" in text and "a planted bug" in text and "rig" in text


@pytest.mark.parametrize(
    ("error", "match"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "/data/out/x.exr"), "disk is full"),
        (PermissionError(errno.EACCES, "Permission denied", "/data/ro"), "permission denied"),
        (OSError(errno.EROFS, "Read-only file system", "/mnt/ro/x"), "read-only"),
        (MemoryError(), "not enough memory"),
    ],
)
def test_system_failures_users_cause_are_expected_errors(
    monkeypatch, tmp_path, capsys, error, match
):
    monkeypatch.setenv("LABKIT_LOG_DIR", str(tmp_path / "logs"))
    monkeypatch.setattr(rig_cli, "load_rig", _raise(error))
    status = main(["rig", "check", str(tmp_path / "rig.yaml")])
    err = capsys.readouterr().err
    assert status == EXPECTED and err.count("\n") == 1 and match in err
    assert "Traceback" not in err and not (tmp_path / "logs").exists()
    if getattr(error, "filename", None):
        assert error.filename in err


def test_an_interrupt_exits_130_after_clean_up(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(rig_cli, "load_rig", _raise(KeyboardInterrupt()))
    assert main(["rig", "check", str(tmp_path / "rig.yaml")]) == 130
    assert capsys.readouterr().err == "labkit: interrupted\n"


@pytest.mark.parametrize("content", [b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", b"\xff" * 64])
def test_a_binary_rig_file_is_a_clear_error(tmp_path, capsys, content):
    rig = tmp_path / "rig.yaml"
    rig.write_bytes(content)
    assert main(["rig", "check", str(rig)]) == EXPECTED
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(rig) in err and "Traceback" not in err


def _labkit(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "labkit", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kwargs,
    )


def test_a_closed_pipe_is_not_a_traceback(sim_rig_path):
    reader_gone = _labkit("rig", "check", str(sim_rig_path))
    reader_gone.stdout.close()  # `labkit … | head -0`: the reader left before any output
    _, err = reader_gone.communicate()
    assert reader_gone.returncode == 141 and err == b""


def test_sigterm_runs_the_clean_up(tmp_path):
    script = (
        "import sys, time\n"
        "from labkit.cli import main\n"
        "import labkit.cli.rig as r\n"
        "from labkit.io.output_folder import staged_output_folder\n"
        "def slow(path):\n"
        "    with staged_output_folder(sys.argv[1], command='t') as stage:\n"
        "        (stage / 'x').write_text('x'); print('staged', flush=True); time.sleep(60)\n"
        "r.load_rig = slow\n"
        "sys.exit(main(['rig', 'check', 'x.yaml']))\n"
    )
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == b"staged"
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143 and err == b"labkit: terminated\n"
    assert list(tmp_path.iterdir()) == []  # staging folder and lock removed, nothing written
