"""Effect models against independent references: the gravity wrenches, deflections and thermal
growth of :mod:`torchcal.sim.physsim` (its own URDF parser and kinematics, no torchcal code), exact
identities of the linear forms, and save/load round trips."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcal import CalibratedModel, Robot, load, save
from torchcal.effects import GravityDeformation, JointCompliance, ThermalDrift
from torchcal.effects.gravity import gravity_wrenches
from torchcal.sim.physsim import PhysicalRobot
from torchcal.sim.humanoid import humanoid_urdf
from torchcal.kinematics.robots import urdf_path

UR5E = urdf_path("ur5e").read_text()
PAYLOAD = dict(payload_kg=4.0, payload_com_m=(0.02, -0.03, 0.09))
MU = torch.tensor([4.0, 0.08, -0.12, 0.36], dtype=torch.float64)  # m, m·s of PAYLOAD


def _q(real, n=40):
    return real.sample_q(n)


@pytest.mark.parametrize("which", ["ur5e", "humanoid"])
def test_gravity_wrenches_match_the_independent_simulator(which):
    """Force and moment at the base and at every joint (URDF inertials, parts of the tree the
    robot does not model, and a payload) against physsim's own recursion."""
    urdf, mk = (UR5E, ["tool@flange"]) if which == "ur5e" else (humanoid_urdf(), ["lh@l_hand", "head_link"])
    real = PhysicalRobot(urdf, mk, seed=1, geometric_errors=False, **PAYLOAD)
    q = _q(real)
    ref = real.gravity_wrenches(q)
    robot = Robot.from_urdf(urdf, markers=mk)
    W = gravity_wrenches(robot, torch.tensor(q))
    tot = W.urdf + torch.einsum("nfab,b->nfa", W.payload, MU)
    checked = 0
    for f, name in enumerate(W.names):
        r = ref["base"] if name == "base" else ref["joints"].get(name)
        if r is None:
            continue
        F = (W.R[:, f] @ tot[:, f, :3, None])[..., 0].numpy()
        M = (W.R[:, f] @ tot[:, f, 3:, None])[..., 0].numpy()
        np.testing.assert_allclose(F, r["F_N"], atol=1e-9)
        np.testing.assert_allclose(M, r["M_Nm"], atol=1e-9)
        checked += 1
    assert checked == len(W.names)


def _family(robot, modes):
    eff = GravityDeformation(robot, modes=modes)
    K = len(modes)
    return eff, K


@pytest.mark.parametrize("truth,mode,c", [
    ({"lateral": {"elbow_joint": (0.0, 4e-6, 0.0)}}, "elbow_joint.bend_y", 4e-6),
    ({"lateral": {"shoulder_lift_joint": (3e-6, 3e-6, 0.0)}}, "shoulder_lift_joint.bend", 3e-6),  # axis z
    ({"base_tilt": (2e-6, 2e-6)}, "base.tilt", 2e-6),
    ({"base_tilt": (2e-6, 0.0)}, "base.tilt_x", 2e-6),
])
def test_deformation_modes_move_the_markers_as_the_simulator_does(truth, mode, c):
    """A bending or tilting mode's displacement equals the simulator's exact deflection to first
    order (the rotations are micro-radians)."""
    kw = dict(seed=2, geometric_errors=False, instrument_frame=np.eye(4), **PAYLOAD)
    stiff = PhysicalRobot(UR5E, ["tool@flange=0.0,0.0,0.1"], **kw)
    soft = PhysicalRobot(UR5E, ["tool@flange=0.0,0.0,0.1"], **kw, **truth)
    q = _q(stiff)
    want = soft.reach(q) - stiff.reach(q)  # (N, 1, 3) m
    robot = Robot.from_urdf(UR5E, markers=["tool@flange=0.0,0.0,0.1"])
    eff, K = _family(robot, [mode])
    theta = torch.cat([torch.tensor([c], dtype=torch.float64), MU, torch.zeros(2, dtype=torch.float64)])
    got = eff.position_delta(theta[None], eff.prepare(torch.tensor(q), {}))[0].numpy()
    assert np.abs(want).max() > 2e-5  # the deflection is well above a tracker's noise
    assert np.abs(got - want).max() < 0.01 * np.abs(want).max()


def test_joint_twist_is_the_simulators_torsion_exactly():
    kw = dict(seed=3, geometric_errors=False, instrument_frame=np.eye(4), **PAYLOAD)
    stiff = PhysicalRobot(UR5E, ["tool@flange"], **kw)
    soft = PhysicalRobot(UR5E, ["tool@flange"], **kw, torsion={"elbow_joint": 2e-5, "shoulder_lift_joint": 1e-5})
    q = _q(stiff)
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    eff = JointCompliance(robot, ["shoulder_lift_joint", "elbow_joint"])
    theta = torch.cat([torch.tensor([1e-5, 2e-5], dtype=torch.float64), MU, torch.zeros(2, dtype=torch.float64)])
    dq = eff.joint_delta(theta[None], eff.prepare(torch.tensor(q), {}))[0]
    p = robot.positions(torch.tensor(q) + dq).numpy()
    np.testing.assert_allclose(p, soft.reach(q), atol=1e-12)


