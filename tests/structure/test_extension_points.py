"""ARCHITECTURE.md's "where a new piece goes", tested: a toy effect and a toy solver, each in one
file of ``tests/toys/`` that only registers it, run through ``calibrate``, the loop, a pose plan and
the command line with nothing else changed. (A new measurement type has no registry yet: it still
touches ``measure/observations.py`` and ``measure/io.py``.)

The data are simulated here, independently of the effect class: the toy error ``Δq = a q²`` is
added to the commanded angles before the robot's kinematics with known geometric errors, and
noise is drawn on top. The solvers see only the commands and the measured positions.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from torchcal.effects import EFFECTS
from torchcal.effects import registry as effect_registry
from torchcal.kinematics.robots import shipped
from torchcal.measure.data import Measurements
from torchcal.optim import base as solver_registry
from torchcal.pipelines.calibrate import calibrate
from torchcal.pipelines.loop.run import run_loop
from torchcal.sim.serial import SimConfig, random_configs, random_errors

TOYS = Path(__file__).resolve().parents[1] / "toys"
NOISE = 0.02e-3  # m per axis
QUAD = {"shoulder_lift_joint": 4e-3, "elbow_joint": -3e-3}  # 1/rad: up to ~10 mrad at the joint limits


@pytest.fixture(scope="module")
def toys():
    """Load the toy files (each registers its piece) and take the registrations back afterwards,
    so that no other test sees a toy among the loop's candidates or the solvers."""
    saved = dict(EFFECTS), dict(effect_registry._BY_TYPE), dict(solver_registry._REGISTRY)
    for name in ("toy_effect", "toy_solver"):
        spec = importlib.util.spec_from_file_location(f"torchcal_{name}", TOYS / f"{name}.py")
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    yield
    for reg, old in zip((EFFECTS, effect_registry._BY_TYPE, solver_registry._REGISTRY), saved):
        reg.clear()
        reg.update(old)


@pytest.fixture(scope="module")
def robot():
    return shipped("ur5e")


def _truth(robot, seed: int):
    """The robot's true geometry: nominal plus drawn joint and marker errors."""
    return random_errors(robot, robot.params(), SimConfig(seed=seed), torch.Generator().manual_seed(seed))


def _measured(robot, truth, n: int, seed: int, quad: dict[str, float]) -> Measurements:
    """``n`` rows of the robot with geometry ``truth`` and the toy error ``quad``, measured with noise."""
    g = torch.Generator().manual_seed(seed)
    q = random_configs(robot, n, g)
    dq = torch.zeros_like(q)
    for j, a in quad.items():
        i = robot.joint_names.index(j)
        dq[:, i] = a * q[:, i] ** 2
    p = robot.positions(q + dq, truth.values)
    p = p + NOISE * torch.randn(p.shape, generator=g, dtype=p.dtype)
    return Measurements(q=q, positions=p, marker_names=list(robot.marker_names),
                        joint_names=list(robot.joint_names), robot=robot.name)


def test_the_toys_are_registered_by_their_files_alone(toys):
    from torchcal.optim import available, get_solver, is_population
    assert "toy_quadratic" in EFFECTS and "toy_descent" in available(population=False)
    assert not is_population("toy_descent") and get_solver("toy_descent").name == "toy_descent"


def test_calibrate_runs_the_toy_solver_to_the_lm_solution(toys, robot):
    data = _measured(robot, _truth(robot, 0), 60, 1, {})
    kw = dict(free=["base.*"], register=False, prior=None)
    toy = calibrate(robot, data, method="toy_descent", **kw)
    lm = calibrate(robot, data, method="lm", **kw)
    assert toy.solver.method == "toy_descent"
    # the instrument frame alone: a well-posed problem both solvers must bring to one minimum
    assert toy.stages[-1].train.rmse == pytest.approx(lm.stages[-1].train.rmse, rel=1e-3)
    assert (toy.params.values[:6] - lm.params.values[:6]).abs().max() < 1e-6


@pytest.mark.slow
def test_the_loop_tries_and_names_the_toy_effect(toys, robot):
    truth = _truth(robot, 1)
    train, test = _measured(robot, truth, 150, 2, QUAD), _measured(robot, truth, 60, 3, QUAD)
    res = run_loop(robot, train, test, candidates=["toy_quadratic"], elm=False, log=None)
    found = [a for a in res.accepted if a.name == "toy_quadratic"]
    assert found, [c.to_json() for c in res.candidates]
    fitted = {n.split(".")[1]: v for n, v in found[0].params.items()}
    for j, a in QUAD.items():  # the modes it kept are the joints the toy error was put on, at their size
        assert fitted[j] == pytest.approx(a, rel=0.2)
    assert set(fitted) <= set(QUAD) | {j for j in fitted if abs(fitted[j]) < 3e-4}
    assert res.stages[-1].test.mean < 0.5 * res.stages[1].test.mean


def test_a_pose_plan_plans_for_the_toy_effect(toys, robot):
    from torchcal.pipelines.plan.run import plan_poses, plannable_effects
    assert "toy_quadratic" in plannable_effects()  # it reads nothing but the commanded angles
    plan = plan_poses(robot, 30, n_candidates=600, effects=["toy_quadratic"], seed=0)
    toy = {n: v for n, v in plan.std_errors.items() if n.startswith("toy_quadratic.")}
    assert toy and all(0 < v < 1e-3 for v in toy.values())  # 1/rad: 1e-3 would be ~10 mrad at ±π
    bare = plan_poses(robot, 30, n_candidates=600, seed=0)
    assert not any(n.startswith("toy_quadratic.") for n in bare.std_errors)


def test_the_command_line_offers_the_toy_solver(toys):
    from torchcal.cli.app import build_parser
    parser, _ = build_parser()
    args = parser.parse_args(["calibrate", "--robot", "ur5e", "--data", "x.csv", "--out", "o", "--method",
                              "toy_descent"])
    assert args.method == "toy_descent"
