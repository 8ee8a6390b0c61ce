"""Issue 36, item 7 and the data class: the door counts distinct poses, names the line of the file
(blank lines included), treats covariates as strictly as positions, and says before the work
when a fit will not fit in memory."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from torchcal import Robot
from torchcal.measure.io import load_measurements

REPO = Path(__file__).resolve().parents[2]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
SMR = "smr@flange=0,0,0.05"


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


def test_one_pose_measured_again_and_again_is_refused(tmp_path, torchcal_cli, ur5e_csv):
    lines = _lines(ur5e_csv)
    same = tmp_path / "same.csv"
    same.write_text("\n".join([lines[0]] + [lines[1]] * 100) + "\n")
    for prior in ("none", "auto"):
        rc, _, err = torchcal_cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", same, "--prior", prior,
                                  "--out", tmp_path / "o")
        assert rc == 2 and "the joints never moved" in err and "100 rows" in err, err
    # three poses measured 30 times each are three poses, not 90
    few = tmp_path / "few.csv"
    few.write_text("\n".join([lines[0]] + lines[1:4] * 30) + "\n")
    rc, _, err = torchcal_cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", few, "--out", tmp_path / "o")
    assert rc == 2 and "only 3 different poses" in err, err
    assert not (tmp_path / "o").exists()


def test_blank_lines_do_not_shift_the_line_a_message_names(tmp_path, torchcal_cli, ur5e_csv):
    lines = _lines(ur5e_csv)
    bad = lines[:3] + ["", "  ", ""] + lines[3:]
    k = 8  # a line after the blank ones
    bad[k - 1] = "abc," + bad[k - 1].split(",", 1)[1]
    f = tmp_path / "blank.csv"
    f.write_text("\n".join(bad) + "\n")
    rc, _, err = torchcal_cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", f, "--out", tmp_path / "o")
    assert rc == 2 and re.search(rf"blank\.csv, line {k}, column .*'abc' is not a number", err), err


def _with_column(src: Path, dst: Path, name: str, value) -> Path:
    lines = _lines(src)
    dst.write_text("\n".join([lines[0] + f",{name}"] + [ln + f",{value(i)}" for i, ln in enumerate(lines[1:])]) + "\n")
    return dst


def test_an_infinite_covariate_is_refused_and_an_empty_one_left_out(tmp_path, ur5e_csv):
    robot = Robot.from_urdf(UR5E, markers=[SMR])
    inf = _with_column(ur5e_csv, tmp_path / "inf.csv", "temperature", lambda i: "inf" if i == 5 else 20 + 0.1 * i)
    with pytest.raises(ValueError, match=r"inf\.csv, line 7, column 'temperature': inf is not a finite value"):
        load_measurements(inf, robot)
    empty = _with_column(ur5e_csv, tmp_path / "empty.csv", "temperature", lambda i: "")
    with pytest.warns(UserWarning, match=r"column 'temperature' is empty; it is not used as a covariate"):
        data = load_measurements(empty, robot)
    assert "temperature" not in data.covariates
    full = _with_column(ur5e_csv, tmp_path / "full.csv", "temperature", lambda i: 20 + 0.1 * i)
    assert "temperature" in load_measurements(full, robot).covariates


def test_a_fit_larger_than_the_memory_is_refused_with_the_figures(tmp_path, torchcal_cli, ur5e_csv, monkeypatch):
    from torchcal.measure import memory

    # the estimate follows rows × parameters: 20 Jacobian copies, as measured (see the module docstring)
    assert memory.estimate_bytes(200_000, 1, 57) == pytest.approx(0.5e9 + 20 * 200_000 * 3 * 57 * 8)
    monkeypatch.setattr(memory, "available_bytes", lambda: 1e6)  # 1 MB left
    rc, _, err = torchcal_cli("calibrate", "--robot", UR5E, "--marker", SMR, "--data", ur5e_csv, "--out",
                              tmp_path / "o")
    assert rc == 2 and re.search(r"60 rows × 1 marker\(s\) × \d+ parameters needs about [\d.]+ GB", err), err
    assert "fewer rows" in err and not (tmp_path / "o").exists()
