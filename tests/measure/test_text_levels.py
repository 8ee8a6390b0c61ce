"""A text column (a tool, an operator, a day) loads as levels, carries through subsets, and a
saved file reads back the same."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcal.kinematics.robots import shipped
from torchcal.measure.io import load_measurements, save_measurements


def _write(path, robot, tools):
    rng = np.random.default_rng(0)
    n = len(tools)
    q = rng.uniform(-1.5, 1.5, (n, robot.dof))
    p = robot.positions(torch.as_tensor(q), check=False).numpy()
    head = robot.joint_names + [f"{robot.marker_names[0]}.{a}" for a in "xyz"] + ["temperature", "tool"]
    lines = [",".join(head)]
    for i in range(n):
        lines.append(",".join([f"{v:.17g}" for v in q[i]] + [f"{v:.17g}" for v in p[i, 0]] + [f"{20 + i * 0.1:.3f}",
                                                                                           tools[i]]))
    path.write_text("\n".join(lines) + "\n")


def test_text_column_loads_as_levels_and_round_trips(tmp_path):
    robot = shipped("ur5e")
    tools = ["gripper", "probe", "probe", "", "gripper", "probe", "gripper", "probe"]
    f = tmp_path / "m.csv"
    _write(f, robot, tools)
    data = load_measurements(f, robot)
    assert sorted(k for k in data.covariates if "=" in k) == ["tool=gripper", "tool=probe"]
    assert data.covariates["tool=probe"][:3].tolist() == [0.0, 1.0, 1.0]
    assert bool(torch.isnan(data.covariates["tool=probe"][3]))  # not recorded: no level
    sub = data.subset([1, 4])
    assert sub.covariates["tool=gripper"].tolist() == [0.0, 1.0]
    g = tmp_path / "again.csv"
    save_measurements(g, data)
    assert "tool" in g.read_text().splitlines()[0].split(",")
    again = load_measurements(g, robot)
    for k in ("tool=gripper", "tool=probe", "temperature"):
        assert torch.allclose(again.covariates[k], data.covariates[k], equal_nan=True)


def test_a_text_joint_cell_is_still_refused(tmp_path):
    robot = shipped("ur5e")
    f = tmp_path / "m.csv"
    _write(f, robot, ["a", "b", "a", "b"])
    text = f.read_text().splitlines()
    cells = text[2].split(",")
    cells[0] = "abc"
    text[2] = ",".join(cells)
    f.write_text("\n".join(text) + "\n")
    with pytest.raises(ValueError, match="'abc' is not a number"):
        load_measurements(f, robot)
