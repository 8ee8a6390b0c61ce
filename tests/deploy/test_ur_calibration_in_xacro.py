"""A UR arm's ``calibration.yaml`` is ``ur_description``'s ``default_kinematics.yaml`` layout and
drops into a UR-style xacro macro, which reads it with ``xacro.load_yaml`` and puts its values in
the joint origins, as ``ur_macro.xacro`` does (issue 35 §2). The expanded URDF's kinematics are
the calibrated model's."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from torchcal.cli.app import main
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.ur_layout import UR_KEYS, ur_joints

xacro = pytest.importorskip("xacro", reason="xacro (pip install xacro; in the dev extra) loads the UR description")

UR5E = Path(__file__).resolve().parents[2] / "urdf" / "ur5e.urdf"
MARKERS = ["flange", "tcp@flange=0.05,0.02,0.1"]  # a point off the flange axis: orientation counts too
_LINKS = ["link0", "link1", "link2", "link3", "link4", "link5", "link6", "flange"]


def _ur_macro(prefix: str = "") -> str:
    """A UR-style description: the macro takes the kinematics file, loads it with xacro.load_yaml,
    reads every key into properties and writes them into the six joints' origins; the flange is
    fixed, as in ur_description."""
    props = [f'<xacro:property name="{k}_{a}" value="${{sec_kinematics[\'{k}\'][\'{a}\']}}"/>'
             for k in UR_KEYS for a in ("x", "y", "z", "roll", "pitch", "yaw")]
    joints = []
    for i, (k, j) in enumerate(UR_KEYS.items()):
        joints.append(f'''
    <joint name="{prefix}{j}" type="revolute">
      <parent link="{prefix}{_LINKS[i]}"/><child link="{prefix}{_LINKS[i + 1]}"/>
      <origin xyz="${{{k}_x}} ${{{k}_y}} ${{{k}_z}}" rpy="${{{k}_roll}} ${{{k}_pitch}} ${{{k}_yaw}}"/>
      <axis xyz="0 0 1"/><limit lower="-6.2832" upper="6.2832" effort="150" velocity="3.14"/>
    </joint>''')
    links = "".join(f'\n    <link name="{prefix}{n}"' + (' calibration="${kinematics_hash}"' if n == "link0" else "")
                    + "/>" for n in _LINKS)
    return f'''<?xml version="1.0"?>
<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="ur5e">
  <xacro:macro name="ur_robot" params="kinematics_parameters_file">
    <xacro:property name="config_kinematics_parameters" value="${{xacro.load_yaml(kinematics_parameters_file)}}"/>
    <xacro:property name="sec_kinematics" value="${{config_kinematics_parameters['kinematics']}}"/>
    <xacro:property name="kinematics_hash" value="${{sec_kinematics['hash']}}"/>
    {"".join(props)}{links}{"".join(joints)}
    <joint name="{prefix}flange_joint" type="fixed">
      <parent link="{prefix}link6"/><child link="{prefix}flange"/><origin xyz="0 0 0.0996" rpy="0 0 0"/>
    </joint>
  </xacro:macro>
  <xacro:arg name="kinematics_params" default=""/>
  <xacro:ur_robot kinematics_parameters_file="$(arg kinematics_params)"/>
</robot>
'''


def _expand(tmp: Path, calibration: Path) -> str:
    src = tmp / "ur.urdf.xacro"
    src.write_text(_ur_macro())
    doc = xacro.process_file(str(src), mappings={"kinematics_params": str(calibration)})
    return doc.toprettyxml(indent="  ")


def _planted(robot: Robot) -> torch.Tensor:
    """Errors on four UR joints (origin and zero offset); elbow_joint and flange_joint unchanged."""
    g = torch.Generator().manual_seed(5)
    p = torch.zeros(robot.n_params, dtype=torch.float64)
    for j in ("shoulder_pan_joint", "shoulder_lift_joint", "wrist_2_joint", "wrist_3_joint"):
        for s in ("dx", "dy", "dz", "droll", "dpitch", "dyaw", "offset"):
            n = f"{j}.{s}"
            if n in robot.param_names:
                p[robot.param_names.index(n)] = float(torch.randn((), generator=g, dtype=torch.float64)) * 1e-3
    return p


def test_the_ur5e_is_told_by_its_joints():
    robot = Robot.from_urdf(UR5E, markers=["flange"])
    assert ur_joints(robot.joints) == dict(UR_KEYS)
    kr5 = Robot.from_urdf(UR5E.parent / "kuka_kr5_arc.urdf", markers=["flange"])
    assert ur_joints(kr5.joints) is None


def test_the_ur_calibration_loads_in_a_ur_macro_and_gives_the_calibrated_kinematics(tmp_path):
    robot = Robot.from_urdf(UR5E, markers=MARKERS)
    p = _planted(robot)
    _, cal_path = robot.export_calibration(p, tmp_path)
    cal = yaml.safe_load(cal_path.read_text())
    kin = cal["kinematics"]
    assert set(kin) == set(UR_KEYS) | {"hash"} and kin["hash"].startswith("calib_")
    # an unchanged joint is listed too, with its nominal origin
    assert kin["forearm"] == {"x": -0.425, "y": 0.0, "z": 0.0, "roll": 0.0, "pitch": 0.0, "yaw": 0.0}
    urdf = _expand(tmp_path, cal_path)
    assert f'calibration="{kin["hash"]}"' in urdf
    back = Robot.from_urdf(urdf, markers=MARKERS)
    q = torch.rand(50, 6, generator=torch.Generator().manual_seed(6), dtype=torch.float64) * 4 - 2
    np.testing.assert_allclose(back.positions(q).numpy(), robot.positions(q, p, base=False).numpy(),
                               atol=1e-12, rtol=0)


@pytest.mark.slow
def test_a_ur5e_calibrated_on_the_command_line_drops_into_the_ur_macro(tmp_path, capsys):
    data = tmp_path / "ur.csv"
    assert main(["simulate", "--robot", str(UR5E), "--marker", "flange", "--poses", "60", "--seed", "7",
                 "--out", str(data), "--quiet"]) == 0
    out = tmp_path / "cell"
    assert main(["calibrate", "--robot", str(UR5E), "--marker", "flange", "--data", str(data), "--out", str(out)]) == 0
    capsys.readouterr()
    urdf = _expand(tmp_path, out / "calibration.yaml")
    back = Robot.from_urdf(urdf, markers=["flange"])
    exported = Robot.from_urdf(out / "calibrated.urdf", markers=["flange"])
    q = torch.rand(50, 6, generator=torch.Generator().manual_seed(8), dtype=torch.float64) * 4 - 2
    np.testing.assert_allclose(back.positions(q).numpy(), exported.positions(q).numpy(), atol=1e-12, rtol=0)
