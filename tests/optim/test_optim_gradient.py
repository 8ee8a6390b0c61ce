"""Gradient solvers: Levenberg-Marquardt, Gauss-Newton, L-BFGS and Adam (torchcal.optim)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from torchcal.optim import FunctionProblem, LeastSquaresProblem, get_solver, minimize
from torchcal.optim.gradient import LBFGS, Adam, GaussNewton
from torchcal.optim.lm import LevenbergMarquardt

# torch loads JIT decompositions on the first forward-mode autograd call (jacfwd) and warns
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")

F64 = torch.float64
TIGHT = dict(ftol=1e-15, xtol=1e-15, gtol=1e-14)


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(n)


def unbounded(k: int) -> tuple[torch.Tensor, torch.Tensor]:
    inf = torch.full((k,), torch.inf, dtype=F64)
    return -inf, inf


# -- test problems -----------------------------------------------------------------------------
T_EXPSIN = torch.linspace(0.0, 3.0, 40, dtype=F64)
TRUTH_EXPSIN = torch.tensor([2.0, -0.7, 0.5, 3.0], dtype=F64)


def expsin(X: torch.Tensor) -> torch.Tensor:
    """``y = a exp(b t) + c sin(d t)``, batched ``(P, 4) -> (P, 40)``."""
    a, b, c, d = X.unbind(-1)
    t = T_EXPSIN
    return a[:, None] * torch.exp(b[:, None] * t) + c[:, None] * torch.sin(d[:, None] * t)


def expsin_problem(**kw) -> LeastSquaresProblem:
    y = expsin(TRUTH_EXPSIN[None])[0]
    x0 = TRUTH_EXPSIN * torch.tensor([1.3, 0.7, 1.4, 0.8], dtype=F64)  # 20-40 % off
    lo, hi = unbounded(4)
    return LeastSquaresProblem(lambda X: expsin(X) - y, lo, hi, x0=x0, **kw)


def rosenbrock(X: torch.Tensor) -> torch.Tensor:
    return torch.stack([10.0 * (X[:, 1] - X[:, 0] ** 2), 1.0 - X[:, 0]], -1)


def rosenbrock_np(p: np.ndarray) -> np.ndarray:
    return np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])


def rosenbrock_problem() -> LeastSquaresProblem:
    lo, hi = unbounded(2)
    return LeastSquaresProblem(rosenbrock, lo, hi, x0=torch.tensor([-1.2, 1.0], dtype=F64))


_rng = np.random.default_rng(1)
T_EXP = np.linspace(0.0, 4.0, 50)
Y_EXP = 3.0 * np.exp(-1.3 * T_EXP) + 0.5 + 0.05 * _rng.standard_normal(50)
X0_EXP = np.array([1.5, -0.6, 0.2])


def exp_np(p: np.ndarray) -> np.ndarray:
    return p[0] * np.exp(p[1] * T_EXP) + p[2] - Y_EXP


def exp_torch(X: torch.Tensor) -> torch.Tensor:
    t, y = torch.from_numpy(T_EXP), torch.from_numpy(Y_EXP)
    return X[:, 0:1] * torch.exp(X[:, 1:2] * t) + X[:, 2:3] - y


def exp_problem(lower=None, upper=None, residual_fn=exp_torch) -> LeastSquaresProblem:
    lo, hi = unbounded(3)
    lo = lo if lower is None else torch.tensor(lower, dtype=F64)
    hi = hi if upper is None else torch.tensor(upper, dtype=F64)
    return LeastSquaresProblem(residual_fn, lo, hi, x0=torch.from_numpy(X0_EXP.copy()))


@pytest.fixture(scope="module")
def scipy_exp():
    return least_squares(exp_np, X0_EXP, method="lm", ftol=1e-15, xtol=1e-15, gtol=1e-15)


# -- exact recovery ------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["lm", "gn"])
def test_recovers_exact_parameters(method):
    res = minimize(expsin_problem(), method)
    assert res.converged, res.message
    assert float((res.x - TRUTH_EXPSIN).abs().max()) < 1e-9
    assert res.x.dtype == F64
    assert res.method == method
    assert len(res.history) == res.n_iter + 1
    assert res.history[-1] == res.fun < 1e-18


@pytest.mark.parametrize("options", [dict(scaling="marquardt"), dict(jac="3-point"),
                                     dict(jac="2-point"), dict(mu0=0.1)])
def test_lm_variants_recover_parameters(options):
    res = minimize(expsin_problem(), "lm", **options)
    tol = 1e-6 if options.get("jac") == "2-point" else 1e-9  # forward differences: O(sqrt eps)
    assert float((res.x - TRUTH_EXPSIN).abs().max()) < tol, res.message


def test_analytic_jacobian_is_used():
    calls = []

    def jac(x):
        calls.append(1)
        return torch.func.jacfwd(lambda v: expsin(v[None])[0])(x)

    res = minimize(expsin_problem(jacobian_fn=jac), "lm")
    assert len(calls) == res.extra["n_jac"] > 0
    # rejected steps reuse J: at most one Jacobian per accepted step plus the start
    assert res.extra["n_jac"] == res.n_iter - res.extra["n_rejected"] + 1


# -- agreement with scipy --------------------------------------------------------------------
def test_lm_matches_scipy_on_rosenbrock():
    ref = least_squares(rosenbrock_np, [-1.2, 1.0], method="lm", ftol=1e-15, xtol=1e-15, gtol=1e-15)
    res = minimize(rosenbrock_problem(), "lm", **TIGHT)
    assert np.abs(res.x.numpy() - ref.x).max() < 1e-7
    # the minimum cost is zero: compare absolutely at the scale of a converged zero
    assert res.extra["cost"] < 1e-20 and ref.cost < 1e-20
    assert res.extra["cost"] == pytest.approx(0.5 * res.fun)


def test_lm_matches_scipy_on_noisy_exponential(scipy_exp):
    res = minimize(exp_problem(), "lm", **TIGHT)
    assert res.converged, res.message
    assert abs(res.extra["cost"] - scipy_exp.cost) <= 1e-10 * scipy_exp.cost
    assert np.abs(res.x.numpy() - scipy_exp.x).max() < 1e-7
    # extras describe the solution: residuals, Jacobian and cost are consistent with x
    r = exp_torch(res.x[None])[0]
    assert torch.allclose(res.extra["residuals"], r, rtol=0, atol=1e-14)
    J = torch.func.jacfwd(lambda v: exp_torch(v[None])[0])(res.x)
    assert res.extra["jacobian"].shape == (50, 3)
    assert torch.allclose(res.extra["jacobian"], J, rtol=1e-12, atol=1e-12)
    assert res.extra["cost"] == pytest.approx(0.5 * float(r @ r), rel=1e-14)


def test_gn_matches_scipy_on_noisy_exponential(scipy_exp):
    res = minimize(exp_problem(), "gn", **TIGHT)
    assert abs(res.extra["cost"] - scipy_exp.cost) <= 1e-10 * scipy_exp.cost
    assert np.abs(res.x.numpy() - scipy_exp.x).max() < 1e-7


# -- gain-ratio damping ----------------------------------------------------------------------
def test_lm_damping_follows_gain_ratio():
    # from (-1.2, 1) the undamped Gauss-Newton step overshoots Rosenbrock's valley badly
    mu0 = 1e-10
    seen = []
    res = minimize(rosenbrock_problem(), "lm", mu0=mu0, callback=lambda i, f: seen.append((i, f)))
    mus = [mu0, *res.extra["mu_history"]]
    hist = res.history
    # the first trials are rejected: fitness unchanged, mu multiplied by nu = 2, 4, 8, ...
    assert hist[1] == hist[0] and hist[2] == hist[0]
    assert mus[1] == pytest.approx(2 * mu0, rel=1e-12)
    assert mus[2] == pytest.approx(8 * mu0, rel=1e-12)
    assert mus[3] == pytest.approx(64 * mu0, rel=1e-12)
    # the whole run obeys the rule: rejected -> mu *= nu, nu *= 2; accepted -> factor in [1/3, 2]
    nu, n_acc, n_rej = 2.0, 0, 0
    for i in range(res.n_iter):
        ratio = mus[i + 1] / mus[i]
        if hist[i + 1] == hist[i]:
            assert ratio == pytest.approx(nu, rel=1e-12)
            nu *= 2.0
            n_rej += 1
        else:
            assert hist[i + 1] < hist[i]
            assert 1 / 3 - 1e-12 <= ratio <= 2.0
            nu = 2.0
            n_acc += 1
    assert n_rej == res.extra["n_rejected"] >= 3 and n_acc > 0
    assert [i for i, _ in seen] == list(range(1, res.n_iter + 1))
    assert [f for _, f in seen] == hist[1:]
    assert float((res.x - 1.0).abs().max()) < 1e-9


# -- autograd solvers ------------------------------------------------------------------------
def test_lbfgs_reaches_the_least_squares_minimum(scipy_exp):
    res = minimize(exp_problem(), "lbfgs")
    best = 2 * scipy_exp.cost  # fitness = sum of squares = 2 * cost
    assert res.fun - best <= 1e-8 * best
    assert res.fun < res.history[0] * 1e-2
    assert all(b <= a for a, b in zip(res.history, res.history[1:]))


def test_adam_gets_near_the_minimum(scipy_exp):
    res = minimize(exp_problem(), "adam", lr=0.02, max_iter=3000)
    best = 2 * scipy_exp.cost
    assert res.fun - best <= 1e-5 * best
    assert np.abs(res.x.numpy() - scipy_exp.x).max() < 1e-3


@pytest.mark.parametrize("method", ["lbfgs", "adam"])
def test_autograd_solvers_on_exact_problem(method):
    opts = dict(lr=0.01, max_iter=3000) if method == "adam" else {}
    res = minimize(expsin_problem(), method, **opts)
    assert float((res.x - TRUTH_EXPSIN).abs().max()) < 1e-6, res.message


# -- bounds ----------------------------------------------------------------------------------
@pytest.mark.parametrize("method,options", [("lm", TIGHT), ("gn", TIGHT), ("lbfgs", {}),
                                            ("adam", dict(lr=0.02, max_iter=3000)),
                                            ("lm", dict(jac="3-point", **TIGHT))])
def test_bounds_are_respected(method, options):
    lower, upper = [0.0, -5.0, -5.0], [2.5, 5.0, 5.0]  # unconstrained optimum has a ~ 3.03
    evaluated = []

    def recording(X):
        evaluated.append(X.detach().clone())
        return exp_torch(X)

    ref = least_squares(exp_np, X0_EXP, method="trf", bounds=(lower, upper),
                        ftol=1e-15, xtol=1e-15, gtol=1e-15)
    assert ref.x[0] == pytest.approx(2.5)  # the bound is active at the constrained optimum
    res = minimize(exp_problem(lower, upper, recording), method, **options)
    lo, hi = torch.tensor(lower, dtype=F64), torch.tensor(upper, dtype=F64)
    X = torch.cat(evaluated)
    assert bool(((X >= lo) & (X <= hi)).all()), "a point outside the bounds was evaluated"
    assert bool(((res.x >= lo) & (res.x <= hi)).all())
    assert float(res.x[0]) == 2.5
    assert np.abs(res.x.numpy() - ref.x).max() < 1e-6
    assert 0.5 * res.fun - ref.cost <= 1e-9 * ref.cost


# -- rank deficiency -------------------------------------------------------------------------
T_RD = torch.linspace(0.0, 2.0, 30, dtype=F64)


def sum_only(X: torch.Tensor) -> torch.Tensor:
    """Parameters 0 and 1 enter only through their sum (truth: sum 0.8, slope -0.5)."""
    y = torch.exp(0.8 * T_RD) - 0.5 * T_RD
    return torch.exp((X[:, 0:1] + X[:, 1:2]) * T_RD) + X[:, 2:3] * T_RD - y


def sum_only_problem(x0) -> LeastSquaresProblem:
    lo, hi = unbounded(3)
    return LeastSquaresProblem(sum_only, lo, hi, x0=torch.tensor(x0, dtype=F64))


def test_gn_gives_minimum_norm_solution_on_rank_deficient_problem():
    res = minimize(sum_only_problem([0.0, 0.0, 0.0]), "gn")
    assert res.extra["rank"] == 2
    assert res.fun < 1e-20
    # of all (a, b) with a + b = 0.8 the minimum-norm one is a = b = 0.4
    assert torch.allclose(res.x, torch.tensor([0.4, 0.4, -0.5], dtype=F64), rtol=0, atol=1e-9)
    # from another start the unseen direction a - b keeps its start value
    res = minimize(sum_only_problem([0.3, -0.1, 0.0]), "gn")
    assert torch.allclose(res.x, torch.tensor([0.6, 0.2, -0.5], dtype=F64), rtol=0, atol=1e-9)


def test_gn_free_subset_holds_the_others():
    res = minimize(sum_only_problem([0.0, 0.1, 0.0]), "gn", free=[0, 2])
    assert float(res.x[1]) == 0.1  # held exactly at x0
    assert torch.allclose(res.x, torch.tensor([0.7, 0.1, -0.5], dtype=F64), rtol=0, atol=1e-9)
    assert res.extra["rank"] == 2


def test_lm_converges_in_cost_on_rank_deficient_problem():
    res = minimize(sum_only_problem([0.0, 0.0, 0.0]), "lm")
    assert res.converged, res.message
    assert res.fun < 1e-18
    assert float(res.x[0] + res.x[1]) == pytest.approx(0.8, abs=1e-9)


# -- non-default fitness, registry, options, errors ------------------------------------------
def test_history_uses_problem_fitness():
    y = expsin(TRUTH_EXPSIN[None])[0]
    lo, hi = unbounded(4)
    l1 = lambda X: (expsin(X) - y).abs().sum(-1)  # noqa: E731
    prob = LeastSquaresProblem(lambda X: expsin(X) - y, lo, hi, fitness_fn=l1,
                               x0=TRUTH_EXPSIN * 1.2)
    res = minimize(prob, "lm")
    assert res.fun == pytest.approx(float(l1(res.x[None])[0]), rel=1e-12, abs=1e-300)
    assert res.history[0] == pytest.approx(float(l1(prob.x0[None])[0]), rel=1e-12)
    assert res.extra["cost"] != pytest.approx(0.5 * res.history[0])


def test_registry_names_and_aliases():
    assert isinstance(get_solver("lm"), LevenbergMarquardt)
    assert isinstance(get_solver("Levenberg-Marquardt"), LevenbergMarquardt)
    assert isinstance(get_solver("gauss-newton"), GaussNewton)
    assert isinstance(get_solver("lbfgs"), LBFGS)
    assert isinstance(get_solver("adam"), Adam)


def test_max_iter_stops_without_converging():
    res = minimize(rosenbrock_problem(), "lm", max_iter=3)
    assert res.n_iter == 3 and not res.converged
    assert "max_iter" in res.message


def test_progress_bar_runs(capsys):
    res = minimize(expsin_problem(), "gn", progress=True)
    assert res.converged
    assert "gn" in capsys.readouterr().err


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_problem_without_residuals_names_the_fix(method):
    lo, hi = unbounded(2)
    prob = FunctionProblem(lambda X: (X ** 2).sum(-1), lo, hi)
    with pytest.raises(TypeError, match="LeastSquaresProblem"):
        minimize(prob, method)


def test_non_differentiable_fitness_names_the_fix():
    lo, hi = unbounded(2)
    prob = FunctionProblem(lambda X: torch.from_numpy((X.detach().numpy() ** 2).sum(-1)), lo, hi,
                           x0=torch.ones(2, dtype=F64))
    with pytest.raises(TypeError, match="autograd"):
        minimize(prob, "lbfgs")


def test_bad_options_raise():
    with pytest.raises(ValueError, match="scaling"):
        get_solver("lm", scaling="diag")
    with pytest.raises(ValueError, match="jac"):
        get_solver("gn", jac="complex-step")
    with pytest.raises(ValueError, match="mu0"):
        get_solver("lm", mu0=0.0)
    with pytest.raises(ValueError, match="free"):
        minimize(expsin_problem(), "gn", free=[7])


def test_wrong_jacobian_shape_is_reported():
    with pytest.raises(ValueError, match="jacobian must have shape"):
        minimize(expsin_problem(jacobian_fn=lambda x: torch.zeros(4, 40, dtype=F64)), "lm")
