"""CUDA against the CPU: the fused position kernel, the kinematics, a calibration, swarm restarts and a
small loop give the CPU's numbers on the GPU. Marked ``gpu`` (``python -m pytest -m gpu``); skipped
where CUDA is absent, so CI runs without a GPU. scripts/gpu_check.sh runs them on a lent machine."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from conftest import same_run
from torchcal import Robot, calibrate
from torchcal.kinematics.fk_fused import FusedPositions, compile_available
from torchcal.kinematics.robots import shipped
from torchcal.optim import FunctionProblem, get_solver, minimize_runs
from torchcal.pipelines.loop.run import run_loop
from torchcal.sim.serial import SimConfig, simulate, simulate_with_effects

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(),
                                 reason="no CUDA device here: the gpu tests compare CUDA with CPU results")]

REPO = Path(__file__).resolve().parents[2]
CUDA = torch.device("cuda")


def _kr5(device="cpu", markers=("smr@flange=0,0,0",)):
    return Robot.from_urdf(REPO / "urdf" / "kuka_kr5_arc.urdf", markers=list(markers), device=device)


@pytest.mark.parametrize("name", ["kr5_urdf", "tree_robot"])
def test_fused_kernel_on_cuda_equals_cpu_positions(request, name, make_params, make_q):
    """The KR5 (the graphs scripts/gpu_figures.py compiled before, found in inductor's cache) for both
    calls; the tree robot (prismatic, mimic, tilted axes, four markers) for the population call: each
    compilation costs seconds."""
    cpu = _kr5() if name == "kr5_urdf" else request.getfixturevalue(name)
    gpu = cpu.to(CUDA)
    q, full = make_q(cpu, 64, 1), make_params(cpu, 2)
    kern = FusedPositions(gpu, full.to(CUDA))
    assert kern.compiled == compile_available(CUDA)  # compiled by default on CUDA where Triton is there
    if name == "kr5_urdf":
        torch.testing.assert_close(kern(q.to(CUDA)).cpu(), cpu.positions(q, full), atol=1e-12, rtol=0)
    X = full + 0.01 * torch.randn(17, cpu.n_params, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    torch.testing.assert_close(kern(q.to(CUDA), X.to(CUDA)).cpu(), cpu.positions(q, X), atol=1e-12, rtol=0)
    assert kern.compiled == compile_available(CUDA)  # and it did not fall back


def test_kinematics_and_jacobian_on_cuda_equal_cpu(make_params, make_q):
    cpu = _kr5(markers=("flange", "smr@link6=0.01,0.02,0.1"))
    gpu = cpu.to(CUDA)
    q, p = make_q(cpu, 40, 4), make_params(cpu, 5)
    qg, pg = q.to(CUDA), p.to(CUDA)
    torch.testing.assert_close(gpu.positions(qg, pg).cpu(), cpu.positions(q, p), atol=1e-12, rtol=0)
    torch.testing.assert_close(gpu.fk(qg, pg).cpu(), cpu.fk(q, p), atol=1e-12, rtol=0)
    torch.testing.assert_close(gpu.param_jacobian(qg, pg).cpu(), cpu.param_jacobian(q, p), atol=1e-10, rtol=0)


def test_calibrate_on_cuda_equals_cpu():
    cpu = _kr5()
    data, _ = simulate(cpu, SimConfig(n=120, seed=11))
    test, _ = simulate(cpu, SimConfig(n=40, seed=12))
    a = calibrate(cpu, data, test=test, method="lm")
    b = calibrate(cpu.to(CUDA), data.to(CUDA), test=test.to(CUDA), method="lm")
    assert a.params.free_names == b.params.free_names and set(a.unidentifiable) == set(b.unidentifiable)
    # ~30 LM fits (the CV-chosen prior on 120 rows): reductions in another order leave a few nm, nrad
    torch.testing.assert_close(b.params.values.cpu(), a.params.values, atol=1e-8, rtol=0)
    assert abs(a.stages[-1]["test"]["mean_mm"] - b.stages[-1]["test"]["mean_mm"]) < 1e-9


def test_batched_restarts_on_cuda_equal_runs_alone():
    centre = torch.tensor([0.3, -1.2, 2.1, 0.7], dtype=torch.float64, device=CUDA)
    prob = FunctionProblem(lambda X: ((X - centre) ** 2).sum(-1), -3 * torch.ones(4, dtype=torch.float64, device=CUDA),
                           3 * torch.ones(4, dtype=torch.float64, device=CUDA))
    runs = minimize_runs(prob, "ldpso-bt", seeds=[0, 5, 9], n_max=30, n_min=8, max_iter=40)
    for r, seed in zip(runs, [0, 5, 9]):
        alone = get_solver("ldpso-bt", seed=seed, n_max=30, n_min=8, max_iter=40).minimize(prob)
        same_run(r, alone)  # other batch shapes, other CUDA kernels: to rounding


def test_small_loop_on_cuda_makes_the_cpu_decisions():
    robot = shipped("kuka_kr5_arc")
    noisy, _, _ = simulate_with_effects(robot, SimConfig(n=120, seed=2, noise=2e-5), ["joint_compliance"])
    train, test = noisy.subset(torch.arange(90)), noisy.subset(torch.arange(90, 120))
    a = run_loop(robot, train, test, elm=False, log=None)
    b = run_loop(robot.to(CUDA), train.to(CUDA), test.to(CUDA), elm=False, log=None)
    assert [s["name"] for s in a.stages] == [s["name"] for s in b.stages]
    assert [(c["name"], c["joints"]) for c in a.accepted] == [(c["name"], c["joints"]) for c in b.accepted]
    assert a.params.free_names == b.params.free_names
    torch.testing.assert_close(b.params.values.cpu(), a.params.values, atol=1e-8, rtol=0)
