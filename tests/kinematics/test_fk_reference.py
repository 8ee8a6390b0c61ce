"""Forward kinematics of the shipped robots against independent references.

* yourdfpy (scene-graph FK, numpy float64) on 1,000 random configurations per robot, every link;
* pytorch-kinematics on the same configurations;
* the DH model against the shipped URDF, and the zero pose against ``robot_data``;
* the URDF inertials against ``robot_data`` (masses, world-frame COMs and inertia tensors);
* a small tree URDF with a mimic joint and a prismatic branch.

Rotations are compared elementwise on the rotation matrices.  An elementwise bound eps on
R_a - R_b bounds the rotation angle of R_a R_b^T by about sqrt(2) eps (for small angles the
off-diagonal entries of the difference are the angle components), so "1e-10 elementwise" is a
1e-10 rad-level check.
"""
from __future__ import annotations

import importlib.util
import io
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yourdfpy

from torchcal import Robot
from torchcal.kinematics.robot_data import ROBOTS, get_robot
from torchcal.kinematics.robots import SHIPPED, dh_table, link_inertials, shipped, urdf_path

N_CONFIGS = 1000
ROOT = Path(__file__).resolve().parents[2]


def _yourdfpy(text_or_path) -> yourdfpy.URDF:
    src = io.StringIO(text_or_path) if isinstance(text_or_path, str) else str(text_or_path)
    return yourdfpy.URDF.load(src, build_scene_graph=True, load_meshes=False,
                              build_collision_scene_graph=False, load_collision_meshes=False)


def _configs(robot: Robot, n: int, seed: int) -> np.ndarray:
    """n configurations uniform within the joint limits, columns in robot.joint_names order."""
    lo, hi = (x.numpy() for x in robot.joint_limits)
    assert np.isfinite(lo).all() and np.isfinite(hi).all()
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, robot.dof))


def _yourdfpy_fk(u: yourdfpy.URDF, names: list[str], Q: np.ndarray, links: list[str]) -> np.ndarray:
    """(N, len(links), 4, 4) link poses in the base link frame, one update_cfg per row."""
    out = np.empty((len(Q), len(links), 4, 4))
    for n, q in enumerate(Q):
        u.update_cfg(dict(zip(names, q)))  # a dict: a list is matched by length, not by name
        for m, link in enumerate(links):
            out[n, m] = u.get_transform(link, u.base_link)
    return out


def _dh_frames(name: str, q: np.ndarray) -> list[np.ndarray]:
    """DH frames 0..n at one configuration, straight from the robot_data table (numpy, no
    torchcal): A_i = Rz(theta_i + q_i) Tz(d_i) Tx(a_i) Rx(alpha_i) (prismatic: Tz(d_i + q_i))."""
    T = np.eye(4)
    frames = [T]
    for row, qi in zip(get_robot(name)["joints"], q):
        th, d = row["theta"], row["d"]
        if row["type"] == "prismatic":
            d = d + qi
        else:
            th = th + qi
        ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(row["alpha"]), math.sin(row["alpha"])
        A = np.array([[ct, -st * ca, st * sa, row["a"] * ct],
                      [st, ct * ca, -ct * sa, row["a"] * st],
                      [0.0, sa, ca, d],
                      [0.0, 0.0, 0.0, 1.0]])
        T = T @ A
        frames.append(T)
    return frames


@pytest.fixture(scope="module", params=SHIPPED)
def case(request):
    """A shipped robot with every link as a marker, its yourdfpy model and 1,000 configs."""
    name = request.param
    u = _yourdfpy(urdf_path(name))
    links = list(u.link_map)
    robot = shipped(name, markers=links)
    Q = _configs(robot, N_CONFIGS, seed=1234 + SHIPPED.index(name))
    return name, robot, u, links, Q


# ----------------------------------------------------------------------------- references
def test_fk_matches_yourdfpy(case):
    name, robot, u, links, Q = case
    assert sorted(robot.joint_names) == sorted(u.actuated_joint_names)
    assert robot.marker_names == links and len(links) == robot.dof + 2  # link0..link{n}, flange
    T = robot.fk(torch.from_numpy(Q)).numpy()  # one batch
    ref = _yourdfpy_fk(u, robot.joint_names, Q, links)
    assert np.abs(T[..., :3, 3] - ref[..., :3, 3]).max() < 1e-10  # m
    assert np.abs(T[..., :3, :3] - ref[..., :3, :3]).max() < 1e-10  # elementwise, ~rad
    np.testing.assert_array_equal(T[..., 3, :], ref[..., 3, :])