def test_linear_form_reproduces_the_bilinear_model():
    """At coordinates (c, c·μ) the linear basis gives exactly the model's displacement and joint
    deflection, for every mode of the family at once."""
    robot = Robot.from_urdf(UR5E, markers=["tool@flange=0.01,0.02,0.1"])
    eff = GravityDeformation(robot)
    q = torch.tensor(_q(PhysicalRobot(UR5E, ["tool@flange"], seed=4), 25))
    prep = eff.prepare(q, {})
    K = len(eff.mode_labels())
    g = torch.Generator().manual_seed(0)
    theta = torch.zeros(eff.n_params, dtype=torch.float64)
    theta[:K] = torch.rand(K, generator=g, dtype=torch.float64) * 1e-5
    theta[K:K + 4] = MU
    basis = eff.linear_basis(prep)
    coords = torch.cat([torch.cat([theta[k:k + 1], theta[k] * MU]) for k in range(K)])
    assert basis.shared == 4 and len(basis.groups) == K
    dp, dq = eff.position_delta(theta[None], prep)[0], eff.joint_delta(theta[None], prep)[0]
    assert float((basis.dp @ coords - dp).abs().max()) < 1e-12 * float(dp.abs().max()) + 1e-18
    assert float((basis.dq @ coords - dq).abs().max()) < 1e-12 * float(dq.abs().max()) + 1e-18


def test_gravity_tilt_is_a_first_order_rotation_of_gravity():
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    q = torch.tensor(_q(PhysicalRobot(UR5E, ["tool@flange"], seed=5), 20))
    t = 2e-3
    level = JointCompliance(robot)
    tilted = JointCompliance(robot, gravity=(9.81 * math.sin(t), 0.0, -9.81 * math.cos(t)))
    K = len(level.mode_labels())
    theta = torch.cat([torch.full((K,), 1e-5, dtype=torch.float64), MU, torch.zeros(2, dtype=torch.float64)])
    ref = tilted.joint_delta(theta[None], tilted.prepare(q, {}))[0]
    theta[K + 4] = t
    got = level.joint_delta(theta[None], level.prepare(q, {}))[0]
    flat = JointCompliance(robot).joint_delta((theta * (torch.arange(len(theta)) != K + 4))[None], level.prepare(q, {}))[0]
    assert float((got - flat).abs().max()) > 1e-7  # the tilt matters
    # and is right to first order: what is left is of the order of t relative
    assert float((got - ref).abs().max()) < 3 * t * float((ref - flat).abs().max())


def test_thermal_growth_of_one_link_matches_the_simulator():
    kw = dict(seed=6, geometric_errors=False, instrument_frame=np.eye(4))
    cold = PhysicalRobot(UR5E, ["tool@flange"], **kw, thermal={"elbow_joint": 0.0})
    warm = PhysicalRobot(UR5E, ["tool@flange"], **kw, thermal={"elbow_joint": 2.3e-5})
    q = _q(cold)
    T = np.full(len(q), 35.0)
    want = warm.reach(q, temperature=T) - cold.reach(q, temperature=T)
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    eff = ThermalDrift(robot, covariate="temperature", t0=20.0, modes=["elbow_joint.growth"])
    got = eff.position_delta(torch.tensor([[2.3e-5]], dtype=torch.float64),
                             eff.prepare(torch.tensor(q), {"temperature": torch.tensor(T)}))[0].numpy()
    np.testing.assert_allclose(got, want, atol=1e-3 * np.abs(want).max())


def test_uniform_thermal_growth_scales_positions():
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    q = torch.tensor(_q(PhysicalRobot(UR5E, ["tool@flange"], seed=7), 10))
    eff = ThermalDrift(robot, covariate="temperature", t0=20.0, modes=["uniform"])
    T = torch.full((10,), 30.0, dtype=torch.float64)
    d = eff.position_delta(torch.tensor([[1e-5]], dtype=torch.float64), eff.prepare(q, {"temperature": T}))[0]
    np.testing.assert_allclose(d.numpy(), 1e-4 * robot.positions(q, base=False).numpy(), rtol=1e-12)


