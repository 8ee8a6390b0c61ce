"""``run.yaml`` repeats its run: paths relative to its folder (the tree may move), no output of its
own, and a repeat without a new ``--out`` is told so in one line (issue 35 §2)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from torchcal.cli.app import main

UR5E = Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf"


pytestmark = pytest.mark.slow  # one calibration to repeat (about 8 s on two shared cores)


@pytest.fixture(scope="module")
def cell(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("run") / "work"
    (work / "urdf").mkdir(parents=True)
    shutil.copy(UR5E, work / "urdf" / "ur5e.urdf")
    assert main(["simulate", "--robot", str(work / "urdf" / "ur5e.urdf"), "--marker", "flange", "--poses", "30",
                 "--seed", "2", "--out", str(work / "d.csv"), "--quiet"]) == 0
    assert main(["calibrate", "--robot", str(work / "urdf" / "ur5e.urdf"), "--data", str(work / "d.csv"),
                 "--marker", "flange", "--holdout", "0.2", "--out", str(work / "cell1"), "--quiet"]) == 0
    return work


def test_run_yaml_holds_relative_paths_and_no_output(cell):
    run = yaml.safe_load((cell / "cell1" / "run.yaml").read_text())
    assert "out" not in run
    assert run["robot"] == str(Path("..") / "urdf" / "ur5e.urdf") and run["data"] == str(Path("..") / "d.csv")
    assert run["holdout"] == 0.2 and run["marker"] == ["flange"]


def test_a_moved_tree_repeats_the_run_into_a_new_out(cell, tmp_path, capsys):
    moved = tmp_path / "moved"
    shutil.copytree(cell, moved)  # another machine, another folder: the relative paths still hold
    assert main(["calibrate", "--config", str(moved / "cell1" / "run.yaml"), "--out", str(moved / "cell2"),
                 "--quiet"]) == 0
    a, b = (json.loads((moved / c / "params.json").read_text()) for c in ("cell1", "cell2"))
    assert a["names"] == b["names"]
    assert max(abs(x - y) for x, y in zip(a["values"], b["values"])) < 1e-9


def test_a_repeat_without_a_new_out_is_told_so_in_one_line(cell, capsys):
    capsys.readouterr()
    assert main(["calibrate", "--config", str(cell / "cell1" / "run.yaml")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "repeats the run that wrote" in err and "--out cell1-repeat" in err, err
