"""Independent swarm runs as one batch (torchcal.optim.minimize_runs) against the same runs one by one."""
from __future__ import annotations

import pytest
import torch

from conftest import same_run
from torchcal.kinematics.robots import shipped
from torchcal.measure.data import Measurements
from torchcal.optim import FunctionProblem, get_solver, minimize_runs
from torchcal.problems.calibration import CalibrationProblem

D = torch.float64
SEEDS = [0, 7, 3]


def _kr5_problem():
    """Seed 000's set-up, small: 24 DH errors of the KR5 arc from 12 flange positions, Σ‖ΔP‖ through the
    compact position kernel."""
    robot = shipped("kuka_kr5_arc", source="dh")
    dh = [n for n in robot.param_names if n.rsplit(".", 1)[1] in ("da", "dd", "dalpha", "dtheta")]
    ps = robot.params()
    ps.only(*dh)
    rng = torch.tensor([2.5e-4 if u == "m" else 0.05 for u in ps.units], dtype=D)
    ps.lower, ps.upper = torch.where(ps.free, -rng, 0 * rng), torch.where(ps.free, rng, 0 * rng)
    g = torch.Generator().manual_seed(1)
    truth = torch.where(ps.free, (2 * torch.rand(len(ps), generator=g, dtype=D) - 1) * rng, 0 * rng)
    q = 0.8 * (2 * torch.rand(12, robot.dof, generator=g, dtype=D) - 1)
    data = Measurements(q, robot.positions(q, truth), list(robot.marker_names), list(robot.joint_names))
    return CalibrationProblem(robot, ps, data, fitness="sum_norm")


@pytest.mark.parametrize("method,options", [("pso", dict(pop_size=24, max_iter=15)),
                                            ("ldpso-bt", dict(n_max=24, n_min=6, max_iter=15))])
def test_batched_runs_equal_runs_alone(method, options):
    prob = _kr5_problem()
    runs = minimize_runs(prob, method, seeds=SEEDS, **options)
    assert len(runs) == len(SEEDS)
    for r, seed in zip(runs, SEEDS):
        alone = get_solver(method, seed=seed, **options).minimize(prob)
        assert alone.n_iter == options["max_iter"]  # the budget, not a tolerance, ends these runs
        same_run(r, alone)
    assert len({r.fun for r in runs}) == len(SEEDS)  # different seeds really gave different runs


def _plateaus(X):
    """A staircase: the best fitness stops improving once a run reaches a step it cannot leave,
    at an iteration that depends on the run. The steps are 1/4 high: the last bits of a point
    change the fitness only on a step's edge, so when each run stops is decided by the swarm, not
    by rounding, and the runs' counts compare exactly."""
    return torch.floor(4 * ((X - 0.3) ** 2).sum(-1)) / 4


def test_each_run_stops_on_its_own_and_leaves_the_batch():
    calls = []

    def fitness(X):
        calls.append(X.shape[0])
        return _plateaus(X)

    prob = FunctionProblem(fitness, -3 * torch.ones(3, dtype=D), 3 * torch.ones(3, dtype=D))
    opts = dict(pop_size=5, max_iter=60, stall_iter=4, w=0.5)
    seeds = [0, 1, 2, 3, 4]
    runs = minimize_runs(prob, "pso", seeds=seeds, **opts)
    for r, seed in zip(runs, seeds):
        calls_before = len(calls)
        alone = get_solver("pso", seed=seed, **opts).minimize(prob)
        same_run(r, alone)
        assert len(calls) - calls_before == alone.n_iter + 1
    stops = sorted(r.n_iter for r in runs)
    assert len(set(stops)) > 1 and stops[-1] < 60  # they stop apart, and every one before max_iter
    assert all(r.converged and "over the last 4 iterations" in r.message for r in runs)
    # the batch evaluated, per iteration, five points for every run still going
    batch = calls[: stops[-1] + 1]
    assert batch == [5 * sum(s >= t for s in stops) for t in range(stops[-1] + 1)]


def test_batched_runs_refused_for_solvers_without_a_batch():
    prob = FunctionProblem(_plateaus, -torch.ones(2, dtype=D), torch.ones(2, dtype=D))
    with pytest.raises(ValueError, match="cannot run several runs as one batch"):
        minimize_runs(prob, "cpso", seeds=[0, 1], pop_size=4, max_iter=2)
    with pytest.raises(ValueError, match="at least one seed"):
        minimize_runs(prob, "pso", seeds=[], pop_size=4, max_iter=2)
    with pytest.raises(ValueError, match="stall_iter"):
        get_solver("pso", stall_iter=0)
