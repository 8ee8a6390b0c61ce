"""Issue 36, item 9 and the faults class: SIGTERM is an interrupt that leaves no lock and says
so; a standard output that fails is told apart from the run's own files; a file-system error
names its true cause."""
from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchcal.cli.common import report_failure

REPO = Path(__file__).resolve().parents[2]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
SMR = "smr@flange=0,0,0.05"
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _args(data, out, cmd="calibrate"):
    return [sys.executable, "-m", "torchcal", cmd, "--robot", UR5E, "--marker", SMR, "--data", str(data), "--out",
            str(out)]


@pytest.mark.slow
def test_sigterm_is_an_interrupt_that_leaves_nothing(tmp_path, ur5e_csv):
    out = tmp_path / "o"
    p = subprocess.Popen(_args(ur5e_csv, out, "loop"), env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    lock = tmp_path / ".o.torchcal-lock"
    deadline = time.time() + 120
    while not lock.exists() and time.time() < deadline and p.poll() is None:
        time.sleep(0.1)
    assert lock.exists(), "the run never claimed its output"
    time.sleep(2.0)  # into the work
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143 and "terminated (SIGTERM); nothing was written" in err, err
    assert "Traceback" not in err
    assert sorted(x.name for x in tmp_path.iterdir()) == [], "a lock or a temporary folder was left"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system")
def test_a_full_standard_output_is_not_a_failed_run(tmp_path, ur5e_csv):
    out = tmp_path / "o"
    with open("/dev/full", "w") as full:
        r = subprocess.run(_args(ur5e_csv, out), env=ENV, stdout=full, stderr=subprocess.PIPE, text=True, timeout=300)
    assert r.returncode == 74 and "could not write to standard output" in r.stderr, r.stderr
    assert f"the results in {out} are complete" in r.stderr and "nothing was written" not in r.stderr
    assert (out / "calibrated.urdf").is_file() and "Traceback" not in r.stderr


def test_a_file_system_error_names_its_true_cause(capsys):
    long_name = "<robot>" + "x" * 5000
    rc = report_failure("calibrate", OSError(errno.ENAMETOOLONG, "File name too long", long_name), False)
    err = capsys.readouterr().err
    assert rc == 2 and "choose a shorter --out" in err and "free some space" not in err
    assert len(err) < 600  # never a whole file's text
    rc = report_failure("calibrate", OSError(errno.ENOSPC, "No space left on device", "o/x"), False)
    assert rc == 2 and "free some space" in capsys.readouterr().err
    rc = report_failure("calibrate", RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate "
                                                  "8000000000 bytes"), False)
    err = capsys.readouterr().err
    assert rc == 2 and "ran out of memory" in err and "fewer rows" in err and "(a bug)" not in err


def test_a_library_cut_short_by_sigterm_is_the_termination(tmp_path, ur5e_csv, monkeypatch, capsys):
    """SIGTERM that arrives while a compiled library initialises comes out of the import as an
    ``ImportError``: the command still reports the termination (exit 143), not an internal error."""
    import torchcal.cli.app as app
    from torchcal.cli import runtime

    def cut_short(a, argv):
        try:
            runtime._on_sigterm(signal.SIGTERM, None)  # what the handler does when the signal arrives
        except runtime.Terminated:
            pass  # swallowed by the library's initialisation, which fails instead
        raise ImportError("initialization failed")

    monkeypatch.setattr(app, "_calibrate", cut_short)
    rc = app.main(_args(ur5e_csv, tmp_path / "o")[3:])
    err = capsys.readouterr().err
    assert rc == 143 and "terminated (SIGTERM); nothing was written" in err, err
    assert "internal error" not in err and not (tmp_path / "o").exists()
    assert runtime.terminated()
    with runtime.command_runtime():  # the flag is the command's: the next command starts clear
        assert not runtime.terminated()
