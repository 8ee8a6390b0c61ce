"""A clean URDF out (issue 25, item 4): joints the calibration did not change stay byte for byte,
only the changed joints' ``<origin>`` lines differ, nothing else in the file is lost, no rpy is
rewritten needlessly near gimbal lock, the exported kinematics equal the calibrated model's (read
back by torchcal and by pytorch-kinematics), and ``calibration.yaml`` reproduces the exported
origins from the nominal ones."""
from __future__ import annotations

import difflib
import functools
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
import yourdfpy
from lxml import etree

from torchcal import Robot
from torchcal.kinematics.robots import SHIPPED, urdf_path
from torchcal.kinematics.transforms import rpy_to_matrix, so3_exp
from torchcal.kinematics.urdf_edit import rpy_near

from conftest import TIAGO_URDF

SHIPPED_MARKERS = {"kuka_kr5_arc": ["smr@flange=0.01,0.02,0.03"], "ur5e": ["smr@flange=0.01,0.02,0.03"],
                   "kuka_iiwa14": ["smr@flange=0.01,0.02,0.03"], "scara": ["smr@flange=0.01,0.02,0.03"]}
TIAGO_MARKERS = ["hand_BL@wrist_ft_tool_link=0.05,0.03,0.1"]

# every tag a URDF carries that kinematics does not read, a comment, and a <joint> inside a
# <transmission> of the same name as a robot joint (it must not be taken for that joint)
FULL_URDF = """<?xml version="1.0"?>
<!-- a description with everything an integrator's URDF has -->
<robot name="full" xmlns:xacro="http://ros.org/wiki/xacro">
  <material name="grey"><color rgba="0.5 0.5 0.5 1"/></material>
  <link name="base">
    <inertial>
      <origin xyz="0 0 0.05" rpy="0 0 0"/>
      <mass value="4.0"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/>
    </inertial>
    <visual><origin xyz="0 0 0.05"/><geometry><cylinder radius="0.08" length="0.1"/></geometry>
      <material name="grey"/></visual>
    <collision><geometry><box size="0.16 0.16 0.1"/></geometry></collision>
  </link>
  <link name="link1">
    <visual><geometry><mesh filename="package://full/meshes/link1.stl" scale="0.001 0.001 0.001"/></geometry></visual>
  </link>
  <link name="link2"/>
  <link name="link3"/>
  <link name="tool"/>
  <!-- the first axis: calibrated by hand in 2021 -->
  <joint name="j1" type="revolute">
    <parent link="base"/>
    <child link="link1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="50" velocity="2"/>
    <dynamics damping="0.1" friction="0.2"/>
    <safety_controller soft_lower_limit="-2.9" soft_upper_limit="2.9" k_position="10" k_velocity="1"/>
  </joint>
  <joint name="j2" type="revolute">
    <parent link="link1"/>
    <child link="link2"/>
    <origin rpy="-1.5707963267948966 -1.5707963267948966 0" xyz="0.05 0 0.1"/>
    <axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="link2"/>
    <child link="link3"/>
    <origin xyz="0.4 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/>
  </joint>
  <joint name="tool_joint" type="fixed">
    <parent link="link3"/>
    <child link="tool"/>
  </joint>
  <transmission name="t1">
    <type>transmission_interface/SimpleTransmission</type>
    <joint name="j1"><hardwareInterface>hardware_interface/PositionJointInterface</hardwareInterface></joint>
    <actuator name="m1"><mechanicalReduction>100</mechanicalReduction></actuator>
  </transmission>
  <gazebo reference="link1"><material>Gazebo/Grey</material></gazebo>
  <gazebo><plugin name="ros_control" filename="libgazebo_ros_control.so"/></gazebo>
</robot>
"""


def _robot_joint_origin_lines(text: str) -> dict[int, str]:
    """0-based line index of each robot joint's <origin> -> the joint's name (lxml source lines,
    independent of torchcal's own text scanning)."""
    root = etree.fromstring(text.encode())
    out = {}
    for j in root.findall("joint"):
        o = j.find("origin")
        if o is not None:
            out[o.sourceline - 1] = j.get("name")
    return out


