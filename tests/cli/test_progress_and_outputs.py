"""Through the command line (issue 35 §4, issue 33 §2): ``--progress`` on the long commands shows a
total and the time left, the fleet says what it does as it goes, ``plan`` names every file it
writes, and ``--holdout`` is not taken for a held-out file that is the training file."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from torchcal.cli.app import main

URDF = Path(__file__).resolve().parents[2] / "urdf"
UR5E, KR5 = str(URDF / "ur5e.urdf"), str(URDF / "kuka_kr5_arc.urdf")
# tqdm's line: "<desc>: 40%|████      | 2/5 [00:01<00:02, ...]": done/total and elapsed<left
_BAR = re.compile(r"(\d+)/(\d+) \[\d\d:\d\d<\d\d:\d\d")


def _sim(path: Path, robot: str, n: int, seed: int) -> Path:
    assert main(["simulate", "--robot", robot, "--marker", "flange", "--poses", str(n), "--seed", str(seed),
                 "--out", str(path), "--quiet"]) == 0
    return path


def _totals(err: str) -> set[tuple[int, int]]:
    return {(int(a), int(b)) for a, b in _BAR.findall(err)}


def test_plan_shows_its_progress_and_names_every_file_it_writes(tmp_path, capsys):
    out = tmp_path / "poses.csv"
    assert main(["plan", "--robot", KR5, "--marker", "smr@flange=0,0,0", "--candidates", "300", "--select", "12",
                 "--refine-steps", "5", "--progress", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    written = cap.out.split("wrote ", 1)[1].strip().split(", ")
    assert sorted(written) == sorted(str(p) for p in tmp_path.iterdir()), (written, list(tmp_path.iterdir()))
    assert str(tmp_path / "poses.plan.png") in written
    # the bar's total: 2 passes over the candidates, 12 poses selected, 5 refinement steps
    assert (19, 19) in _totals(cap.err), cap.err


def test_the_fleet_says_what_it_does_as_it_goes_and_counts_its_robots(tmp_path, capsys):
    d = tmp_path / "cell"
    d.mkdir()
    for i in range(3):
        _sim(d / f"r{i}.csv", UR5E, 25, seed=10 + i)
    capsys.readouterr()
    assert main(["fleet", "--robot", UR5E, "--marker", "flange", "--data", str(d), "--no-figures", "--progress",
                 "--out", str(tmp_path / "fleet")]) == 0
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    read = next(i for i, x in enumerate(lines) if x.startswith("read 3 robots"))
    done = next(i for i, x in enumerate(lines) if x.startswith("calibrated 3 robots"))
    assert read < done, err  # the stages are told in order, before the end
    assert (3, 3) in _totals(err), err


@pytest.mark.slow
def test_the_loop_bar_has_a_total_per_round(tmp_path, capsys):
    data = _sim(tmp_path / "d.csv", UR5E, 40, seed=3)
    capsys.readouterr()
    assert main(["loop", "--robot", UR5E, "--marker", "flange", "--data", str(data), "--effect", "joint_scale",
                 "--effect", "cyclic_joint_error", "--no-elm", "--folds", "2", "--progress",
                 "--out", str(tmp_path / "o")]) == 0
    totals = _totals(capsys.readouterr().err)
    assert (2, 2) in totals or (1, 1) in totals, totals  # round 1 tries both; a later round what is left


@pytest.mark.slow
def test_holdout_rows_are_not_taken_for_the_training_file(tmp_path, capsys):
    data = _sim(tmp_path / "d.csv", UR5E, 40, seed=4)
    capsys.readouterr()
    assert main(["calibrate", "--robot", UR5E, "--marker", "flange", "--data", str(data), "--holdout", "0.25",
                 "--out", str(tmp_path / "split")]) == 0
    assert "held-out file is the training file" not in capsys.readouterr().err
    # the same file given as --test is still named
    assert main(["calibrate", "--robot", UR5E, "--marker", "flange", "--data", str(data), "--test", str(data),
                 "--out", str(tmp_path / "same")]) == 0
    assert "held-out file is the training file" in capsys.readouterr().err
