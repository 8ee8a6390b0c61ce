"""The compact position-only kinematics path (torchcal.kinematics.fk_compact) against the general one."""
from __future__ import annotations

import pytest
import torch

from torchcal.kinematics.transforms import matrix_to_quat
from torchcal.kinematics.fk_compact import PositionKernel
from torchcal.measure.data import Measurements
from torchcal.problems.calibration import CalibrationProblem

FREE_SETS = {
    "all": lambda n: True,
    "dh-and-marker-points": lambda n: n.rsplit(".", 1)[1] in ("da", "dd", "dalpha", "dtheta", "dx", "dy", "dz"),
    "no-base": lambda n: not n.startswith("base."),
    "offsets": lambda n: n.endswith((".offset", ".dtheta")),
    "base-only": lambda n: n.startswith("base."),
}


def _population(robot, full, free, P, seed):
    g = torch.Generator().manual_seed(seed)
    X = full[free] + 0.02 * torch.randn(P, int(free.sum()), generator=g, dtype=torch.float64)
    F = full.expand(P, -1).clone()
    F[:, free] = X
    return X, F


@pytest.mark.parametrize("name", ["kr5", "modified_arm", "scara", "tree_robot"])
@pytest.mark.parametrize("free_set", list(FREE_SETS))
def test_kernel_equals_general_positions(request, name, free_set, make_params, make_q):
    robot = request.getfixturevalue(name)
    q, full = make_q(robot, 9, 1), make_params(robot, 2)  # non-zero fixed values everywhere
    free = torch.tensor([FREE_SETS[free_set](n) for n in robot.param_names])
    if not bool(free.any()):
        pytest.skip(f"{name} has no parameter in the set {free_set}")
    kern = PositionKernel(robot, q, full, torch.nonzero(free).flatten())
    for P, seed in ((4, 3), (1, 4), (7, 5), (2, 6)):  # grows, shrinks and grows the work buffers
        X, F = _population(robot, full, free, P, seed)
        ref = robot.positions(q, F)  # (P, N, M, 3)
        out = kern(X).reshape(ref.shape)
        torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def test_kernel_observation_subset_and_no_base(tree_robot, make_params, make_q):
    robot = tree_robot
    q, full = make_q(robot, 6, 7), make_params(robot, 8)
    rows = torch.tensor([0, 0, 2, 3, 5, 5, 1])
    cols = torch.tensor([0, 3, 1, 2, 0, 3, 1])
    idx = torch.arange(robot.n_params)
    kern = PositionKernel(robot, q, full, idx, rows, cols, base=False)
    X, F = _population(robot, full, torch.ones(robot.n_params, dtype=torch.bool), 3, 9)
    ref = robot.positions(q, F, base=False)[:, rows, cols]
    torch.testing.assert_close(kern(X), ref, atol=1e-12, rtol=0)
    assert kern.n_obs == rows.numel()


@pytest.mark.parametrize("fitness", ["sum_norm", "sse"])
def test_problem_fitness_compact_equals_general(kr5, make_q, fitness):
    robot = kr5
    q = make_q(robot, 12, 3)
    truth = 1e-3 * torch.randn(robot.n_params, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    data = Measurements(q, robot.positions(q, truth), list(robot.marker_names), list(robot.joint_names))
    ps = robot.params()
    ps.fix("base.*")
    ps.values[0] = 0.3  # a fixed, non-zero base x: must reach the kernel
    ps.lower, ps.upper = ps.lower.clamp(min=-0.01), ps.upper.clamp(max=0.01)
    make = lambda c: CalibrationProblem(robot, ps, data, fitness=fitness, compact=c)  # noqa: E731
    fast, slow = make(True), make(False)
    X = fast.lower + (fast.upper - fast.lower) * torch.rand(6, fast.dim, generator=torch.Generator().manual_seed(1),
                                                            dtype=torch.float64)
    torch.testing.assert_close(fast.fitness(X), slow.fitness(X), atol=0, rtol=1e-12)
    assert fast._kernel_cache is not None and slow.__dict__.get("_kernel_cache") is None
    # changing a fixed value in place rebuilds the kernel
    ps.values[0] = -0.2
    torch.testing.assert_close(fast.fitness(X), slow.fitness(X), atol=0, rtol=1e-12)


def test_problem_fitness_falls_back_for_other_blocks(kr5, make_q):
    robot = kr5
    q = make_q(robot, 8, 4)
    T = robot.fk(q)
    data = Measurements(q, T[:, :, :3, 3], list(robot.marker_names), list(robot.joint_names),
                        quaternions=matrix_to_quat(T[:, :, :3, :3]))
    ps = robot.params()
    ps.fix("base.*")
    prob = CalibrationProblem(robot, ps, data, fitness="sse", rot_weight=0.1)
    X = 1e-4 * torch.ones(2, prob.dim, dtype=torch.float64)
    assert prob._kernels() is None
    r = prob.residuals(X)
    torch.testing.assert_close(prob.fitness(X), (r * r).sum(-1), atol=0, rtol=1e-13)  # a sum: to rounding


def test_problem_fitness_on_partial_axes_takes_the_general_path(kr5, make_q):
    robot = kr5
    q = make_q(robot, 10, 5)
    p = robot.positions(q)
    p[::3, 0, 1] = float("nan")  # a marker seen in x and z only on every third row
    data = Measurements(q, p + 1e-4, list(robot.marker_names), list(robot.joint_names))
    ps = robot.params()
    ps.fix("base.*")
    fast, slow = (CalibrationProblem(robot, ps, data, fitness="sse", compact=c)
                  for c in (True, False))
    X = 1e-4 * torch.randn(4, fast.dim, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    torch.testing.assert_close(fast.fitness(X), slow.fitness(X), atol=0, rtol=1e-12)
    assert fast._kernels() is None and bool(torch.isfinite(fast.fitness(X)).all())
