"""The command line with an instrument's own files: ``--sep ';' --decimal , --units mm
--column-map`` on a command that reads measurements, ``torchcal import``, an orientation column that
never changes (a position-only tracker's placeholder), and another session's held-out rows with
``--reregister``."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal import Robot
from torchcal.cli.app import main
from torchcal.measure.io import load_measurements, save_measurements
from torchcal.sim.serial import SimConfig, simulate

UR5E = str(Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf")
MAP = ["--column-map", "X [mm]=flange.x", "--column-map", "Y [mm]=flange.y", "--column-map", "Z [mm]=flange.z"]


def _export(path: Path, data) -> None:
    """``data`` as a German-locale tracker writes it: ';', decimal commas, mm, its own column names."""
    head = list(data.joint_names) + ["X [mm]", "Y [mm]", "Z [mm]"]
    rows = [";".join(head)]
    for q, p in zip(data.q.tolist(), data.positions[:, 0].tolist()):
        rows.append(";".join(repr(v).replace(".", ",") for v in q + [1000 * x for x in p]))
    path.write_text("\n".join(rows) + "\n")


@pytest.fixture(scope="module")
def sim():
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    return robot, *simulate(robot, SimConfig(n=40, seed=4))


def _table(text: str) -> list[float]:
    return [float(x) for line in text.splitlines() if line.rstrip().endswith("[mm]") for x in line.split()[2:-1]]


@pytest.mark.slow
def test_calibrate_reads_the_export_as_it_reads_its_own_csv(tmp_path, sim, capsys):
    robot, data, _ = sim
    save_measurements(tmp_path / "own.csv", data)
    _export(tmp_path / "export.csv", data)
    assert main(["calibrate", "--robot", UR5E, "--data", str(tmp_path / "own.csv"), "--out", str(tmp_path / "a")]) == 0
    own = _table(capsys.readouterr().out)
    assert main(["calibrate", "--robot", UR5E, "--data", str(tmp_path / "export.csv"), "--sep", ";", "--decimal", ",",
                 "--units", "mm", *MAP, "--marker", "flange", "--out", str(tmp_path / "b")]) == 0
    got = _table(capsys.readouterr().out)
    assert len(own) == len(got) == 4 and np.allclose(own, got, atol=2e-4)  # the same fit, to the table's digits


def test_a_semicolon_file_read_as_commas_names_the_options(tmp_path, sim, capsys):
    robot, data, _ = sim
    _export(tmp_path / "export.csv", data)
    assert main(["calibrate", "--robot", UR5E, "--data", str(tmp_path / "export.csv"), "--marker", "flange",
                 "--out", str(tmp_path / "a")]) == 2
    assert "--sep ';' --decimal ','" in capsys.readouterr().err


def test_import_writes_torchcals_csv(tmp_path, sim, capsys):
    robot, data, _ = sim
    _export(tmp_path / "export.csv", data)
    out = tmp_path / "data.csv"
    assert main(["import", str(tmp_path / "export.csv"), "--robot", UR5E, "--marker", "flange", "--out", str(out),
                 "--sep", "semicolon", "--decimal", ",", "--units", "mm", *MAP]) == 0
    assert "wrote 40 rows" in capsys.readouterr().out
    back = load_measurements(out, robot)
    assert torch.allclose(back.q, data.q, atol=1e-12) and torch.allclose(back.positions, data.positions, atol=1e-12)
    assert main(["import", str(tmp_path / "export.csv"), "--robot", UR5E, "--marker", "flange", "--out", str(out),
                 "--sep", ";", "--decimal", ",", "--units", "mm", *MAP]) == 2  # never overwrites


@pytest.mark.slow
def test_a_constant_orientation_is_left_out_with_one_line(tmp_path, sim, capsys):
    """import-bag writes identity quaternions for a position-only tracker: not a measurement."""
    robot, data, _ = sim
    q = torch.zeros(len(data), 1, 4, dtype=data.q.dtype)
    q[..., 0] = 1.0
    data = data._with(data.q, data.positions, list(data.marker_names), q, {}, None, {})
    save_measurements(tmp_path / "bag.csv", data)
    assert main(["loop", "--robot", UR5E, "--data", str(tmp_path / "bag.csv"), "--effect", "none", "--no-elm",
                 "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert len([ln for ln in err.splitlines() if "placeholder" in ln]) == 1, err
    assert "no free parameter" not in err


@pytest.mark.slow
def test_another_session_with_a_moved_instrument(tmp_path, sim, capsys):
    """The same robot measured again after the tracker was set up 15 mm and 8 mrad elsewhere: refused
    as measured, with the cause found; accepted with --reregister, both figures printed."""
    robot, data, truth = sim
    moved = truth.clone()
    moved.values[moved.names.index("base.y")] += 0.015
    moved.values[moved.names.index("base.rx")] += 0.008
    again, _ = simulate(robot, SimConfig(n=30, seed=9), true_params=moved)
    save_measurements(tmp_path / "s1.csv", data)
    save_measurements(tmp_path / "s2.csv", again)
    args = ["loop", "--robot", UR5E, "--data", str(tmp_path / "s1.csv"), "--test", str(tmp_path / "s2.csv"),
            "--effect", "none", "--no-elm"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "do not belong to this robot's model" in err and "the instrument moved" in err and "--reregister" in err
    assert main(args + ["--reregister", "--out", str(tmp_path / "b")]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "registered anew" in ln)
    measured, anew = (float(x) for x in re.findall(r"([\d.]+) mm", line))
    assert measured > 10 and anew < 0.1  # 15 mm moved; the tracker's noise is 0.02 mm per axis
