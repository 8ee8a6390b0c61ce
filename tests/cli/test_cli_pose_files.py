"""The command line on measured orientations and with the new sizes and priors: a 6-D pose file goes
through ``torchcal loop`` with its orientations used and reported, ``--plausible-mm`` moves the
refusal, and ``--prior none`` / ``--prior cv`` are what ``report.json`` says."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from torchcal.sim.cases import make_case


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "torchcal", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


@pytest.mark.slow
def test_loop_fits_and_reports_orientations_from_a_pose_file(tmp_path):
    c = make_case("pose6d", 0)
    (tmp_path / "robot.urdf").write_text(c.urdf)
    c.train.save_csv(tmp_path / "train.csv")
    c.test.save_csv(tmp_path / "test.csv")
    assert ".qw" in (tmp_path / "train.csv").read_text().splitlines()[0]
    r = _cli("loop", "--robot", "robot.urdf", "--data", "train.csv", "--test", "test.csv", "--marker", c.markers[0],
             "--no-elm", "--out", "out", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    first, last = rep["stages"][0]["test"]["orientation"], rep["stages"][-1]["test"]["orientation"]
    assert last["mean_mrad"] < first["mean_mrad"] and last["n"] == len(c.test)
    assert "Measured orientations, angle error per stage (mrad)" in (tmp_path / "out" / "report.md").read_text()
    # orientations ignored on request: no orientation statistics at all
    r = _cli("loop", "--robot", "robot.urdf", "--data", "train.csv", "--marker", c.markers[0], "--no-elm",
             "--orientation-weight", "0", "--out", "out0", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rep0 = json.loads((tmp_path / "out0" / "report.json").read_text())
    assert "orientation" not in rep0["stages"][-1]["train"]


@pytest.mark.slow
def test_calibrate_prior_and_plausible_sizes_from_the_command_line(tmp_path):
    c = make_case("arm9_mocap", 0)
    (tmp_path / "robot.urdf").write_text(c.urdf)
    c.train.save_csv(tmp_path / "train.csv")
    base = ["calibrate", "--robot", "robot.urdf", "--data", "train.csv", "--marker", c.markers[0]]
    r = _cli(*base, "--prior", "none", "--out", "plain", cwd=tmp_path)
    # 45 rows of a 9-joint arm: without a prior, tied combinations of offsets leave the plausible range
    assert r.returncode == 2 and "plausible" in r.stderr and not (tmp_path / "plain").exists(), r.stderr
    r = _cli(*base, "--prior", "none", "--plausible-mrad", "100", "--out", "wide", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "wide" / "report.json").read_text())["prior_mm"] is None
    r = _cli(*base, "--out", "auto", cwd=tmp_path)  # the default: a CV-chosen prior on these 45 rows
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "auto" / "report.json").read_text())
    assert rep["prior_mm"] is not None and "cross-validation" in rep["prior_reason"]
