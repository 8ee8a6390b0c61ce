"""Batched IK, the calibrated model's effects hook, and command correction on a simulated robot."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.deploy.correct import Corrector
from torchcal.elm import ELM
from torchcal.kinematics.ik import REASONS, solve_ik
from torchcal.deploy.model import CalibratedModel, apply_pose_error, pose_error
from torchcal.kinematics.robots import shipped
from torchcal.sim.serial import SimConfig, random_errors

torch.set_num_threads(1)

CENTER = torch.tensor([0.0, -1.0, 1.2, 0.0, 0.6, 0.0], dtype=torch.float64)
HALF = torch.tensor([0.7, 0.35, 0.45, 0.9, 0.5, 1.0], dtype=torch.float64)


def region(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return CENTER + HALF * (2 * torch.rand(n, 6, generator=g, dtype=torch.float64) - 1)


@pytest.fixture(scope="module")
def kr5():
    return shipped("kuka_kr5_arc")


class CyclicEffect:
    """A test effect: ``a sin(q) + b cos(2q)`` on every joint (rad)."""

    effect_type = "test_cyclic"

    def __init__(self, a: torch.Tensor, b: torch.Tensor, name: str = "cyclic"):
        self.name, self.a, self.b = name, a, b

    def joint_correction(self, q, covariates):
        return self.a * torch.sin(q) + self.b * torch.cos(2 * q)

    def state_dict(self):
        return {"a": self.a, "b": self.b, "name": self.name}

    @classmethod
    def from_state_dict(cls, state, robot=None):
        return cls(state["a"], state["b"], state["name"])


class SimRobot:
    """Truth for the correction tests: geometric errors + a cyclic joint error. Fitting code
    below only calls :meth:`measure`."""

    def __init__(self, robot, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        self.robot = robot
        self.truth = random_errors(robot, robot.params(), SimConfig(base_distance=0.0), g)
        self.effect = CyclicEffect(torch.tensor([0, 3e-4, -3e-4, 2e-4, 0, 0], dtype=torch.float64),
                                   torch.tensor([0, 1.5e-4, 1.5e-4, 0, 0, 0], dtype=torch.float64))

    def pose(self, q):
        return self.robot.fk(q + self.effect.joint_correction(q, None), self.truth)[:, 0]

    measure = pose


# ------------------------------------------------------------------ IK
def test_ik_recovers_random_targets(kr5):
    q = region(40, 1)
    p = kr5.params().values + 1e-3 * torch.randn(kr5.n_params, generator=torch.Generator().manual_seed(2),
                                                  dtype=torch.float64)
    T = kr5.fk(q, p)[:, 0]
    res = solve_ik(kr5, p, T, q + 0.05)
    assert bool(res.converged.all()) and res.reason == ["ok"] * 40
    assert float(res.pos_err.max()) <= 1e-9 and float(res.rot_err.max()) <= 1e-9
    T2 = kr5.fk(res.q, p)[:, 0]
    assert float((T2 - T).abs().max()) < 1e-8
    # position-only targets (redundant: 3 of 6 DoF)
    rp = solve_ik(kr5, p, T[:, :3, 3], q + 0.1)
    assert bool(rp.converged.all()) and float(rp.pos_err.max()) <= 1e-9


def test_ik_reports_failures(kr5):
    q = region(3, 3)
    T = kr5.fk(q)[:, 0]
    far = T.clone()
    far[:, :3, 3] = torch.tensor([3.0, 0.5, 0.4], dtype=torch.float64)
    res = solve_ik(kr5, None, far, q, restarts=0)
    assert res.reason == ["unreachable"] * 3 and not bool(res.converged.any())
    # a pose that needs A3 beyond its lower limit (-0.26 rad), started on that branch
    qb = torch.tensor([[0.2, -1.0, -0.6, 0.3, 0.6, 0.2]], dtype=torch.float64)
    Tb = kr5.fk(qb, check=False)[:, 0]
    rb = solve_ik(kr5, None, Tb, torch.tensor([[0.2, -1.0, -0.2, 0.3, 0.6, 0.2]], dtype=torch.float64), restarts=0)
    assert rb.reason == ["joint_limits"]
    lo, hi = kr5.joint_limits
    assert bool(((rb.q >= lo) & (rb.q <= hi)).all())
    assert set(res.reason + rb.reason) <= set(REASONS)
    with pytest.raises(ValueError, match=r"\(N, 4, 4\) poses or \(N, 3\) positions"):
        solve_ik(kr5, None, torch.zeros(5, 2))


# ------------------------------------------------------------------ model and effects hook
def test_pose_error_round_trip():
    g = torch.Generator().manual_seed(0)
    from torchcal.kinematics.transforms import homogeneous, so3_exp

    T = homogeneous(so3_exp(torch.randn(8, 3, generator=g, dtype=torch.float64)),
                    torch.randn(8, 3, generator=g, dtype=torch.float64))
    e = 1e-3 * torch.randn(8, 6, generator=g, dtype=torch.float64)
    T2 = apply_pose_error(T, e)
    torch.testing.assert_close(pose_error(T, T2), e, rtol=0, atol=1e-15)


def test_effects_hook_and_residual_in_predict_pose(kr5):
    sim = SimRobot(kr5)
    q = region(20, 4)
    model = CalibratedModel(kr5, sim.truth, effects=[sim.effect])
    # kinematics + effect = the simulated truth
    torch.testing.assert_close(model.predict_pose(q)[:, 0], sim.pose(q), rtol=0, atol=1e-15)
    torch.testing.assert_close(model.joint_values(q), q + sim.effect.joint_correction(q, None))
    assert torch.equal(model.predict_error(q), torch.zeros(20, 6, dtype=torch.float64))
    # with a residual ELM, predict_pose = geometric pose ⊕ predicted error
    elm = ELM(10, seed=0).fit(q, 1e-4 * torch.randn(20, 6, generator=torch.Generator().manual_seed(0),
                                                    dtype=torch.float64))
    m2 = CalibratedModel(kr5, sim.truth, effects=[sim.effect], residual=elm)
    torch.testing.assert_close(m2.predict_pose(q)[:, 0], apply_pose_error(sim.pose(q), elm.predict(q)))
    with pytest.raises(ValueError, match="takes 6 inputs but q"):
        CalibratedModel(kr5, residual=elm, covariates=["temperature"])
    with pytest.raises(TypeError, match="lacks name"):
        CalibratedModel(kr5, effects=[object()])


class ThermalShift:
    """A test position effect: robot-base marker positions grow by ``k (T - 20)`` along z."""

    covariates = ["temperature"]

    def __init__(self, k: float, name: str = "thermal"):
        self.name, self.k = name, k

    def joint_correction(self, q, covariates):
        return torch.zeros_like(q)

    def position_correction(self, p, q, covariates):
        dz = self.k * (covariates["temperature"] - 20.0)
        return p + torch.stack([torch.zeros_like(dz), torch.zeros_like(dz), dz], -1)[:, None, :]

    def state_dict(self):
        return {"k": self.k, "name": self.name}

    @classmethod
    def from_state_dict(cls, state, robot=None):
        return cls(state["k"], state["name"])


def test_effects_are_summed_at_the_command_and_position_hook(kr5):
    sim = SimRobot(kr5)
    q = region(10, 11)
    e2 = CyclicEffect(torch.full((6,), 1e-3, dtype=torch.float64), torch.zeros(6, dtype=torch.float64), name="c2")
    m = CalibratedModel(kr5, sim.truth, effects=[sim.effect, e2])
    # a sum of three terms, added here in another order than the model may: to a few ulps of q
    torch.testing.assert_close(m.joint_values(q), q + sim.effect.joint_correction(q, {}) + e2.joint_correction(q, {}),
                               rtol=0, atol=4 * torch.finfo(q.dtype).eps * float(q.abs().max()))
    # a position effect acts in the robot base frame, before the instrument (base) frame
    p = kr5.params()
    p["base.x"], p["base.y"], p["base.rz"], p["base.rx"] = 0.5, -0.2, 0.7, 0.1
    mt = CalibratedModel(kr5, p, effects=[ThermalShift(2e-5)])
    assert mt.required_covariates == ["temperature"]
    temp = torch.linspace(20, 40, 10, dtype=torch.float64)
    T = mt.predict_pose(q, {"temperature": temp})
    p0 = p.clone()
    for n in ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz"):
        p0[n] = 0.0
    from torchcal.kinematics.transforms import so3_exp

    Rb = so3_exp(torch.tensor([0.1, 0.0, 0.7], dtype=torch.float64))
    pb = kr5.fk(q, p0)[:, 0, :3, 3] + torch.stack([0 * temp, 0 * temp, 2e-5 * (temp - 20)], -1)
    want = pb @ Rb.T + torch.tensor([0.5, -0.2, 0.0], dtype=torch.float64)
    torch.testing.assert_close(T[:, 0, :3, 3], want, rtol=0, atol=1e-14)
    torch.testing.assert_close(T[:, 0, :3, :3], kr5.fk(q, p)[:, 0, :3, :3], rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"needs covariates \['temperature'\]"):
        mt.predict_pose(q)


def test_covariates_are_inputs_of_the_residual(kr5):
    q = region(30, 5)
    temp = torch.linspace(20, 30, 30, dtype=torch.float64)
    Y = torch.stack([1e-5 * (temp - 25)] * 3, 1)
    elm = ELM(8, seed=1).fit(torch.cat([q, temp[:, None]], 1), Y)
    m = CalibratedModel(kr5, residual=elm, covariates=["temperature"])
    e = m.predict_error(q, {"temperature": temp})
    # the covariate is the (N, dof + 1)-th column of the ELM input, by name or as a matrix
    assert e.shape == (30, 3) and torch.equal(e, elm.predict(torch.cat([q, temp[:, None]], 1)))
    assert torch.equal(e, m.predict_error(q, temp[:, None]))
    assert float((m.predict_error(q, {"temperature": temp + 5}) - e).abs().max()) > 1e-6
    with pytest.raises(ValueError, match="needs covariates"):
        m.predict_error(q)


# ------------------------------------------------------------------ correction
def test_correction_with_exact_model_reaches_targets(kr5):
    """With the true model (truth params + the effect), corrected commands put the real robot on
    the targets to the correction tolerance."""
    sim = SimRobot(kr5)
    q_t = region(50, 6)
    T_t = kr5.fk(q_t)[:, 0]
    res = Corrector(CalibratedModel(kr5, sim.truth, effects=[sim.effect]), tol_mm=1e-4, frame="instrument").correct(T_t, q0=q_t)
    assert bool(res.converged.all()), res.summary()
    assert float(res.predicted_error_mm.max()) <= 1e-4 and float(res.predicted_rot_error_mrad.max()) <= 1e-3
    reached = sim.pose(res.q)
    assert float((reached[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1).max()) < 2e-7
    assert int(res.n_outer.max()) <= 6


def test_correction_drives_simulated_robot_closer(kr5):
    """Seed 002 model-free: an ELM learns the total pose error from measured data only; the
    corrected commands bring the simulated robot much closer than the uncorrected ones."""
    sim = SimRobot(kr5, seed=1)
    q = region(300, 7)
    Y = pose_error(kr5.fk(q)[:, 0], sim.measure(q))  # measured - nominal target
    model = CalibratedModel(kr5, kr5.params(), residual=ELM(40, seed=0).fit(q, Y))
    q_t = region(80, 8)
    T_t = kr5.fk(q_t)[:, 0]  # nominal IK of these targets gives q_t: the uncorrected commands
    res = Corrector(model, frame="instrument").correct(T_t, q0=q_t)
    assert bool(res.converged.all()), res.summary()
    before = (sim.pose(q_t)[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1)
    after = (sim.pose(res.q)[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1)
    assert float(after.mean()) < 0.3 * float(before.mean())
    # position-only targets work the same way
    rp = Corrector(model, frame="instrument").correct(T_t[:, :3, 3], q0=q_t)
    after_p = (sim.pose(rp.q)[:, :3, 3] - T_t[:, :3, 3]).norm(dim=-1)
    assert bool(rp.converged.all()) and float(after_p.mean()) < 0.3 * float(before.mean())


def test_correction_reports_unreachable_targets(kr5):
    q_t = region(4, 9)
    T_t = kr5.fk(q_t)[:, 0]
    T_t[1, :3, 3] = torch.tensor([2.8, 0.0, 0.5], dtype=torch.float64)
    res = Corrector(CalibratedModel(kr5), frame="instrument").correct(T_t, q0=q_t)
    assert res.reason[1] == "unreachable" and not bool(res.converged[1])
    assert bool(res.converged[[0, 2, 3]].all())
    assert float(res.predicted_error_mm[1]) > 100
    assert math.isfinite(float(res.predicted_error_mm[1]))