def _check_only_changed_origins(original: str, exported: str, changed: set[str]) -> int:
    """Every line of ``original`` is in ``exported`` unchanged, except the <origin> lines of the
    joints in ``changed``; added lines are marker/instrument links before </robot>, the note after
    <robot>, or an <origin> added to a changed joint that had none."""
    a, b = original.splitlines(keepends=True), exported.splitlines(keepends=True)
    origin_of = _robot_joint_origin_lines(original)
    for op, i1, i2, j1, j2 in difflib.SequenceMatcher(None, a, b, autojunk=False).get_opcodes():
        if op == "equal":
            continue
        assert op in ("replace", "insert"), f"lines removed from the URDF: {a[i1:i2]}"
        for i in range(i1, i2):
            assert origin_of.get(i) in changed, f"line {i + 1} changed but is no changed joint's origin: {a[i]!r}"
        n = i2 - i1  # a replaced origin line, then perhaps lines added right after it
        assert all(x.lstrip().startswith("<origin") for x in b[j1:j1 + n]), b[j1:j1 + n]
        new = "".join(b[j1 + n:j2])
        assert not new or ("<origin" in new and new.count("\n") == 1) or "marker_" in new or "<!--" in new, new
    for i, name in origin_of.items():
        if name not in changed:
            assert a[i] in b
    return sum(i2 - i1 for op, i1, i2, _, _ in difflib.SequenceMatcher(None, a, b, autojunk=False).get_opcodes()
               if op == "replace")


def _random_on(robot: Robot, joints: list[str], seed: int, scale: float = 1e-3) -> torch.Tensor:
    """Errors of ``scale`` on the named joints' origins and offsets, the marker and the base;
    every other parameter exactly zero."""
    g = torch.Generator().manual_seed(seed)
    p = torch.zeros(robot.n_params, dtype=torch.float64)
    for i, n in enumerate(robot.param_names):
        if n.split(".")[0] in joints or n.startswith("base.") or n.split(".")[0] in robot.marker_names:
            p[i] = scale * (2 * torch.rand((), generator=g, dtype=torch.float64) - 1)
    return p


def _cases():
    out = [(name, urdf_path(name), SHIPPED_MARKERS[name]) for name in SHIPPED]
    return out + [("tiago", TIAGO_URDF, TIAGO_MARKERS)]


@pytest.mark.parametrize("name,path,markers", _cases(), ids=[c[0] for c in _cases()])
def test_unchanged_joints_stay_byte_for_byte(name, path, markers, tmp_path):
    if not path.is_file():
        pytest.skip(f"{path} not found: shared data is needed for this case")
    robot = Robot.from_urdf(path, markers=markers)
    original = path.read_text()
    # nothing changed: the file is the original plus the marker link
    robot.export_urdf(None, tmp_path / "nominal.urdf")
    assert _check_only_changed_origins(original, (tmp_path / "nominal.urdf").read_text(), set()) == 0
    # every other joint changed: those alone differ, one origin line each
    changed = [jt.name for jt in robot.joints][::2]
    p = _random_on(robot, changed, seed=3)
    exported = robot.export_urdf(p, tmp_path / "cal.urdf")
    assert 0 < _check_only_changed_origins(original, exported, set(changed)) <= len(changed)


def test_every_tag_comment_and_transmission_joint_is_kept(tmp_path):
    robot = Robot.from_urdf(FULL_URDF, markers=["tool"])
    p = _random_on(robot, ["j1", "j2", "j3", "tool_joint"], seed=5)
    exported = robot.export_urdf(p, tmp_path / "full.urdf", note="geometric part only", with_markers=True)
    _check_only_changed_origins(FULL_URDF, exported, {"j1", "j2", "j3", "tool_joint"})
    for tag in ("<!-- a description", "<!-- the first axis", "<inertial>", "<visual>", "<collision>", "<mesh ",
                "<transmission", "<gazebo", "<plugin", "<dynamics", "<safety_controller", "<material"):
        assert exported.count(tag) == FULL_URDF.count(tag) > 0, tag
    assert "<!-- geometric part only -->" in exported
    # the transmission's <joint name="j1"> was left alone; the tool joint gained an origin
    root = etree.fromstring(exported.encode())
    assert root.find("transmission/joint").find("origin") is None
    assert root.find("joint[@name='tool_joint']/origin") is not None
    back = Robot.from_urdf(exported, markers=["marker_tool"])
    q = torch.tensor([[0.3, -0.4, 0.5], [-1.0, 0.7, 1.2]], dtype=torch.float64)
    np.testing.assert_allclose(back.positions(q).numpy(), robot.positions(q, p, base=False).numpy(),
                               atol=1e-12, rtol=0)


def _rpy_of(exported: str, joint: str) -> np.ndarray:
    o = etree.fromstring(exported.encode()).find(f"joint[@name='{joint}']/origin")
    return np.array([float(v) for v in o.get("rpy").split()])


