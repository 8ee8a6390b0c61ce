"""One Problem protocol, any solver: every system torchcal identifies is a
:class:`torchcal.problems.base.Problem`, and the least-squares and swarm solvers all run on each.
Also: every simulator answers ``simulate(n, seed=...)`` with reproducible data and its truth apart."""
from __future__ import annotations

import pytest
import torch

from torchcal.dynamics.excitation import FourierExcitation
from torchcal.dynamics import scara
from torchcal.kinematics.robots import shipped
from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_paths import spiral_trajectory
from torchcal.measure.laser import Laser, psd_frame
from torchcal.measure.registration import register_base
from torchcal.optim import minimize
from torchcal.pipelines.dynamics import DynamicsSettings
from torchcal.problems.base import Problem
from torchcal.problems.calibration import CalibrationProblem
from torchcal.problems.dynamics import TorqueFitProblem, physical_box
from torchcal.problems.elm import ELMProblem
from torchcal.problems.excitation import ExcitationProblem
from torchcal.problems.psd import SpotResidual
from torchcal.problems.rrru import RRRUCalibration
from torchcal.sim.compliant_arm import CompliantArm, ur5e_masses
from torchcal.sim.psd import PSDSimulator
from torchcal.sim.rrru import TrackerSimulator, simulate_tracker
from torchcal.sim.scara import ScaraTorqueSimulator
from torchcal.sim.serial import SimConfig, simulate, simulated_robot

F64 = dict(dtype=torch.float64)


def _box(prob: Problem, half: torch.Tensor | float) -> Problem:
    """Finite bounds around the start, for the swarm solvers (the protocol's bounds are public)."""
    x0 = prob.start()
    prob.lower, prob.upper = x0 - half, x0 + half
    return prob


def _serial() -> Problem:
    robot = shipped("ur5e", markers=["flange"])
    data, _ = simulate(robot, SimConfig(n=30, noise=2e-5, seed=4))
    p = register_base(robot, data)  # the instrument frame from the data, as calibrate starts
    p.only("shoulder_lift*", "elbow*")
    return _box(CalibrationProblem(robot, p, data), 2e-3)


def _psd() -> Problem:
    robot = shipped("kuka_kr5_arc", source="dh")
    centres = torch.tensor([[0.95, -0.30, 0.15], [0.85, 0.45, 0.55]], **F64)
    R = torch.stack([psd_frame(torch.tensor([0.1, 0.0, 1.0], **F64) - c, 0.3 * j) for j, c in enumerate(centres)])
    true = torch.zeros(robot.n_params, **F64)
    i = robot.param_names.index("joint_a2.da")
    true[i] = 4e-4
    sim = PSDSimulator(robot, true, Laser(), R, centres, q0=torch.tensor([0.0, -1.4, 2.4, 0.0, 0.5, 0.0], **F64))
    data = sim.simulate(8, seed=1).data
    free = robot.params()
    free.only("joint_a2.da")
    return _box(SpotResidual(robot, Laser(), data, free, R, centres), 1e-3)


def _rrru() -> Problem:
    model = RRRU()
    T = spiral_trajectory(20)
    true = torch.zeros(model.n_params, **F64)
    true[0], true[3] = 1e-3, 2e-4
    theta, _, meas = simulate_tracker(model, T, true, 1e-5, generator=torch.Generator().manual_seed(0))
    return _box(RRRUCalibration(model, theta, meas, free=["dtheta_11", "dL_11"], p0=T), 3e-3)


def _torque_fit() -> Problem:
    ex = FourierExcitation.from_robot("scara")
    xi = scara.lumped(scara.PlanarParams.from_robot("scara"), False)
    sim = ScaraTorqueSimulator(ex, ex.random(1, torch.Generator().manual_seed(0))[0], xi, False, DynamicsSettings())
    d = sim.simulate(200, seed=2).data
    return TorqueFitProblem(d["W"], d["tau_meas"], *physical_box())


def _excitation() -> Problem:
    return ExcitationProblem(FourierExcitation.from_robot("scara"))


