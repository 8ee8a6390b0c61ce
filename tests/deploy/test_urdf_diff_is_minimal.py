"""``calibrated.urdf`` differs from the input only as ``torchcal/kinematics/export.py`` states:
the origins of joints changed by more than their standard error (and 1e-9 m / rad), no rounding
noise written as a number, marker links only on request (issue 35 §2)."""
from __future__ import annotations

import difflib
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal.cli.app import main
from torchcal.kinematics.robot import Robot

URDF = Path(__file__).resolve().parents[2] / "urdf"
UR5E = URDF / "ur5e.urdf"
_NUM = re.compile(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _changed_joints(original: str, exported: str) -> set[str]:
    """The joints whose lines differ, by name (every changed line must be a joint's <origin>)."""
    names, current = {}, None
    for i, line in enumerate(original.splitlines()):
        m = re.search(r'<joint name="([^"]+)"', line)
        current = m.group(1) if m else current
        names[i] = current
    out = set()
    sm = difflib.SequenceMatcher(a=original.splitlines(), b=exported.splitlines(), autojunk=False)
    for tag, i1, i2, j1, j2 in sm.get_opcodes():
        if tag == "equal":
            continue
        assert tag == "replace" and i2 - i1 == j2 - j1, (tag, exported.splitlines()[j1:j2])
        for i in range(i1, i2):
            assert "<origin" in original.splitlines()[i], original.splitlines()[i]
            out.add(names[i])
    return out


def _p(robot: Robot, values: dict[str, float]) -> torch.Tensor:
    p = torch.zeros(robot.n_params, dtype=torch.float64)
    for n, v in values.items():
        p[robot.param_names.index(n)] = v
    return p


def test_only_joints_changed_beyond_their_standard_error_are_rewritten(tmp_path):
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    p = _p(robot, {"wrist_2_joint.dx": 2e-4,          # 20 standard errors: rewritten
                   "shoulder_lift_joint.dx": 3e-6,    # within its standard error of 5 µm: kept
                   "elbow_joint.dyaw": 4e-10,         # below 1e-9 rad, no standard error given: kept
                   "flange_joint.dz": 1e-12})         # the 1e-12 m of a prior fit: kept
    se = {"wrist_2_joint.dx": 1e-5, "shoulder_lift_joint.dx": 5e-6}
    text = robot.export_urdf(p, tmp_path / "c.urdf", std_errors=se)
    assert _changed_joints(UR5E.read_text(), text) == {"wrist_2_joint"}
    assert "marker_" not in text  # markers only on request
    assert "marker_flange" in robot.export_urdf(p, tmp_path / "m.urdf", std_errors=se, with_markers=True)
    # calibration.yaml holds the same calibration as the URDF
    _, cal = robot.export_calibration(p, tmp_path, std_errors=se)
    import yaml
    assert set(yaml.safe_load(cal.read_text())["corrections"]) == {"wrist_2_joint"}


@pytest.mark.parametrize("urdf", ["ur5e.urdf", "kuka_kr5_arc.urdf", "kuka_iiwa14.urdf"])
def test_no_rounding_noise_is_written_as_a_number(urdf, tmp_path):
    """A fit leaves rounding noise in values that are zero (-2.198e-20 was written into an origin)."""
    robot = Robot.from_urdf(URDF / urdf, markers=["flange"])
    g = torch.Generator().manual_seed(11)
    joints = [n for n in robot.param_names if n.rsplit(".", 1)[-1] in ("dx", "dy", "dz", "droll", "dpitch", "dyaw")
              and not n.startswith(("base.", "flange."))]
    p = _p(robot, {n: float(torch.randn((), generator=g, dtype=torch.float64)) * 1e-3 for n in joints})
    # a fitted value that is zero up to the solver's rounding, beside a real change of the same joint
    first = joints[0].rsplit(".", 1)[0]
    p[robot.param_names.index(f"{first}.dx")], p[robot.param_names.index(f"{first}.dy")] = 2e-4, -2.198e-20
    text = robot.export_urdf(p, tmp_path / "c.urdf")
    values = [float(v) for o in re.findall(r"<origin [^>]*>", text) for v in _NUM.findall(o)]
    tiny = [v for v in values if v != 0.0 and abs(v) < 1e-15]
    assert not tiny, tiny
    back = Robot.from_urdf(text, markers=["flange"])  # and the kinematics are still the calibrated ones
    q = torch.rand(20, robot.dof, generator=g, dtype=torch.float64) - 0.5
    np.testing.assert_allclose(back.positions(q).numpy(), robot.positions(q, p, base=False).numpy(), atol=1e-12)


@pytest.mark.slow
def test_the_command_line_rewrites_exactly_the_joints_its_fit_moved_significantly(tmp_path, capsys):
    data = tmp_path / "ur.csv"
    assert main(["simulate", "--robot", str(UR5E), "--marker", "flange", "--poses", "40", "--seed", "9",
                 "--angle-error-mrad", "0.02", "--length-error-mm", "0.01", "--noise-mm", "0.05",
                 "--out", str(data), "--quiet"]) == 0
    out = tmp_path / "cell"
    assert main(["calibrate", "--robot", str(UR5E), "--marker", "flange", "--data", str(data), "--out",
                 str(out)]) == 0
    capsys.readouterr()
    fit = json.loads((out / "params.json").read_text())
    se = fit["std_errors"]
    moved = {n.rsplit(".", 1)[0] for n, v in zip(fit["names"], fit["values"])
             if not n.startswith("base.") and abs(v) > max(1e-9, se.get(n) or 0.0)}
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    moved &= {j.name for j in robot.joints}
    got = _changed_joints(UR5E.read_text(), (out / "calibrated.urdf").read_text())
    assert got == moved, (got, moved)
    assert "marker_" not in (out / "calibrated.urdf").read_text()
