"""Tests of torchcal.dynamics: SCARA regressor, generic Lagrangian regressor, Fourier excitation
design, and identification (least squares, RLS, chaotic PSO with seed 001's settings)."""
from __future__ import annotations

import math

import pytest
import torch
from torch.func import jvp

from torchcal.dynamics import excitation as exc
from torchcal.problems import dynamics as idf
from torchcal.problems.excitation import ExcitationProblem
from torchcal.dynamics import lagrangian, scara
from torchcal.optim import get_solver
from torchcal.optim.ga import GeneticAlgorithm

D = torch.float64
SEED_SWARM = dict(pop_size=200, max_iter=200, c1=1.3, c2=1.8, w=(0.9, 0.2))


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def states(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (3 * torch.randn(n, 2, generator=g, dtype=D), 2 * torch.randn(n, 2, generator=g, dtype=D),
            5 * torch.randn(n, 2, generator=g, dtype=D))


@pytest.fixture(scope="module")
def truth() -> scara.PlanarParams:
    return scara.PlanarParams.from_robot("scara")


# -- model --------------------------------------------------------------------------------------
@pytest.mark.parametrize("friction", [False, True])
def test_regressor_reproduces_lagrangian(truth, friction):
    p = scara.PlanarParams(**{k: getattr(truth, k) for k in ("m1", "m2", "I1", "I2", "a1", "a2", "x1", "x2")},
                           **(dict(fv=(0.8, 0.5), fc=(1.2, 0.7)) if friction else {}))
    q, qd, qdd = states(200, 0)
    W = scara.regressor(q, qd, qdd, friction)
    assert W.shape == (200, 2, 10 if friction else 6)
    tau_direct = scara.lagrangian_torque(p, q, qd, qdd)
    assert torch.allclose(W @ scara.lumped(p, friction), tau_direct, rtol=0, atol=1e-9)
    # the base form carries the same model
    Wb = scara.base_regressor(q, qd, qdd)
    assert torch.allclose(Wb @ scara.base_params(p), W[..., :6] @ scara.lumped(p), rtol=0, atol=1e-12)


def test_lumped_parameter_ties(truth):
    xi = scara.lumped(truth)
    A, B, C = scara.base_params(truth).tolist()
    assert xi.tolist() == pytest.approx([A, C, B, C, C, B])
    assert A == pytest.approx(0.07 + 0.04 + 7.0 * 0.17 ** 2 + 4.5 * (0.325 ** 2 + 0.15 ** 2))
    lo, hi = idf.physical_box()
    assert bool(((xi > lo) & (xi < hi)).all())
    # not centred on the truth: a swarm starting at the box centre gets no free answer
    assert bool(((xi - lo) / (hi - lo) < 0.3).all())


def test_generic_serial_regressor_matches_planar_model(truth):
    """Autodiff Lagrangian of the 4-DOF DH SCARA (inertials from robot_data) gives the planar
    model on joints 1-2, and the planar gravity torques when gravity is put in the plane."""
    from torchcal.kinematics.robots import link_inertials, shipped

    robot = shipped("scara", source="dh", markers=["link1", "link2", "link3", "link4"])
    pi = lagrangian.inertial_vector(link_inertials("scara"))
    g = torch.Generator().manual_seed(3)
    q2, qd2, qdd2 = states(24, 1)
    q = torch.cat([q2, 0.2 * torch.rand(24, 1, generator=g, dtype=D), torch.randn(24, 1, generator=g, dtype=D)], 1)
    qd = torch.cat([qd2, torch.randn(24, 2, generator=g, dtype=D)], 1)
    qdd = torch.cat([qdd2, torch.randn(24, 2, generator=g, dtype=D)], 1)
    planar = scara.regressor(q2, qd2, qdd2) @ scara.lumped(truth)

    Y = lagrangian.serial_regressor(robot, q, qd, qdd)  # gravity along -z: no work on joints 1-2
    assert Y.shape == (24, 4, 40)
    tau = Y @ pi
    assert torch.allclose(tau[:, :2], planar, rtol=0, atol=1e-9)
    assert torch.allclose(tau[:, 2:], torch.zeros_like(tau[:, 2:]), atol=1e-12)  # massless quill

    gy = 9.81
    tau_g = lagrangian.serial_regressor(robot, q, qd, qdd, gravity=(0.0, -gy, 0.0)) @ pi
    c1, c12 = torch.cos(q2[:, 0]), torch.cos(q2[:, 0] + q2[:, 1])
    grav = torch.stack([gy * ((truth.m1 * truth.x1 + truth.m2 * truth.a1) * c1 + truth.m2 * truth.x2 * c12),
                        gy * truth.m2 * truth.x2 * c12], 1)
    assert torch.allclose(tau_g[:, :2], planar + grav, rtol=0, atol=1e-9)


# -- excitation ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ex() -> exc.FourierExcitation:
    return exc.FourierExcitation.from_robot("scara")


def test_fourier_derivatives_and_layout(ex):
    x = ex.random(1, torch.Generator().manual_seed(0))[0]
    t = torch.linspace(0.0, 7.0, 50, dtype=D)
    q, qd, qdd = ex.evaluate(x, t)
    assert q.shape == (50, 2)
    _, dq = jvp(lambda s: ex.evaluate(x, s)[0], (t,), (torch.ones_like(t),))
    _, dqd = jvp(lambda s: ex.evaluate(x, s)[1], (t,), (torch.ones_like(t),))
    assert torch.allclose(dq, qd, atol=1e-12) and torch.allclose(dqd, qdd, atol=1e-12)
    # periodic, and q0 is the mean position over a period
    qa, _, _ = ex.evaluate(x, ex.times(400))
    assert torch.allclose(qa.mean(0), ex.split(x)[2], atol=1e-12)
    assert ex.dim == 14 and ex.names()[6] == "j1.q0"


def test_projection_enforces_limits(ex):
    g = torch.Generator().manual_seed(1)
    raw = ex.random(64, g, feasible=False)
    fine = ex.times(20 * ex.n_samples)
    assert bool((ex.violation(raw, fine) > 0).any())  # the box alone is not feasible
    proj = ex.project(raw)
    assert float(ex.violation(proj, fine).max()) == 0.0
    # a feasible vector is left as it is, up to the between-samples margin
    again = ex.project(proj)
    assert torch.allclose(again, proj, rtol=1e-3, atol=0)
    # penalty mode charges the raw, infeasible vectors
    pen = ExcitationProblem(ex, constraint="penalty")
    sc = ExcitationProblem(ex)
    v = ex.violation(raw)
    assert bool((pen.fitness(raw) >= pen.penalty * v).all())
    assert torch.allclose(pen.fitness(proj), sc.fitness(proj), rtol=1e-3)


def test_condition_number_objective_is_batched(ex):
    prob = ExcitationProblem(ex)
    X = ex.random(5, torch.Generator().manual_seed(2))
    f = prob.fitness(X)
    assert f.shape == (5,)
    for i in range(5):
        W = prob.observation_matrix(X[i:i + 1])[0]
        s = torch.linalg.svdvals(W)
        assert float(f[i]) == pytest.approx(float(s[0] / s[-1]), rel=1e-8)
        assert float(prob.fitness(X[i:i + 1])[0]) == pytest.approx(float(f[i]), rel=1e-12)
    assert math.isinf(float(prob.fitness(torch.zeros(1, ex.dim, dtype=D))[0]))  # no motion


def test_optimised_excitation_beats_random_and_is_feasible(ex):
    prob = ExcitationProblem(ex)
    g = torch.Generator().manual_seed(0)
    X_rand = ex.random(20, g)
    c_rand = prob.fitness(X_rand)
    ga = get_solver("ga", seed=0, max_iter=60, **GeneticAlgorithm.PRESETS["seed001"]).minimize(prob)
    grad = get_solver("lbfgs", max_iter=25).minimize(ExcitationProblem(ex, x0=X_rand[0]))
    fine = ex.times(20 * ex.n_samples)
    for r in (ga, grad):
        x = prob.decode(r.x[None])
        assert float(ex.violation(x, fine)[0]) == 0.0
        assert r.fun < float(c_rand[0]) and r.fun < float(c_rand.median())
        assert float(prob.fitness(r.x[None])[0]) == pytest.approx(r.fun, rel=1e-9)
    assert grad.fun < float(c_rand.min())


# -- identification -----------------------------------------------------------------------------
def test_least_squares_recovers_truth_noise_free(ex, truth):
    x = ex.random(1, torch.Generator().manual_seed(4))[0]
    for friction in (False, True):
        p = scara.PlanarParams(**{k: getattr(truth, k) for k in ("m1", "m2", "I1", "I2", "a1", "a2", "x1", "x2")},
                               fv=(0.8, 0.5), fc=(1.2, 0.7))
        xi = scara.lumped(p, friction)
        W = scara.regressor(*ex.evaluate(x, ex.times(400)), friction)
        tau = W @ xi
        assert torch.allclose(idf.ols(W, tau), xi, rtol=0, atol=1e-9)
        xr, hist = idf.rls(W, tau)
        assert hist.shape == (400, xi.numel())
        # RLS with λ = 1 and P0 = δ I is the ridge solution with weight 1/δ
        A, y = W.reshape(-1, xi.numel()), tau.reshape(-1)
        ridge = torch.linalg.solve(A.T @ A + torch.eye(xi.numel(), dtype=D) / 1e6, A.T @ y)
        assert torch.allclose(xr, ridge, rtol=1e-9, atol=0)
        assert torch.allclose(xr, xi, rtol=1e-4, atol=0)
        assert float(idf.torque_rmse(W, tau, xi)) < 1e-12


@pytest.fixture(scope="module")
def seed_problem(ex, truth):
    """Seed 001's identification problem: GA-designed excitation, noisy torques and states,
    physical box bounds; plus a validation trajectory."""
    prob = ExcitationProblem(ex)
    ga = get_solver("ga", seed=0, **GeneticAlgorithm.PRESETS["seed001"]).minimize(prob)
    g = torch.Generator().manual_seed(1000)
    xi = scara.lumped(truth)

    def data(x):
        q, qd, qdd = ex.evaluate(x, ex.times(1000, 2.0))
        tau = scara.regressor(q, qd, qdd) @ xi + 0.1 * torch.randn(1000, 2, generator=g, dtype=D)
        noisy = [v + s * torch.randn(v.shape, generator=g, dtype=D) for v, s in
                 ((q, 1e-4), (qd, 1e-3), (qdd, 1e-2))]
        return scara.regressor(*noisy), tau

    W, tau = data(prob.decode(ga.x[None])[0])
    Wv, tauv = data(ex.random(1, torch.Generator().manual_seed(2000))[0])
    return W, tau, Wv, tauv, xi


def test_cpso_seed_settings_within_1pct_of_least_squares(seed_problem):
    W, tau, Wv, tauv, xi = seed_problem
    lo, hi = idf.physical_box()
    problem = idf.TorqueFitProblem(W, tau, lo, hi)
    x_ls = idf.ols(W, tau)
    f_ls = float(problem.fitness(x_ls[None])[0])
    assert f_ls == pytest.approx(float(idf.torque_rmse(W, tau, x_ls)), rel=1e-12)
    res = get_solver("cpso", seed=0, mu=4.0, **SEED_SWARM).minimize(problem)
    assert res.n_iter == 200 and len(res.history) == 201
    assert res.fun >= f_ls * (1 - 1e-12)  # least squares is the optimum
    assert res.fun <= 1.01 * f_ls
    assert float(idf.torque_rmse(Wv, tauv, res.x)) <= 1.01 * float(idf.torque_rmse(Wv, tauv, x_ls))
    assert float(((x_ls - xi) / xi).abs().max()) < 0.05  # the noisy LS estimate is close


def test_torque_fit_problem_shapes(seed_problem):
    W, tau, *_ = seed_problem
    lo, hi = idf.physical_box()
    problem = idf.TorqueFitProblem(W, tau, lo, hi)
    X = torch.stack([lo, hi, 0.5 * (lo + hi)])
    assert problem.residuals(X).shape == (3, 2000)
    f = problem.fitness(X)
    assert f.shape == (3,)
    assert float(f[2]) == pytest.approx(float(idf.torque_rmse(W, tau, X[2])), rel=1e-12)
