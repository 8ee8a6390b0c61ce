"""Host waits per iteration, counted on the CPU (tests/host_syncs.py): what a GPU run would wait for."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from host_syncs import HostSyncs

from torchcal import Robot
from torchcal.measure.registration import register_base
from torchcal.optim import lm
from torchcal.optim.lm import LevenbergMarquardt, note_device_size
from torchcal.problems.base import LeastSquaresProblem
from torchcal.problems.calibration import CalibrationProblem
from torchcal.sim.serial import SimConfig, simulate

REPO = Path(__file__).resolve().parents[2]


def _waits(counts) -> int:
    # Robot._base reads whether a base is all zero only for CPU tensors (a shortcut a GPU never takes)
    return sum(v for (what, where), v in counts.items() if not where.endswith(" _base"))


def test_counter_sees_reads_data_dependent_sizes_and_copies():
    x = torch.arange(6.0)
    with HostSyncs() as h:
        x.sum().item(), x.tolist(), bool(x[0]), float(x[1])
        torch.nonzero(x > 2), x[x > 2], torch.tensor([1.0, 2.0])
        x[0] = 3.0  # a Python number written in: no copy
    kinds = sorted(k for k, _ in h.counts)
    assert kinds == ["__bool__", "__float__", "aten.index (boolean mask)", "aten.lift_fresh", "aten.nonzero",
                     "item", "tolist"]
    assert h.total == 7


def _count_per_step(solver: LevenbergMarquardt, prob):
    """Run ``solver`` on ``prob``, counting the host waits of each trial step: ``(result,
    waits per step, waits of the whole run)``."""
    per_step = []
    step = LevenbergMarquardt.step

    def counted(self, *a):
        with HostSyncs() as h:
            out = step(self, *a)
        per_step.append(_waits(h.counts))
        return out

    solver.step = counted.__get__(solver)
    with HostSyncs() as whole:
        res = solver.minimize(prob)
    return res, per_step, _waits(whole.counts)


def _rosenbrock() -> LeastSquaresProblem:
    """Rosenbrock's residuals ``(1 - x1, 10 (x2 - x1²))`` from ``(-1.2, 1)``. The Gauss-Newton step
    from there solves the linear residual exactly and the quadratic one along its tangent, landing
    at ``(1, -3.84)``: a sum of squares of 2343 against 24.2 at the start. With a damping of 1e-9
    the first step is that step, so it is rejected by a factor of 100, whatever the rounding."""
    def res(X):
        return torch.stack([1 - X[:, 0], 10 * (X[:, 1] - X[:, 0] ** 2)], -1)

    def jac(x):
        return torch.stack([torch.stack([-torch.ones_like(x[0]), torch.zeros_like(x[0])]),
                            torch.stack([-20 * x[0], 10 * torch.ones_like(x[0])])])

    lim = torch.full((2,), 10.0, dtype=torch.float64)
    return LeastSquaresProblem(res, -lim, lim, x0=torch.tensor([-1.2, 1.0], dtype=torch.float64), jacobian_fn=jac)


def test_lm_iteration_waits_at_most_three_times():
    """An accepted step reads the Cholesky status, the step's scalars and the new gradient test;
    a rejected one the first two. On a calibration problem: the Jacobian, the residuals and the
    parameter bookkeeping read nothing and copy no index list to the device. On Rosenbrock's
    residuals with a tiny initial damping: steps that are rejected (by construction, see
    :func:`_rosenbrock`) read two."""
    robot = Robot.from_urdf(REPO / "urdf" / "kuka_kr5_arc.urdf", markers=["smr@flange=0,0,0"])
    data = simulate(robot, SimConfig(n=40, seed=3))[0]
    ps = robot.params()
    ps.fix("smr.droll", "smr.dpitch", "smr.dyaw", "joint_a1.*", "joint_a6.d*", "smr.dz")
    ps = register_base(robot, data, ps)
    ps.values[ps.index("joint_a2.droll")] += 1.0  # a start far off: several steps
    ps.values[ps.index("joint_a3.dpitch")] -= 1.0
    for prob in (CalibrationProblem(robot, ps, data), _rosenbrock()):
        res, per_step, whole = _count_per_step(LevenbergMarquardt(mu0=1e-9, scaling="identity"), prob)
        rejected = res.extra["n_rejected"]
        assert res.converged and res.n_iter == len(per_step) >= 3
        assert max(per_step) <= 3  # taken or rejected, never more
        # the start (bounds, the columns fitted, the first gradient test) and, at the end, the history and results
        assert whole <= sum(per_step) + 7
    assert rejected > 0 and float(res.x.sub(1).abs().max()) < 1e-6  # Rosenbrock's: rejections, then (1, 1)


def test_small_problem_on_a_gpu_is_said_once(monkeypatch, caplog):
    monkeypatch.setattr(lm, "_told", set())
    cuda = torch.device("cuda")  # a device object only: nothing runs on it
    with caplog.at_level(logging.WARNING, logger="torchcal.optim.lm"):
        assert note_device_size(cuda, 900, 40)
        assert note_device_size(cuda, 450, 52)
        assert not note_device_size(cuda, 30_000, 40)
        assert not note_device_size(torch.device("cpu"), 900, 40)
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1
    assert "(900 residuals, 40 parameters) is too small to gain from cuda" in msgs[0] and "device='cpu'" in msgs[0]


def test_free_index_follows_changes_of_the_free_flags():
    robot = Robot.from_urdf(REPO / "urdf" / "kuka_kr5_arc.urdf", markers=["flange"])
    ps = robot.params()
    a = ps.free_index
    assert ps.free_index is a  # kept while the flags stay
    ps.fix("base.*")
    assert torch.equal(ps.free_index, torch.nonzero(ps.free).flatten()) and ps.free_index.numel() == a.numel() - 6
    ps.free = torch.zeros_like(ps.free)
    assert ps.free_index.numel() == 0 and ps.free_names == []
    with pytest.raises(KeyError):
        ps.fix("nothing.*")