def _elm() -> Problem:
    g = torch.Generator().manual_seed(0)
    X = torch.rand(60, 3, generator=g, **F64)
    Y = torch.sin(3 * X[:, :1]) + X[:, 1:2] ** 2
    return ELMProblem(X[:40], Y[:40], X[40:], Y[40:], n_hidden=8)


PROBLEMS = {"serial calibration": _serial, "PSD calibration": _psd, "3-RRRU calibration": _rrru,
            "SCARA torque fit": _torque_fit, "excitation design": _excitation, "ELM tuning": _elm}
SWARM = {"pso": dict(pop_size=16, max_iter=8), "ga": dict(pop_size=12, max_iter=6), "mma": dict(pop_size=6, max_iter=4)}


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_every_system_is_a_problem_and_every_solver_runs_on_it(name):
    prob = PROBLEMS[name]()
    assert isinstance(prob, Problem)
    x0 = prob.start()
    f0 = float(prob.fitness(x0[None])[0])
    finals = {}
    methods = dict(SWARM)
    if prob.has_residuals:
        methods["lm"] = dict(max_iter=20)
    for method, opts in methods.items():
        res = minimize(prob, method, seed=0, **opts)
        fx = float(prob.fitness(res.x.to(prob.dtype)[None])[0])
        assert fx == pytest.approx(res.fun, rel=1e-9, abs=1e-15), (method, fx, res.fun)
        assert bool(((res.x >= prob.lower) & (res.x <= prob.upper)).all()), method
        assert res.fun <= f0 * (1 + 1e-12), (method, res.fun, f0)
        assert len(res.history) == res.n_iter + 1
        finals[method] = res.fun
    assert min(finals.values()) < f0, finals  # someone improved on the start


def _tensors(data) -> list[torch.Tensor]:
    """The tensors of a simulated data set, whatever its form (Measurements, PSDData, dict)."""
    items = data.values() if isinstance(data, dict) else vars(data).values()
    return [v for v in items if isinstance(v, torch.Tensor)]


@pytest.mark.slow
def test_every_simulator_is_reproducible_from_its_seed_and_keeps_the_truth_apart():
    robot = shipped("ur5e", markers=["flange"])
    kr5 = shipped("kuka_kr5_arc", source="dh")
    centres = torch.tensor([[0.95, -0.30, 0.15], [0.85, 0.45, 0.55]], **F64)
    R = torch.stack([psd_frame(torch.tensor([0.1, 0.0, 1.0], **F64) - c, 0.3 * j) for j, c in enumerate(centres)])
    ex = FourierExcitation.from_robot("scara")
    xi = scara.lumped(scara.PlanarParams.from_robot("scara"), False)
    rrru_truth = torch.zeros(14, **F64)
    rrru_truth[0] = 1e-3
    sims = {"serial": simulated_robot(robot, SimConfig(noise=2e-5, seed=1)),
            "compliant arm": CompliantArm(shipped("ur5e", markers=["flange"]), ur5e_masses(robot), seed=1),
            "PSD": PSDSimulator(kr5, torch.zeros(kr5.n_params, **F64), Laser(), R, centres, q_noise=1e-5,
                                q0=torch.tensor([0.0, -1.4, 2.4, 0.0, 0.5, 0.0], **F64)),
            "SCARA torques": ScaraTorqueSimulator(ex, ex.random(1, torch.Generator().manual_seed(0))[0], xi, False,
                                                  DynamicsSettings()),
            "3-RRRU tracker": TrackerSimulator(RRRU(), spiral_trajectory(12), rrru_truth, 2e-5)}
    for name, sim in sims.items():
        a, b, c = sim.simulate(6, seed=5), sim.simulate(6, seed=5), sim.simulate(6, seed=6)
        ta, tb, tc = _tensors(a.data), _tensors(b.data), _tensors(c.data)
        assert ta and all(torch.equal(x, y) for x, y in zip(ta, tb)), name
        assert not all(torch.equal(x, y) for x, y in zip(ta, tc)), name
        assert a.truth, name