def test_fk_matches_pytorch_kinematics(case):
    pk = pytest.importorskip("pytorch_kinematics")
    name, robot, u, links, Q = case
    chain = pk.build_chain_from_urdf(urdf_path(name).read_text()).to(dtype=torch.float64)
    pk_names = chain.get_joint_parameter_names()
    assert sorted(pk_names) == sorted(robot.joint_names)
    cols = [robot.joint_names.index(n) for n in pk_names]  # map columns by name
    Qt = torch.from_numpy(Q)
    ref = chain.forward_kinematics(Qt[:, cols])
    T = robot.fk(Qt)
    # pytorch-kinematics' URDF parser reads the joint-origin angles (rpy) in float32
    # (pytorch_kinematics/urdf.py: torch.tensor(origin.rpy, dtype=torch.float32)), which puts its
    # poses about 4e-8 m off the float64 ones (measured: <= 3.7e-8 m) and, for the SCARA's
    # alpha = pi (sin(float32(pi)) = -8.7e-8), 8.7e-8 off in rotation entries; hence 1e-7 here
    # instead of 1e-10.
    for m, link in enumerate(links):
        Tm = ref[link].get_matrix()
        assert Tm.dtype == torch.float64
        err = (T[:, m] - Tm).abs().max().item()
        assert err < 1e-7, (name, link, err)


def test_dh_model_equals_shipped_urdf(case):
    name, robot_urdf, u, links, Q = case
    robot_dh = shipped(name, source="dh", markers=links)
    assert robot_dh.joint_names == robot_urdf.joint_names
    assert any(p.endswith(".da") for p in robot_dh.param_names)  # DH error parameters
    assert not any(p.endswith(".da") for p in robot_urdf.param_names)
    q = torch.from_numpy(Q[:200])
    err = (robot_dh.fk(q) - robot_urdf.fk(q)).abs().max().item()
    assert err < 1e-12, err
    # and both agree with the plain numpy DH product of robot_data (flange = DH frame n)
    fl = links.index("flange")
    T = robot_dh.fk(q).numpy()
    ref = np.stack([_dh_frames(name, qi)[-1] for qi in Q[:200]])
    assert np.abs(T[:, fl] - ref).max() < 1e-12


@pytest.mark.parametrize("name", SHIPPED)
@pytest.mark.parametrize("source", ["dh", "urdf"])
def test_zero_pose(name, source):
    robot = shipped(name, source=source)
    assert robot.marker_names == ["flange"]
    p = robot.fk(torch.zeros(robot.dof))[0, :3, 3].numpy()
    np.testing.assert_allclose(p, ROBOTS[name]["zero_pose"], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- the files
@pytest.mark.parametrize("name", SHIPPED)
def test_urdf_limits_and_names(name):
    data = get_robot(name)
    u = _yourdfpy(urdf_path(name))
    assert u.robot.name == data["urdf_name"]
    for row in data["joints"]:
        j = u.joint_map[row["name"]]
        assert j.type == row["type"]
        assert j.limit.lower == row["lower"] and j.limit.upper == row["upper"]
        assert j.limit.velocity == row["velocity"]
        assert j.limit.effort == (row["effort"] or 0.0)  # 0: not published
    text = urdf_path(name).read_text()
    assert "generated by scripts/make_urdfs.py" in text.lower() and "do not edit by hand" in text
    assert "Approximate" in text and data["source"][:40].split()[0] in text


def test_shipped_urdfs_up_to_date():
    spec = importlib.util.spec_from_file_location("make_urdfs", ROOT / "scripts" / "make_urdfs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--check"]) == 0, "run scripts/make_urdfs.py"


def test_shipped_names_and_errors():
    assert set(SHIPPED) == set(ROBOTS)
    with pytest.raises(KeyError, match="shipped robots"):
        shipped("puma560")
    with pytest.raises(ValueError, match="source"):
        shipped("ur5e", source="xacro")
    rows = dh_table("kuka_kr5_arc")
    assert [r["name"] for r in rows] == [f"joint_a{i}" for i in range(1, 7)]
    r = shipped("kuka_kr5_arc", source="dh")
    assert r.param_names[6:10] == ["joint_a1.da", "joint_a1.dd", "joint_a1.dalpha", "joint_a1.dtheta"]


def test_urdf_path_missing(monkeypatch):
    import torchcal.kinematics.robots as robots

    monkeypatch.setattr(robots, "__file__", "/nonexistent/site-packages/torchcal/robots.py")
    with pytest.raises(FileNotFoundError, match="source='dh'"):
        robots.urdf_path("ur5e")
    assert robots.shipped("ur5e", source="dh").dof == 6  # needs no file


@pytest.mark.parametrize("name", SHIPPED)
def test_urdf_masses(name):
    data = get_robot(name)
    u = _yourdfpy(urdf_path(name))
    masses = {l.name: l.inertial.mass for l in u.robot.links if l.inertial is not None}
    if data["inertials"] is None:
        assert masses == {} and link_inertials(name) == {}
        return
    assert set(masses) == {f"link{i}" for i in range(1, data["dof"] + 1)}
    assert sum(masses.values()) == pytest.approx(sum(i["mass"] for i in data["inertials"]), abs=1e-12)
    for i, inert in enumerate(data["inertials"], start=1):
        assert masses[f"link{i}"] == inert["mass"]


