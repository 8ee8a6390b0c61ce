"""3-RRRU parallel robot (seed 004): IK/FK round trips, implicit gradients, workspace errors,
identifiability and calibration on simulated data."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_params import PARAM_NAMES
from torchcal.kinematics.rrru_paths import line_trajectories, spiral_trajectory
from torchcal.kinematics.rrru_workspace import WorkspaceError
from torchcal.optim import get_solver
from torchcal.problems.rrru import DecorrelatedProblem, RRRUCalibration, identifiability
from torchcal.sim.rrru import simulate_tracker

MM = 1e-3
# seed-sized errors (rad, m), different per branch
TRUTH = torch.tensor([0.0009, -0.0006, 0.0010, 0.25 * MM, 0.19 * MM, -0.14 * MM, 0.20 * MM, 0.16 * MM,
                      -0.12 * MM, 0.29 * MM, 0.22 * MM, -0.18 * MM, -0.97 * MM, 0.71 * MM], dtype=torch.float64)
FREE = [n for n in PARAM_NAMES if n != "dr"]


@pytest.fixture(scope="module")
def model() -> RRRU:
    torch.set_num_threads(1)
    return RRRU()


def workspace_points(n: int, seed: int) -> torch.Tensor:
    """``(n, 3)`` points in the working region: a cylinder of radius 0.5 m about the vertical axis,
    z from 0.5 to 0.9 m (inside the reachable, singularity-free workspace)."""
    g = torch.Generator().manual_seed(seed)
    r = 0.5 * torch.rand(n, generator=g, dtype=torch.float64).sqrt()
    a = 2 * math.pi * torch.rand(n, generator=g, dtype=torch.float64)
    z = 0.5 + 0.4 * torch.rand(n, generator=g, dtype=torch.float64)
    return torch.stack([r * a.cos(), r * a.sin(), z], -1)


def random_params(P: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([0.005] * 3 + [2 * MM] * 11, dtype=torch.float64)
    return scale * (2 * torch.rand(P, 14, generator=g, dtype=torch.float64) - 1)


# ------------------------------------------------------------------------------- kinematics
def test_fk_ik_round_trip_across_workspace(model):
    p = workspace_points(400, 0)
    theta = model.ik(p)
    p_back = model.fk(theta)                       # default Newton start: the workspace centre
    assert (p_back - p).abs().max() < 1e-9
    assert (model.ik(p_back) - theta).abs().max() < 1e-9
    # and with a population of error vectors: (P, N, 3)
    params = random_params(3, 1)
    th = model.ik(p, params)
    assert th.shape == (3, 400, 3)
    pb = model.fk(th, params)
    assert pb.shape == (3, 400, 3)
    assert (pb - p).abs().max() < 1e-9
    assert (model.ik(pb, params) - th).abs().max() < 1e-9
    # (P, N, 3) paired with (P, 14); a wrong leading size is refused
    assert (model.fk(th[:, :5], params) - p[:5]).abs().max() < 1e-9
    with pytest.raises(ValueError, match="paired"):
        model.fk(th[:2], params)


def test_ik_fk_from_angles(model):
    # IK(FK(θ)) = θ for angles of reachable poses, each branch perturbed
    theta = model.ik(workspace_points(200, 2)) + 0.02 * torch.randn(200, 3, generator=torch.Generator().manual_seed(3),
                                                                     dtype=torch.float64)
    p = model.fk(theta)
    assert (model.ik(p) - theta).abs().max() < 1e-9
    assert model.constraint(p, theta).abs().max() < 1e-12


def test_branch_chain_reaches_platform(model):
    """Independent check of the geometry: walking each branch as a serial chain with the IK's
    active and passive angles lands on the platform joint B_i = p + r e_i, and the seed's
    polynomial form of eq. 8 holds."""
    params = random_params(1, 4)[0]
    p = workspace_points(50, 5)
    theta, (th2, th3) = model.ik(p, params, return_passive=True)
    g = model.geometry(params)
    th1 = theta + g["dtheta"]
    for i in range(3):
        e, t = model.E[i], model.T[i]
        z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        u1 = th1[:, i, None].cos() * e + th1[:, i, None].sin() * z
        a12 = th1[:, i, None] + th2[:, i, None]
        u2 = a12.cos() * e + a12.sin() * z
        u3 = th3[:, i, None].cos() * u2 + th3[:, i, None].sin() * t
        A1 = (model.R + params[12]) * e
        B = A1 + g["L1"][i] * u1 + g["L2"][i] * u2 + g["L3"][i] * u3
        assert (B - (p + (model.r + params[13]) * e)).abs().max() < 1e-12
        assert bool((th3[:, i].abs() <= math.pi / 2).all())          # the seed's cos θ_i3 >= 0
        # eq. 8: |B - A_i2|² = L2² + L3² + 2 L2 sqrt(L3² - y²)
        y = p @ t
        lhs = (B - A1 - g["L1"][i] * u1).pow(2).sum(-1)
        L2, L3 = g["L2"][i], g["L3"][i]
        assert (lhs - (L2 ** 2 + L3 ** 2 + 2 * L2 * (L3 ** 2 - y ** 2).sqrt())).abs().max() < 1e-12


# ------------------------------------------------------------------------------- gradients
def test_implicit_gradients_match_finite_differences(model):
    p = workspace_points(4, 6)
    theta = model.ik(p).requires_grad_(True)
    params = random_params(2, 7).requires_grad_(True)
    fk = lambda th, q: model.fk(th, q, p0=p)  # noqa: E731
    assert torch.autograd.gradcheck(fk, (theta, params), eps=1e-6, atol=1e-7, rtol=1e-5)
    # the analytic Jacobians agree with autograd through the implicit node
    J = model.param_jacobian(theta.detach(), params[0].detach())            # (4, 3, 14)
    Ja = torch.autograd.functional.jacobian(lambda q: model.fk(theta.detach(), q), params[0].detach())
    assert (J - Ja).abs().max() < 1e-12
    Jt = model.joint_jacobian(theta.detach(), params[0].detach())           # (4, 3, 3)
    Jta = torch.autograd.functional.jacobian(lambda th: model.fk(th, params[0].detach()), theta.detach())
    assert (Jt - torch.einsum("nink->nik", Jta.reshape(4, 3, 4, 3))).abs().max() < 1e-12


def test_backward_does_not_unroll_newton(model):
    # the graph holds one node for the whole solve, whatever the number of iterations
    theta = model.ik(workspace_points(3, 8)).requires_grad_(True)
    p = model.fk(theta)
    assert type(p.grad_fn).__name__.startswith("_ImplicitFK")
    assert p.grad_fn.next_functions[0][0] is not None   # tensor inputs: theta, params, p0


# ------------------------------------------------------------------------------- workspace errors
@pytest.mark.parametrize("point, words", [
    ([3.0, 0.0, 0.7], "out of reach"),
    ([0.0, 0.0, -0.5], "not below the static platform"),
    ([0.0, 0.9, 0.7], "tangential offset"),
])
def test_ik_outside_workspace_raises(model, point, words):
    p = torch.tensor([[0.0, 0.0, 0.7], point], dtype=torch.float64)
    with pytest.raises(WorkspaceError, match=words) as exc:
        model.ik(p)
    assert "point [1]" in str(exc.value)


def test_fk_unreachable_angles_raise_not_nan(model):
    theta = torch.tensor([[0.3, 0.3, 0.3], [3.0, -2.5, 1.0]], dtype=torch.float64)
    with pytest.raises(WorkspaceError, match="FK: no solution"):
        model.fk(theta)
    out = model.fk(theta, on_failure="nan")                 # what optimisers ask for
    assert torch.isfinite(out[0]).all() and torch.isnan(out[1]).all()


def test_bad_shapes(model):
    with pytest.raises(ValueError, match=r"\(14,\) or \(P, 14\)"):
        model.fk(torch.zeros(2, 3, dtype=torch.float64), torch.zeros(13))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        model.ik(torch.zeros(2, 2))


# ------------------------------------------------------------------------------- identification
def test_identifiability_drops_dr(model):
    S = spiral_trajectory()
    theta = model.ik(S)
    rep = identifiability(model, theta, TRUTH, p0=S)
    assert rep.rank == 13 and rep.dropped == ["dr"]
    assert "dR" in rep.reasons["dr"] and abs(rep.relations["dr"]["dR"] + 1.0) < 1e-9


def test_lm_recovers_errors_from_noise_free_data(model):
    S = spiral_trajectory()
    L = line_trajectories().reshape(-1, 3)
    T = torch.cat([S, L[::3]])
    theta, _, meas = simulate_tracker(model, T, TRUTH)            # noise-free
    prob = RRRUCalibration(model, theta, meas, free=FREE, p0=T)
    res = get_solver("lm").minimize(prob)
    eff = TRUTH[[PARAM_NAMES.index(n) for n in FREE]].clone()
    eff[FREE.index("dR")] = TRUTH[12] - TRUTH[13]                  # dR absorbs -dr
    assert (res.x - eff).abs().max() < 1e-9
    # residuals batched over a population, analytic Jacobian = forward-mode autograd
    X = torch.stack([res.x, torch.zeros_like(res.x)])
    assert prob.residuals(X).shape == (2, 3 * T.shape[0])
    J = prob.jacobian(res.x)
    Jf = torch.autograd.functional.jacobian(lambda x: prob.residuals(x[None])[0], res.x)
    assert (J - Jf).abs().max() < 1e-10


def test_ga_recovers_errors_on_decorrelated_coding(model):
    S = spiral_trajectory()
    theta, _, meas = simulate_tracker(model, S, TRUTH)
    prob = RRRUCalibration(model, theta, meas, free=FREE, p0=S)
    dec = DecorrelatedProblem(prob)
    res = get_solver("ga", seed=0, max_iter=400, mutation_scale=0.05).minimize(dec)
    x = dec.to_x(res.x)
    rms = prob.residuals(x[None]).pow(2).mean().sqrt()
    assert rms < 0.01 * MM                         # from ~6 mm before
    assert prob.residuals(torch.zeros(1, 13, dtype=torch.float64)).pow(2).mean().sqrt() > 1 * MM


@pytest.mark.slow
def test_pipeline_study_reproduces_the_lesson_with_lm():
    """studies.rrru.study end to end (short GA, no Monte Carlo): 13 of 14 parameters identifiable
    (dr is not), LM on the spiral compensates both trajectories within 4 σ of the tracker noise,
    LM on the lines does not on the spiral (the seed's lesson)."""
    from torchcal.studies.rrru import study

    s = study(noise_mm=0.02, seed=0, ga_iter=20, mc_draws=0, raw_ga=False)["summary"]
    assert s["identifiable"] == "13 of 14" and s["dropped"] == ["dr"]
    assert s["before_max_mm"] > 5.0
    assert max(s["lm"]["spiral_cal_on_spiral_max_mm"], s["lm"]["spiral_cal_on_lines_max_mm"]) <= 4 * 0.02
    assert s["lm"]["line_cal_on_spiral_max_mm"] > 4 * 0.02
