"""The fused position kernel (torchcal.kinematics.fk_fused) against Robot.positions, the reference."""
from __future__ import annotations

import logging

import pytest
import torch

from pathlib import Path

from torchcal import Robot
from torchcal.kinematics.fk_fused import FusedPositions, compile_available

REPO = Path(__file__).resolve().parents[2]
ROBOTS = ["kr5", "modified_arm", "scara", "tree_robot"]


def _population(full, free, P, seed):
    g = torch.Generator().manual_seed(seed)
    X = full[free] + 0.02 * torch.randn(P, int(free.sum()), generator=g, dtype=torch.float64)
    F = full.expand(P, -1).clone()
    F[:, free] = X
    return X, F


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("base", [True, False])
def test_fused_equals_positions(request, name, base, make_params, make_q):
    robot = request.getfixturevalue(name)
    q, full = make_q(robot, 11, 1), make_params(robot, 2)  # non-zero values everywhere, base included
    kern = FusedPositions(robot, full, base=base, compile=False)
    torch.testing.assert_close(kern(q), robot.positions(q, full, base=base), atol=1e-12, rtol=0)
    free = torch.tensor([not n.endswith(".dyaw") for n in robot.param_names])  # some fixed, some free
    kern = FusedPositions(robot, full, torch.nonzero(free).flatten(), base=base, compile=False)
    for P, seed in ((5, 3), (1, 4)):
        X, F = _population(full, free, P, seed)
        torch.testing.assert_close(kern(q, X), robot.positions(q, F, base=base), atol=1e-12, rtol=0)


def test_fused_nominal_and_shipped_urdf(make_q):
    robot = Robot.from_urdf(REPO / "urdf" / "kuka_kr5_arc.urdf", markers=["flange", "smr@link6=0.01,0.02,0.1"])
    q = make_q(robot, 7, 5)
    torch.testing.assert_close(FusedPositions(robot, compile=False)(q), robot.positions(q), atol=1e-12, rtol=0)


def test_fused_observation_subset(tree_robot, make_params, make_q):
    robot = tree_robot
    q, full = make_q(robot, 6, 7), make_params(robot, 8)
    rows, cols = torch.tensor([0, 0, 2, 3, 5, 5, 1]), torch.tensor([0, 3, 1, 2, 0, 3, 1])
    kern = FusedPositions(robot, full, None, rows, cols, base=False, compile=False)
    X, F = _population(full, torch.ones(robot.n_params, dtype=torch.bool), 3, 9)
    torch.testing.assert_close(kern(q, X), robot.positions(q, F, base=False)[:, rows, cols], atol=1e-12, rtol=0)
    torch.testing.assert_close(kern(q), robot.positions(q, full, base=False)[rows, cols], atol=1e-12, rtol=0)


@pytest.mark.slow
@pytest.mark.skipif(not compile_available("cpu"), reason="torch.compile has no C++ compiler on this machine")
def test_fused_compiled_on_cpu(kr5, make_params, make_q):
    """The compiled kernel (inductor's C++ loop) gives the eager numbers for two batch sizes, with
    one compilation (the batch size is symbolic). The population call is compiled and checked on
    CUDA (tests/structure/test_gpu_matches_cpu.py) and by scripts/bench_fk.py: each compilation costs tens of seconds here."""
    full = make_params(kr5, 7)
    kern = FusedPositions(kr5, full, compile=True)
    assert kern.compiled
    for n in (13, 40):
        qn = make_q(kr5, n, n)
        torch.testing.assert_close(kern(qn), kr5.positions(qn, full), atol=1e-12, rtol=0)
    assert kern.compiled  # no fallback to eager happened


def test_fused_falls_back_to_eager_with_one_log_line(kr5, make_q, caplog, monkeypatch):
    """A compiler failure at the first call is logged once; the kernel then runs eagerly."""
    kern = FusedPositions(kr5, compile=False)
    q = make_q(kr5, 4, 1)
    ref = kern(q)

    def broken(*a, **k):
        raise RuntimeError("no code generator\nsecond line")

    kern.compiled, kern._fns = True, {"fixed": broken, "population": broken}
    with caplog.at_level(logging.WARNING, logger="torchcal.kinematics.fk_fused"):
        torch.testing.assert_close(kern(q), ref, atol=0, rtol=0)
        torch.testing.assert_close(kern(q), ref, atol=0, rtol=0)
    msgs = [r.getMessage() for r in caplog.records]
    assert len(msgs) == 1 and "no code generator" in msgs[0] and "eagerly" in msgs[0]
    assert not kern.compiled