@pytest.mark.parametrize("name", [n for n in SHIPPED if ROBOTS[n]["inertials"] is not None])
def test_urdf_inertials_world_frame(name):
    """COM and inertia tensor of every link in the base frame, at random q: from the URDF (yourdfpy
    inertial origin composed with the yourdfpy link pose) and from robot_data (DH-frame COM and
    tensor composed with the numpy DH frame pose) agree."""
    data = get_robot(name)
    u = _yourdfpy(urdf_path(name))
    names = [r["name"] for r in data["joints"]]
    rng = np.random.default_rng(7)
    lo = np.array([r["lower"] for r in data["joints"]])
    hi = np.array([r["upper"] for r in data["joints"]])
    for q in rng.uniform(lo, hi, size=(50, len(lo))):
        u.update_cfg(dict(zip(names, q)))
        dh = _dh_frames(name, q)
        for i, inert in enumerate(data["inertials"], start=1):
            link = u.link_map[f"link{i}"]
            T = u.get_transform(link.name, u.base_link) @ link.inertial.origin
            com_urdf = T[:3, 3]
            com_dh = dh[i][:3, :3] @ np.asarray(inert["com"]) + dh[i][:3, 3]
            assert np.abs(com_urdf - com_dh).max() < 1e-12
            I_urdf = T[:3, :3] @ link.inertial.inertia @ T[:3, :3].T
            ixx, ixy, ixz, iyy, iyz, izz = inert["inertia"]
            I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
            I_dh = dh[i][:3, :3] @ I @ dh[i][:3, :3].T
            assert np.abs(I_urdf - I_dh).max() < 1e-14


# ----------------------------------------------------------------------------- tree + mimic
TREE_URDF = """<?xml version="1.0"?>
<robot name="gripper_tree">
  <link name="base"/> <link name="palm"/> <link name="finger_l"/> <link name="finger_r"/>
  <link name="slider"/> <link name="slider_tip"/>
  <joint name="wrist" type="revolute">
    <parent link="base"/> <child link="palm"/>
    <origin xyz="0.1 -0.05 0.3" rpy="0.2 -0.4 1.1"/> <axis xyz="0 0.6 0.8"/>
    <limit lower="-2.5" upper="2.5" effort="10" velocity="2"/>
  </joint>
  <joint name="finger_l_joint" type="revolute">
    <parent link="palm"/> <child link="finger_l"/>
    <origin xyz="0.02 0.04 0.09" rpy="0 0.3 0"/> <axis xyz="1 0 0"/>
    <limit lower="-0.5" upper="0.8" effort="5" velocity="1"/>
  </joint>
  <joint name="finger_r_joint" type="revolute">
    <parent link="palm"/> <child link="finger_r"/>
    <origin xyz="0.02 -0.04 0.09" rpy="0 -0.3 3.14159"/> <axis xyz="1 0 0"/>
    <limit lower="-0.8" upper="0.6" effort="5" velocity="1"/>
    <mimic joint="finger_l_joint" multiplier="-1" offset="0.1"/>
  </joint>
  <joint name="slide" type="prismatic">
    <parent link="base"/> <child link="slider"/>
    <origin xyz="-0.2 0.1 0.05" rpy="-0.7 0.1 0.25"/> <axis xyz="0 1 0"/>
    <limit lower="-0.1" upper="0.3" effort="100" velocity="0.5"/>
  </joint>
  <joint name="slider_tip_joint" type="fixed">
    <parent link="slider"/> <child link="slider_tip"/>
    <origin xyz="0.0 0.03 0.12" rpy="0.5 0 -0.2"/>
  </joint>
</robot>
"""


def _rot(axis, angle) -> np.ndarray:
    """4x4 rotation about a unit axis (Rodrigues)."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    return T


def test_tree_with_mimic_matches_yourdfpy():
    leaves = ["finger_l", "finger_r", "slider_tip"]
    robot = Robot.from_urdf(TREE_URDF, markers=leaves)
    assert robot.joint_names == ["wrist", "finger_l_joint", "slide"]  # the mimic is not a column
    u = _yourdfpy(TREE_URDF)
    assert u.actuated_joint_names == robot.joint_names
    Q = _configs(robot, 200, seed=99)
    T = robot.fk(torch.from_numpy(Q)).numpy()
    ref = _yourdfpy_fk(u, robot.joint_names, Q, leaves)
    assert np.abs(T - ref).max() < 1e-12
    # yourdfpy's mimic handling checked by hand: finger_r = palm . origin . Rx(-q_l + 0.1)
    j = u.joint_map["finger_r_joint"]
    for n in range(0, 200, 20):
        u.update_cfg(dict(zip(robot.joint_names, Q[n])))
        palm = u.get_transform("palm", u.base_link)
        expected = palm @ j.origin @ _rot(j.axis, -Q[n, 1] + 0.1)
        assert np.abs(ref[n, 1] - expected).max() < 1e-12
        assert np.abs(T[n, 1] - expected).max() < 1e-12
