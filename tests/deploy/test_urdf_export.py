"""URDF export: the nominal kinematics of an exported URDF equal the calibrated kinematics of the
robot it came from (joint origins, zero offsets, markers and base frame all folded in)."""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from torchcal import Robot

TIAGO_MARKERS = ["hand_BL@wrist_ft_tool_link=0.05,0.03,0.1", "hand_BR@wrist_ft_tool_link=0.05,-0.03,0.1",
                 "hand_TL@wrist_ft_tool_link=-0.05,0.03,0.12"]


def _reload_and_compare(robot: Robot, params: torch.Tensor, q: torch.Tensor, path) -> Robot:
    xml = robot.export_urdf(params, path, with_instrument=True, with_markers=True)
    assert path.read_text() == xml
    back = Robot.from_urdf(path, markers=[f"marker_{m}" for m in robot.marker_names])
    assert sorted(back.joint_names) == sorted(robot.joint_names)
    cols = [robot.joint_names.index(n) for n in back.joint_names]
    T_back = back.fk(q[:, cols])
    T_cal = robot.fk(q, params)
    assert T_back.shape == T_cal.shape
    np.testing.assert_allclose(T_back[..., :3, 3].numpy(), T_cal[..., :3, 3].numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(T_back[..., :3, :3].numpy(), T_cal[..., :3, :3].numpy(), atol=1e-12, rtol=0)
    # the errors were large enough to matter
    assert float((T_cal - robot.fk(q)).abs().max()) > 1e-2
    return back


def test_export_tree_mimic(tree_robot, make_params, make_q, tmp_path):
    p = make_params(tree_robot, seed=31)
    q = make_q(tree_robot, 12, seed=32)
    back = _reload_and_compare(tree_robot, p, q, tmp_path / "tree.urdf")
    assert back.root == "instrument"  # the non-zero base frame became a new root link
    # the mimic coupling survived (multiplier and offset), with the offsets folded into origins
    xml = (tmp_path / "tree.urdf").read_text()
    assert re.search(r'<mimic[^>]*joint="finger_a_joint"', xml)
    assert back.dof == tree_robot.dof


def test_export_tree_without_mimic_marker(tree_urdf, make_params, make_q, tmp_path):
    """The tree without the mimic finger among the markers: non-z axes, a prismatic and a
    continuous joint, a fixed joint, a point marker, a large base frame."""
    robot = Robot.from_urdf(tree_urdf, markers=["tool", "finger_a", "m1@link4=0.01,0.02,0.03"])
    assert "finger_b_joint" not in [j.name for j in robot.joints]
    p = make_params(robot, seed=35)
    q = make_q(robot, 12, seed=36)
    back = _reload_and_compare(robot, p, q, tmp_path / "tree_nomimic.urdf")
    assert back.root == "instrument"  # the non-zero base frame became a new root link


def test_export_tree_without_base(tree_urdf, make_params, make_q, tmp_path):
    """With a zero base frame no instrument link is added; the root stays the URDF's root."""
    robot = Robot.from_urdf(tree_urdf, markers=["tool", "m1@link4=0.01,0.02,0.03"])
    p = make_params(robot, seed=33)
    p[:6] = 0
    q = make_q(robot, 5, seed=34)
    back = _reload_and_compare(robot, p, q, tmp_path / "tree_nobase.urdf")
    assert back.root == "base"
    assert "instrument" not in (tmp_path / "tree_nobase.urdf").read_text()


def test_export_kr5(kr5, make_params, make_q, tmp_path):
    p = make_params(kr5, seed=41)
    q = make_q(kr5, 12, seed=42)
    _reload_and_compare(kr5, p, q, tmp_path / "kr5.urdf")


def test_export_dh_with_prismatic_row(scara, make_params, make_q, tmp_path):
    p = make_params(scara, seed=43)
    q = make_q(scara, 12, seed=44)
    _reload_and_compare(scara, p, q, tmp_path / "scara.urdf")


def test_export_modified_dh(modified_arm, make_params, make_q, tmp_path):
    p = make_params(modified_arm, seed=45)
    q = make_q(modified_arm, 12, seed=46)
    _reload_and_compare(modified_arm, p, q, tmp_path / "craig.urdf")


def test_export_tiago(tiago_path, make_params, make_q, tmp_path):
    import yourdfpy

    robot = Robot.from_urdf(tiago_path, markers=TIAGO_MARKERS)
    assert robot.joint_names == ["torso_lift_joint"] + [f"arm_{i}_joint" for i in range(1, 8)]
    p = make_params(robot, seed=51, scale=0.01)
    q = make_q(robot, 10, seed=52)
    out = tmp_path / "tiago_cal.urdf"
    _reload_and_compare(robot, p, q, out)

    original, exported = tiago_path.read_text(), out.read_text()
    # the rest of the robot is still there: head, wheels, inertials
    links = set(re.findall(r'<link\s+name="([^"]+)"', exported))
    for name in ("head_1_link", "head_2_link", "wheel_left_link", "wheel_right_link", "base_footprint"):
        assert name in links, f"{name} missing from the exported URDF"
    assert set(re.findall(r'<link\s+name="([^"]+)"', original)) <= links
    assert exported.count("<inertial") == original.count("<inertial") > 10
    # joints that are not calibrated keep their origins exactly
    kw = dict(build_scene_graph=False, load_meshes=False, build_collision_scene_graph=False,
              load_collision_meshes=False)
    u0 = yourdfpy.URDF.load(str(tiago_path), **kw)
    u1 = yourdfpy.URDF.load(str(out), **kw)
    j1 = {j.name: j for j in u1.robot.joints}
    calibrated = {j.name for j in robot.joints}
    untouched = [j for j in u0.robot.joints if j.name not in calibrated]
    assert any(j.name == "head_1_joint" for j in untouched)
    for j in untouched:
        assert j.name in j1, f"joint {j.name} missing from the exported URDF"
        np.testing.assert_allclose(np.asarray(j1[j.name].origin if j1[j.name].origin is not None else np.eye(4)),
                                   np.asarray(j.origin if j.origin is not None else np.eye(4)), atol=1e-12)
        assert j1[j.name].type == j.type


def test_export_tiago_keeps_non_kinematic_elements(tiago_path, tmp_path):
    robot = Robot.from_urdf(tiago_path, markers=TIAGO_MARKERS[:1])
    out = tmp_path / "tiago_nominal.urdf"
    robot.export_urdf(None, out)
    original, exported = tiago_path.read_text(), out.read_text()
    for tag in ("transmission", "gazebo", "safety_controller", "calibration"):
        n0 = len(re.findall(rf"<{tag}[\s>/]", original))
        assert n0 > 0
        assert len(re.findall(rf"<{tag}[\s>/]", exported)) == n0, f"<{tag}> elements were dropped"


def test_export_keeps_comments(tree_urdf, tmp_path):
    xml = tree_urdf.replace('<link name="base"/>', '<!-- calibrated by hand in 2021 -->\n  <link name="base"/>')
    robot = Robot.from_urdf(xml, markers=["tool"])
    out = robot.export_urdf(None, tmp_path / "commented.urdf")
    assert "calibrated by hand in 2021" in out


def test_export_refuses_existing_marker_link(tree_urdf, tmp_path):
    xml = tree_urdf.replace('<link name="tool"/>', '<link name="tool"/>\n  <link name="marker_tool"/>').replace(
        "</robot>", '  <joint name="mt" type="fixed"><parent link="tool"/><child link="marker_tool"/></joint>\n</robot>')
    robot = Robot.from_urdf(xml, markers=["tool"])
    with pytest.raises(ValueError, match="marker_tool.*already exists"):
        robot.export_urdf(None, tmp_path / "x.urdf", with_markers=True)
    assert not (tmp_path / "x.urdf").exists()


def test_export_refuses_existing_base_link(tree_urdf, make_params, tmp_path):
    xml = tree_urdf.replace('<link name="base"/>', '<link name="base"/>\n  <link name="instrument"/>').replace(
        "</robot>", '  <joint name="ib" type="fixed"><parent link="base"/><child link="instrument"/></joint>\n</robot>')
    robot = Robot.from_urdf(xml, markers=["tool"])
    p = make_params(robot, seed=71)
    with pytest.raises(ValueError, match="'instrument' already exists.*base_link="):
        robot.export_urdf(p, tmp_path / "x.urdf", with_instrument=True, with_markers=True)
    robot.export_urdf(p, tmp_path / "y.urdf", base_link="mocap", with_instrument=True, with_markers=True)
    back = Robot.from_urdf(tmp_path / "y.urdf", markers=["marker_tool"])
    assert back.root == "mocap"


@pytest.mark.parametrize("name", ["kr5", "scara", "modified_arm"])
def test_to_urdf_string_dh(request, make_q, make_params, name):
    robot = request.getfixturevalue(name)
    end = robot.markers[0].link
    q = make_q(robot, 10, seed=61)
    text = robot.to_urdf_string()
    assert "marker_" not in text and "instrument" not in text
    back = Robot.from_urdf(text, markers=[end])
    assert back.joint_names == robot.joint_names
    np.testing.assert_allclose(back.fk(q).numpy(), robot.fk(q).numpy(), atol=1e-12, rtol=0)
    # calibrated: joint errors and offsets carried; base and marker errors are not in the text
    p = make_params(robot, seed=62)
    p_joints = p.clone()
    frame = [i for i, n in enumerate(robot.param_names)
             if n.startswith("base.") or n.split(".")[0] in robot.marker_names]
    assert len(frame) == 12
    p_joints[frame] = 0
    cal = Robot.from_urdf(robot.to_urdf_string(p), markers=[end])
    np.testing.assert_allclose(cal.fk(q).numpy(), robot.fk(q, p_joints).numpy(), atol=1e-12, rtol=0)
    assert float((robot.fk(q, p_joints) - robot.fk(q)).abs().max()) > 1e-3


def test_export_keeps_the_robots_root_by_default(tree_urdf, make_params, make_q, tmp_path):
    """The instrument registration is the cell's, not the robot's: by default it stays out of the
    URDF, whose calibrated kinematics then equal the robot's in its own base frame."""
    robot = Robot.from_urdf(tree_urdf, markers=["tool", "m1@link4=0.01,0.02,0.03"])
    p = make_params(robot, seed=37)
    assert float(p[:6].abs().max()) > 0.1  # a real instrument frame
    q = make_q(robot, 6, seed=38)
    xml = robot.export_urdf(p, tmp_path / "own_root.urdf", note="geometric part only", with_markers=True)
    assert "<!-- geometric part only -->" in xml
    back = Robot.from_urdf(tmp_path / "own_root.urdf", markers=[f"marker_{m}" for m in robot.marker_names])
    assert back.root == robot.root
    cols = [robot.joint_names.index(n) for n in back.joint_names]
    np.testing.assert_allclose(back.positions(q[:, cols]).numpy(), robot.positions(q, p, base=False).numpy(),
                               atol=1e-12, rtol=0)