def test_modes_say_what_they_are_in_words():
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    eff = GravityDeformation(robot, modes=["base.tilt_x", "wrist_1_joint.bend_y"])
    K = 2
    eff.theta = torch.cat([torch.tensor([1.5e-6, 4e-6], dtype=torch.float64), MU, torch.zeros(2, dtype=torch.float64)])
    words = eff.describe()
    assert words[0] == "the base tilts about x by 1.5 µrad per N·m of overturning moment"
    assert words[1].startswith("wrist_1_joint bends about its y axis by 4 µrad per N·m")
    assert "4 kg" in words[K] and "payload" in words[K]
    with pytest.raises(ValueError, match="unknown mode"):
        GravityDeformation(robot, modes=["base.tilt_z"])


def test_families_survive_save_and_load(tmp_path):
    """A model with a bending family, joint compliance and per-link thermal growth predicts the
    same after a save/load round trip, time covariates clamped to their training range."""
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    geo = robot.params()
    fam = GravityDeformation(robot, modes=["base.tilt", "elbow_joint.bend_y"])
    fam.theta = torch.cat([torch.tensor([2e-6, 5e-6], dtype=torch.float64), MU, torch.tensor([1e-3, -2e-3],
                                                                                             dtype=torch.float64)])
    th = ThermalDrift(robot, covariate="t_start_robot", t0=100.0, modes=["elbow_joint.growth", "uniform"])
    th.theta = torch.tensor([2e-7, 1e-8], dtype=torch.float64)
    th.covariate_range = {"t_start_robot": (0.0, 200.0)}
    model = CalibratedModel(robot, geo, effects=[fam, th])
    q = torch.tensor(_q(PhysicalRobot(UR5E, ["tool@flange"], seed=8), 12))
    cov = {"t_start_robot": torch.linspace(-500, 900, 12, dtype=torch.float64)}
    before = model.predict_pose(q, cov)
    save(model, tmp_path / "m")
    after = load(tmp_path / "m").predict_pose(q, cov)
    assert torch.equal(before, after)
    # a time covariate beyond the training range acts as its nearest training value
    inside = {"t_start_robot": cov["t_start_robot"].clamp(0, 200)}
    assert torch.equal(model.predict_pose(q, inside), before)


def test_seat_modes_are_the_bending_modes_before_the_joint_turns():
    """Across the axis, a seat (frame before the joint turns) and a bend (after) differ by the
    joint's rotation: equal when the joint angle is zero, and together the same plane."""
    robot = Robot.from_urdf(UR5E, markers=["tool@flange"])
    real = PhysicalRobot(UR5E, ["tool@flange"], seed=9)
    q = torch.tensor(_q(real, 15))
    both = ["elbow_joint.bend_x", "elbow_joint.bend_y", "elbow_joint.seat_x", "elbow_joint.seat_y", "elbow_joint.bend"]
    eff = GravityDeformation(robot, modes=both)
    c = 5e-6

    def disp(qq, which):
        th = torch.zeros(eff.n_params, dtype=torch.float64)
        for w in which:
            th[both.index(w)] = c
        th[5:9] = MU
        return eff.position_delta(th[None], eff.prepare(qq, {}))[0]

    q0 = q.clone()
    q0[:, robot.joint_names.index("elbow_joint")] = 0.0
    assert torch.allclose(disp(q0, ["elbow_joint.seat_x"]), disp(q0, ["elbow_joint.bend_x"]), atol=1e-15)
    assert not torch.allclose(disp(q, ["elbow_joint.seat_x"]), disp(q, ["elbow_joint.bend_x"]), atol=1e-9)
    plane = disp(q, ["elbow_joint.bend"])
    assert torch.allclose(disp(q, ["elbow_joint.seat_x", "elbow_joint.seat_y"]), plane, atol=1e-15)
    assert torch.allclose(disp(q, ["elbow_joint.bend_x", "elbow_joint.bend_y"]), plane, atol=1e-15)


def test_seat_bending_matches_the_simulator_bending_before_the_joint_turns():
    kw = dict(seed=10, geometric_errors=False, instrument_frame=np.eye(4), **PAYLOAD)
    stiff = PhysicalRobot(UR5E, ["tool@flange=0.0,0.0,0.1"], **kw)
    soft = PhysicalRobot(UR5E, ["tool@flange=0.0,0.0,0.1"], **kw, lateral={"elbow_joint": (4e-6, 0.0, 0.0)},
                         lateral_frame="parent")
    q = _q(stiff)
    want = soft.reach(q) - stiff.reach(q)
    robot = Robot.from_urdf(UR5E, markers=["tool@flange=0.0,0.0,0.1"])
    eff = GravityDeformation(robot, modes=["elbow_joint.seat_x"])
    theta = torch.cat([torch.tensor([4e-6], dtype=torch.float64), MU, torch.zeros(2, dtype=torch.float64)])
    got = eff.position_delta(theta[None], eff.prepare(torch.tensor(q), {}))[0].numpy()
    assert np.abs(want).max() > 2e-5
    assert np.abs(got - want).max() < 0.01 * np.abs(want).max()
