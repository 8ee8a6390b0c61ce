"""Issue 36, items 4, 9, 10 and the faults class; issue 35 §2 "files another user can read":
torchcal replaces only what it wrote, never a special file, cleans what a killed run left, takes
over a stale lock, and writes with the user's umask."""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest

from torchcal.outputs import atomic_write_text, claim, staged_dir
from torchcal.outputs_manifest import MANIFEST

REPO = Path(__file__).resolve().parents[2]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
SMR = "smr@flange=0,0,0.05"


def _calibrate(cli, data: Path, out, *extra):
    return cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", data, "--out", out, *extra)


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".partial" in p.name or ".replaced" in p.name
                  or p.name.endswith("-lock"))


@pytest.mark.slow
def test_force_replaces_only_what_torchcal_wrote(tmp_path, torchcal_cli, ur5e_csv):
    out = tmp_path / "o"
    assert _calibrate(torchcal_cli, ur5e_csv, out)[0] == 0
    listed = set(json.loads((out / MANIFEST).read_text())["files"])
    assert "calibrated.urdf" in listed and "run.yaml" in listed
    (out / "notes.txt").write_text("mine")
    rc, _, err = _calibrate(torchcal_cli, ur5e_csv, out, "--force")
    assert rc == 0 and "notes.txt" in err and "kept" in err, err
    assert (out / "notes.txt").read_text() == "mine" and (out / "calibrated.urdf").is_file()
    assert _hidden(tmp_path) == []


def test_a_file_made_while_a_run_writes_is_kept(tmp_path):
    out = tmp_path / "o"
    with staged_dir(out) as d:
        (d / "result.txt").write_text("torchcal's")
        out.mkdir()  # the user makes the folder and puts a file in it while the run works
        (out / "notes.txt").write_text("mine")
    assert (out / "notes.txt").read_text() == "mine" and (out / "result.txt").read_text() == "torchcal's"
    assert _hidden(tmp_path) == []


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_a_fifo_or_a_device_is_never_replaced(tmp_path, torchcal_cli):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for target in (fifo, Path(os.devnull)):
        rc, _, err = torchcal_cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out", target, "--force")
        assert rc == 2 and ("a FIFO" in err or "a device node" in err) and "not even when forced" in err, err
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and stat.S_ISCHR(os.stat(os.devnull).st_mode)


def test_a_symlink_loop_as_out_is_refused(tmp_path, torchcal_cli, ur5e_csv):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    for out in (tmp_path / "a", tmp_path / "a" / "sub"):
        rc, _, err = _calibrate(torchcal_cli, ur5e_csv, out)
        assert rc == 2 and "loops" in err and "(a bug)" not in err, err


def test_leftovers_of_a_killed_run_and_stale_locks_are_cleaned_and_said(tmp_path, torchcal_cli):
    dead = 2 ** 22 + 12345  # above Linux's default pid_max: no such process
    (tmp_path / f".s.csv.abc.{dead}.partial").write_text("half")
    (tmp_path / f".o.x1y2.{dead}.partial").mkdir()
    (tmp_path / f".o.replaced-{dead}").mkdir()
    (tmp_path / ".s.csv.torchcal-lock").write_text(f"{dead}\n")
    rc, _, err = torchcal_cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out", tmp_path / "s.csv")
    assert rc == 0 and "stale lock" in err and "removed what an interrupted run left" in err, err
    with staged_dir(tmp_path / "o") as d:
        (d / "x.txt").write_text("x")
    assert _hidden(tmp_path) == []
    # a lock that holds this very process's id, not taken by it (a restarted container), is stale
    (tmp_path / ".t.csv.torchcal-lock").write_text(f"{os.getpid()}\n")
    rc, _, err = torchcal_cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out", tmp_path / "t.csv")
    assert rc == 0 and "own process id" in err, err
    with claim(tmp_path / "u.csv"):  # but one this process holds is live
        rc, _, err = torchcal_cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out",
                                  tmp_path / "u.csv")
        assert rc == 2 and "another torchcal run" in err, err


@pytest.mark.parametrize("mask, folder, file", [(0o022, 0o755, 0o644), (0o077, 0o700, 0o600), (0o002, 0o775, 0o664)])
def test_results_follow_the_umask(tmp_path, torchcal_cli, mask, folder, file):
    old = os.umask(mask)
    try:
        out = tmp_path / "o"
        with staged_dir(out) as d:  # a result folder, as calibrate, loop and save write it
            atomic_write_text(d / "run.yaml", "a: 1\n")
            (d / "model").mkdir()
            (d / "model" / "model.json").write_text("{}")
        rc, _, err = torchcal_cli("simulate", "--robot", UR5E, "--marker", SMR, "--poses", 5, "--out", tmp_path / "s.csv")
        assert rc == 0, err
    finally:
        os.umask(old)
    for d in (out, out / "model"):
        assert stat.S_IMODE(d.stat().st_mode) == folder, d
    for f in (out / "run.yaml", out / "provenance.json", out / "model" / "model.json", tmp_path / "s.csv"):
        assert stat.S_IMODE(f.stat().st_mode) == file, f


def test_a_result_written_before_manifests_is_replaced_whole(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "provenance.json").write_text(json.dumps({"torchcal": "0.0.1"}))
    (out / "old.txt").write_text("an earlier torchcal's file")
    with staged_dir(out, force=True) as d:
        (d / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir() if p.name != MANIFEST) == ["new.txt", "provenance.json"]
