"""ELM estimator, batched population solve and seed 002's swarm tuning (MA / MMA vs random)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcal.elm import ELM, tune_elm
from torchcal.optim import FunctionProblem, get_solver
from torchcal.problems.elm import ELMProblem, fit_population, hidden_layer, solve_output_weights

torch.set_num_threads(1)


def _data(n: int, seed: int, n_in: int = 4):
    """A smooth 2-output regression problem with inputs in rad-like ranges."""
    g = torch.Generator().manual_seed(seed)
    X = (torch.rand(n, n_in, generator=g, dtype=torch.float64) * 2 - 1) * 1.5
    Y = torch.stack([torch.sin(2 * X[:, 0]) * X[:, 1] + 0.3 * X[:, 2] ** 2,
                     torch.cos(X[:, 3]) * X[:, 0] - 0.5 * X[:, 1] * X[:, 2]], 1) * 1e-3
    return X, Y


@pytest.fixture(scope="module")
def splits():
    X, Y = _data(160, 0)
    Xv, Yv = _data(60, 1)
    Xt, Yt = _data(200, 2)
    return X, Y, Xv, Yv, Xt, Yt


# ------------------------------------------------------------------ the estimator
def test_output_weights_equal_direct_least_squares(splits):
    X, Y, *_ = splits
    elm = ELM(25, seed=3).fit(X, Y)
    H = elm.hidden(X).numpy()
    Ys = ((Y - elm.y_mean_) / elm.y_scale_).numpy()
    V_ls = np.linalg.lstsq(H, Ys, rcond=None)[0]
    V_pinv = np.linalg.pinv(H) @ Ys
    scale = np.abs(V_ls).max()
    assert np.abs(elm.V_.numpy() - V_ls).max() <= 1e-9 * scale
    assert np.abs(elm.V_.numpy() - V_pinv).max() <= 1e-9 * scale
    # ridge: the closed form (HᵀH + λI)⁻¹ HᵀY
    lam = 1e-2
    er = ELM(25, seed=3, ridge=lam).fit(X, Y)
    V_r = np.linalg.solve(H.T @ H + lam * np.eye(25), H.T @ Ys)
    assert np.abs(er.V_.numpy() - V_r).max() <= 1e-10 * np.abs(V_r).max()


def test_random_weights_in_seed_ranges_and_reproducible(splits):
    X, Y, *_ = splits
    a, b = ELM(30, seed=5).fit(X, Y), ELM(30, seed=5).fit(X, Y)
    assert torch.equal(a.V_, b.V_)
    assert float(a.W_.min()) >= -1 and float(a.W_.max()) <= 1
    assert float(a.b_.min()) >= 0 and float(a.b_.max()) <= 1
    # inputs are scaled to [-1, 1] inside, predictions come back in Y's units (m here)
    assert a.predict(X).shape == Y.shape
    assert float(a.rmse(X, Y).max()) < float(Y.std(0).min())


def test_population_solve_equals_loop(splits):
    X, Y, Xv, Yv, *_ = splits
    for ridge in (0.0, 1e-3):
        prob = ELMProblem(X, Y, Xv, Yv, n_hidden=12, ridge=ridge)
        g = torch.Generator().manual_seed(7)
        P = 9
        pop = prob.lower + (prob.upper - prob.lower) * torch.rand(P, prob.dim, generator=g, dtype=torch.float64)
        f = prob.fitness(pop)
        W, b = prob.decode(pop)
        Vp = fit_population(prob.Xt, prob.Yt, W, b, ridge=ridge)
        assert torch.equal(prob.encode(W, b), pop)  # reshapes and a concatenation: no arithmetic
        for i in range(P):
            e = ELM(12, ridge=ridge, input_weights=W[i], biases=b[i]).fit(X, Y)
            # The batched solve and the single fit are the same LAPACK routine on other batch shapes
            # (MKL may take other kernels), so the fits agree to rounding amplified by the condition
            # of the hidden-layer matrix. Compared: the fitted training outputs H V, which a least-
            # squares solution pins down (V itself is free along H's near-null directions).
            H = hidden_layer(prob.Xt, W[i], b[i])
            tol = 100 * torch.finfo(H.dtype).eps * float(torch.linalg.cond(H)) * float(prob.Yt.abs().max())
            torch.testing.assert_close(H @ Vp[i], H @ e.V_, rtol=0, atol=tol)
            pv = (e.predict(Xv) - e.y_mean_) / e.y_scale_
            fi = torch.sqrt(((pv - prob.Yv) ** 2).mean())
            # the validation error, which the swarm minimises: to the same conditioned rounding
            assert abs(float(fi - f[i])) <= max(1e-12 * float(fi), tol)


def test_solve_output_weights_shapes_and_hidden_layer():
    g = torch.Generator().manual_seed(0)
    X = torch.rand(30, 3, generator=g, dtype=torch.float64)
    W = torch.rand(5, 3, 8, generator=g, dtype=torch.float64)
    b = torch.rand(5, 8, generator=g, dtype=torch.float64)
    H = hidden_layer(X, W, b)
    assert H.shape == (5, 30, 8)
    torch.testing.assert_close(H[2], torch.sigmoid(X @ W[2] + b[2]))
    V = solve_output_weights(H, torch.rand(30, 2, generator=g, dtype=torch.float64))
    assert V.shape == (5, 8, 2)


def test_validation_messages(splits):
    X, Y, *_ = splits
    with pytest.raises(ValueError, match="different numbers of rows"):
        ELM(5).fit(X, Y[:-1])
    bad = X.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf.*row 3, column 1"):
        ELM(5).fit(bad, Y)
    with pytest.raises(RuntimeError, match="not fitted"):
        ELM(5).predict(X)
    with pytest.raises(ValueError, match="unknown activation"):
        ELM(5, activation="softsign")
    with pytest.raises(ValueError, match="both input_weights and biases"):
        ELM(5, input_weights=torch.zeros(4, 5))
    with pytest.raises(ValueError, match="columns but this ELM was fitted on 4"):
        ELM(5).fit(X, Y).predict(X[:, :3])
    with pytest.raises(ValueError, match=r"input_weights must be \(4, 5\)"):
        ELM(5, input_weights=torch.zeros(3, 5), biases=torch.zeros(5)).fit(X, Y)


def test_state_dict_round_trip(splits):
    X, Y, *_ = splits
    e = ELM(10, activation="tanh", ridge=1e-4, seed=2).fit(X, Y)
    e2 = ELM.from_state_dict(e.config(), {k: v.clone() for k, v in e.state_dict().items()})
    assert torch.equal(e.predict(X), e2.predict(X))


# ------------------------------------------------------------------ tuning beats random search
def _random_search(problem, n_evals: int, seed: int) -> float:
    g = torch.Generator().manual_seed(seed)
    X = problem.lower + (problem.upper - problem.lower) * torch.rand(n_evals, problem.dim, generator=g,
                                                                      dtype=torch.float64)
    return float(problem.fitness(X).min())


def _sphere(X):
    return (X * X).sum(-1)


def _rastrigin(X):
    return 10 * X.shape[-1] + (X * X - 10 * torch.cos(2 * math.pi * X)).sum(-1)


@pytest.mark.parametrize("fn,bound", [(_sphere, 5.12), (_rastrigin, 5.12)], ids=["sphere", "rastrigin"])
def test_mayflies_beat_random_search_on_test_functions(fn, bound):
    k = 10
    prob = FunctionProblem(fn, torch.full((k,), -bound, dtype=torch.float64), torch.full((k,), bound, dtype=torch.float64))
    for method in ("ma", "mma"):
        wins = 0
        for seed in range(3):
            res = get_solver(method, seed=seed, pop_size=10, max_iter=60).minimize(prob)
            wins += res.fun < _random_search(prob, res.n_evals, seed)
        assert wins == 3, f"{method} lost to random search at equal evaluations on {fn.__name__}"


def test_mayflies_beat_random_search_on_elm_tuning(splits):
    X, Y, Xv, Yv, *_ = splits
    for method in ("ma", "mma"):
        tuned, rnd = [], []
        for seed in range(2):
            elm, res = tune_elm(X, Y, Xv, Yv, method, n_hidden=15, options={"pop_size": 10, "max_iter": 25}, seed=seed)
            _, res_r = tune_elm(X, Y, Xv, Yv, "random", n_hidden=15, options={"n_evals": res.n_evals}, seed=seed)
            assert res_r.n_evals == res.n_evals
            tuned.append(res.fun)
            rnd.append(res_r.fun)
        assert max(tuned) < min(rnd), f"{method}: {tuned} vs random {rnd}"


def test_tune_elm_by_name_returns_fitted_elm(splits):
    X, Y, Xv, Yv, Xt, Yt = splits
    elm, res = tune_elm(X, Y, Xv, Yv, "pso", n_hidden=8, options={"pop_size": 8, "max_iter": 3}, seed=0)
    assert elm.is_fitted and res.method == "pso" and res.x.shape == (4 * 8 + 8,)
    # the tuned network's validation RMSE is what the solver reported
    pv = (elm.predict(Xv) - elm.y_mean_) / elm.y_scale_
    yv = (Yv - elm.y_mean_) / elm.y_scale_
    assert abs(float(torch.sqrt(((pv - yv) ** 2).mean())) - res.fun) < 1e-12
    assert float(elm.W_.abs().max()) <= 1 and float(elm.b_.abs().max()) <= 1
    elm_all, _ = tune_elm(X, Y, Xv, Yv, "ga", n_hidden=8, options={"pop_size": 8, "max_iter": 2}, refit="all")
    assert elm_all.predict(Xt).shape == Yt.shape