def test_gimbal_lock_rpy_stays_near_the_original(tmp_path):
    """j2 sits at (-π/2, -π/2, 0). A correction about the axis along the lock keeps that split
    exactly; one about the yaw axis keeps the numbers within the correction's size. Any tilt off
    the lock gets the closer of the two exact triples; before, (1.55, -1.568, -3.12) came out."""
    robot = Robot.from_urdf(FULL_URDF, markers=["tool"])
    r0 = np.array([-math.pi / 2, -math.pi / 2, 0.0])
    i = {n: k for k, n in enumerate(robot.param_names)}
    for slot, d in (("droll", 2e-3), ("dyaw", 2e-3), ("dpitch", 2e-3)):
        p = torch.zeros(robot.n_params, dtype=torch.float64)
        p[i[f"j2.{slot}"]] = d
        p[i["j2.dx"]] = 1e-4
        exported = robot.export_urdf(p, tmp_path / f"{slot}.urdf")
        rpy = _rpy_of(exported, "j2")
        T = robot.calibrated_joints(p)[[j.name for j in robot.joints].index("j2")].origin
        R = rpy_to_matrix(torch.tensor(rpy)).numpy()
        assert np.abs(R - T[:3, :3]).max() < 1e-15
        if slot == "droll":  # stays at the lock: roll takes the change, yaw and pitch as they were
            np.testing.assert_allclose(rpy, r0 + [d, 0, 0], atol=1e-12)
        elif slot == "dyaw":
            assert np.abs(rpy - r0).max() < 2 * d, rpy
        else:  # leaves the lock: pitch moves by d, roll and yaw only their sum is near; the closer triple
            assert abs(rpy[1] - r0[1]) < 2 * d and abs((rpy[0] + rpy[2]) - (r0[0] + r0[2])) < 2 * d, rpy
            other = np.array([rpy[0] + math.pi, math.pi - rpy[1], rpy[2] + math.pi])
            other = other + 2 * math.pi * np.round((r0 - other) / (2 * math.pi))
            assert np.abs(rpy - r0).sum() <= np.abs(other - r0).sum()
        # the unchanged joint at the top is written as it was
        assert '<origin xyz="0 0 0.3" rpy="0 0 0"/>' in exported


def test_rpy_near_chooses_the_closer_solution():
    rng = np.random.default_rng(0)
    for _ in range(200):
        r0 = rng.uniform(-math.pi, math.pi, 3)
        r0[1] = rng.uniform(-1.5, 1.5)
        R = rpy_to_matrix(torch.tensor(r0)).numpy() @ rpy_to_matrix(torch.tensor(rng.normal(0, 1e-3, 3))).numpy()
        v = rpy_near(R, r0 + rng.choice([-2, 0, 2], 3) * math.pi)  # the reference may be shifted by 2π
        assert np.abs(rpy_to_matrix(torch.tensor(v)).numpy() - R).max() < 1e-14
        assert np.abs(v - r0).max() < 0.05 + 2 * math.pi * 2


class _PK64:
    """pytorch-kinematics reads joint-origin rpy in float32 (pytorch_kinematics/urdf.py:
    ``torch.tensor(origin.rpy, dtype=torch.float32)``) and builds its chain in float32, 4e-8 m
    off; this builds the same transform, and the chain, in float64 so that its FK can be held to
    1e-9."""

    @staticmethod
    def convert(origin):
        import pytorch_kinematics.transforms as tf

        if origin is None:
            return tf.Transform3d(dtype=torch.float64)
        rpy = torch.tensor(origin.rpy, dtype=torch.float64)
        return tf.Transform3d(rot=tf.quaternion_from_euler(rpy, "sxyz"),
                              pos=torch.tensor(origin.xyz, dtype=torch.float64), dtype=torch.float64)


@pytest.mark.parametrize("name,path,markers", _cases(), ids=[c[0] for c in _cases()])
def test_exported_fk_equals_the_calibrated_model(name, path, markers, make_q, tmp_path, monkeypatch):
    if not path.is_file():
        pytest.skip(f"{path} not found: shared data is needed for this case")
    pk = pytest.importorskip("pytorch_kinematics")
    import pytorch_kinematics.urdf as pk_urdf

    robot = Robot.from_urdf(path, markers=markers)
    p = _random_on(robot, [jt.name for jt in robot.joints], seed=11, scale=0.01)
    q = make_q(robot, 20, seed=12)
    exported = robot.export_urdf(p, tmp_path / "cal.urdf", with_markers=True)
    want = robot.positions(q, p, base=False)[:, 0]
    back = Robot.from_urdf(tmp_path / "cal.urdf", markers=[f"marker_{robot.marker_names[0]}"])
    cols = [robot.joint_names.index(n) for n in back.joint_names]
    assert float((back.positions(q[:, cols])[:, 0] - want).abs().max()) < 1e-9
    monkeypatch.setattr(pk_urdf, "_convert_transform", _PK64.convert)
    monkeypatch.setattr(pk_urdf, "chain", SimpleNamespace(Chain=functools.partial(pk.chain.Chain, dtype=torch.float64)))
    chain = pk.build_chain_from_urdf(exported.encode()).to(dtype=torch.float64)
    names = chain.get_joint_parameter_names()
    ref = chain.forward_kinematics(q[:, [robot.joint_names.index(n) for n in names]] if set(names) <= set(
        robot.joint_names) else _full_q(robot, names, q))
    got = ref[f"marker_{robot.marker_names[0]}"].get_matrix()[:, :3, 3]
    root = ref[robot.root].get_matrix()  # pk's root may be another link (TIAGo: the base footprint)
    got = ((got - root[:, :3, 3])[:, None] @ root[:, :3, :3])[:, 0]
    assert float((got - want).abs().max()) < 1e-9
    assert float((want - robot.positions(q, None, base=False)[:, 0]).abs().max()) > 1e-3  # the change mattered


def _full_q(robot: Robot, names: list[str], q: torch.Tensor) -> torch.Tensor:
    """pk's joint vector for a robot with more joints than the calibrated chain (zeros there)."""
    out = torch.zeros(q.shape[0], len(names), dtype=q.dtype)
    for k, n in enumerate(names):
        if n in robot.joint_names:
            out[:, k] = q[:, robot.joint_names.index(n)]
    return out


def _axis_motion(jt, delta: float) -> np.ndarray:
    M = np.eye(4)
    if jt.type == "prismatic":
        M[:3, 3] = np.asarray(jt.axis) * delta
    else:
        M[:3, :3] = so3_exp(torch.as_tensor(np.asarray(jt.axis) * delta)).numpy()
    return M


@pytest.mark.parametrize("name,path,markers", _cases()[:1] + _cases()[-1:], ids=["kuka_kr5_arc", "tiago"])
def test_calibration_yaml_reproduces_the_exported_origins(name, path, markers, tmp_path):
    if not path.is_file():
        pytest.skip(f"{path} not found: shared data is needed for this case")
    robot = Robot.from_urdf(path, markers=markers)
    changed = [jt.name for jt in robot.joints][1::2]
    p = _random_on(robot, changed, seed=21)
    urdf_file, yaml_file = robot.export_calibration(p, tmp_path, note="test")
    cal = yaml.safe_load(yaml_file.read_text())
    assert cal["units"]["x"] == "m" and cal["units"]["roll"] == "rad" and "rad" in cal["units"]["zero_offsets"]
    assert cal["hash"].startswith("calib_")
    kw = dict(build_scene_graph=False, load_meshes=False, build_collision_scene_graph=False,
              load_collision_meshes=False)
    nominal = {j.name: j for j in yourdfpy.URDF.load(str(path), **kw).robot.joints}
    exported = {j.name: j for j in yourdfpy.URDF.load(str(urdf_file), **kw).robot.joints}
    listed = set(cal["corrections"]) | set(cal["zero_offsets"])
    assert listed == set(cal["kinematics"]) and listed <= set(changed) and len(listed) >= len(changed) - 1
    for name_j, j in nominal.items():
        O0 = np.eye(4) if j.origin is None else np.asarray(j.origin)
        O1 = np.eye(4) if exported[name_j].origin is None else np.asarray(exported[name_j].origin)
        if name_j not in listed:
            np.testing.assert_array_equal(O1, O0)
            continue
        c = cal["corrections"].get(name_j, dict.fromkeys(("x", "y", "z", "roll", "pitch", "yaw"), 0.0))
        C = np.eye(4)
        C[:3, :3] = rpy_to_matrix(torch.tensor([c["roll"], c["pitch"], c["yaw"]], dtype=torch.float64)).numpy()
        C[:3, 3] = [c["x"], c["y"], c["z"]]
        jt = robot._specs[name_j]
        rebuilt = O0 @ C @ _axis_motion(jt, cal["zero_offsets"].get(name_j, 0.0))
        np.testing.assert_allclose(rebuilt, O1, atol=1e-12, rtol=0)
        k = cal["kinematics"][name_j]
        Ok = np.eye(4)
        Ok[:3, :3] = rpy_to_matrix(torch.tensor([k["roll"], k["pitch"], k["yaw"]], dtype=torch.float64)).numpy()
        Ok[:3, 3] = [k["x"], k["y"], k["z"]]
        np.testing.assert_allclose(Ok, O1, atol=1e-12, rtol=0)
    # the correction is the parameters themselves, not a round trip through matrices
    j = next(n for n in changed if n in cal["corrections"])
    for s, key in (("dx", "x"), ("droll", "roll"), ("dyaw", "yaw")):
        assert cal["corrections"][j][key] == float(p[robot.param_names.index(f"{j}.{s}")])
