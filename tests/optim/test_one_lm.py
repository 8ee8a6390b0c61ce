"""The one Levenberg-Marquardt iteration: a single problem is a batch of one, a batch solves each problem
as it would be solved alone, and the arrow linear step (the coupled fleet) solves what the dense one does.

The problems are exponential decays ``y = a exp(-k t) + c``, well conditioned (three parameters, forty
samples spread over several time constants, a start within tens of percent), so every solve converges
to its gtol and solutions agree to far below the tolerances used (1e-9 relative, against parameters of
order 1 whose standard error at this noise is about 1e-3)."""
from __future__ import annotations

import torch

from torchcal.optim import minimize
from torchcal.optim.lm_batched import Batch, LMBatchedOptions, lm_batched
from torchcal.optim.lm_linear import lm_arrow
from torchcal.problems.base import LeastSquaresProblem

T = torch.linspace(0.0, 4.0, 40, dtype=torch.float64)


def _data(B: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    truth = torch.stack([1.0 + torch.rand(B, generator=g, dtype=torch.float64),
                         0.5 + torch.rand(B, generator=g, dtype=torch.float64),
                         0.2 * torch.randn(B, generator=g, dtype=torch.float64)], 1)
    Y = truth[:, :1] * torch.exp(-truth[:, 1:2] * T) + truth[:, 2:]
    return truth, Y + 1e-3 * torch.randn(Y.shape, generator=g, dtype=torch.float64)


def _res(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    return X[:, :1] * torch.exp(-X[:, 1:2] * T) + X[:, 2:] - Y


def _jac(X: torch.Tensor) -> torch.Tensor:
    e = torch.exp(-X[:, 1:2] * T)
    return torch.stack([e, -X[:, :1] * T * e, torch.ones_like(e)], -1)


def _problem(y: torch.Tensor, x0: torch.Tensor) -> LeastSquaresProblem:
    inf = torch.full((3,), float("inf"), dtype=torch.float64)
    return LeastSquaresProblem(lambda X: _res(X, y[None]), -inf, inf, x0=x0, jacobian_fn=lambda x: _jac(x[None])[0])


def test_a_batch_of_one_is_the_single_solve():
    """``minimize(problem, "lm")`` runs :class:`Batch` on a batch of one: the same operations on tensors of
    the same shapes in the same order, so the engine's answer is the batched call's exactly (not to a
    tolerance: nothing differs that could round differently)."""
    truth, Y = _data(1)
    x0 = truth[0] * 1.3
    single = minimize(_problem(Y[0], x0), "lm")
    inf = torch.full((3,), float("inf"), dtype=torch.float64)
    batch = lm_batched(lambda X, i: _res(X, Y[i]), lambda X, i: _jac(X), x0[None], torch.ones(1, 3, dtype=torch.bool),
                       -inf, inf)
    assert single.converged and bool(batch.converged[0])
    assert torch.equal(single.x, batch.x[0]) and single.n_iter == int(batch.n_iter[0])


def test_each_problem_of_a_batch_gets_what_it_gets_alone():
    truth, Y = _data(5, seed=1)
    x0 = truth * torch.tensor([1.3, 0.7, 0.0], dtype=torch.float64) + torch.tensor([0.0, 0.0, 0.1])
    free = torch.ones(5, 3, dtype=torch.bool)
    free[2, 2] = False  # one problem keeps its offset fixed: its own smaller system
    inf = torch.full((3,), float("inf"), dtype=torch.float64)
    res = lm_batched(lambda X, i: _res(X, Y[i]), lambda X, i: _jac(X), x0, free, -inf, inf)
    assert bool(res.converged.all())
    for b in range(5):
        if b == 2:
            p = LeastSquaresProblem(lambda X: _res(torch.cat([X, x0[2:3, 2:].expand(X.shape[0], 1)], 1), Y[2:3]),
                                    -inf[:2], inf[:2], x0=x0[2, :2],
                                    jacobian_fn=lambda x: _jac(torch.cat([x, x0[2, 2:]])[None])[0, :, :2])
            alone = minimize(p, "lm").x
            assert float(res.x[2, 2]) == float(x0[2, 2])  # a fixed entry is never written
            got = res.x[2, :2]
        else:
            alone, got = minimize(_problem(Y[b], x0[b]), "lm").x, res.x[b]
            assert float((got - truth[b]).abs().max()) < 0.05  # and it is the decay that made the data
        torch.testing.assert_close(got, alone, rtol=1e-9, atol=1e-12)


def test_zero_rows_change_nothing():
    """A row a problem does not use (a CV fold's held-out rows) is a zero residual and a zero Jacobian
    row: the problem solved with them equals the problem solved on its own rows."""
    truth, Y = _data(1, seed=2)
    x0 = truth[0] * 1.2
    keep = torch.arange(40) % 5 != 0
    w = keep.to(torch.float64)
    inf = torch.full((3,), float("inf"), dtype=torch.float64)
    masked = lm_batched(lambda X, i: _res(X, Y[i]) * w, lambda X, i: _jac(X) * w[:, None], x0[None],
                        torch.ones(1, 3, dtype=torch.bool), -inf, inf)
    Tk = T[keep]
    own = minimize(LeastSquaresProblem(lambda X: X[:, :1] * torch.exp(-X[:, 1:2] * Tk) + X[:, 2:] - Y[:, keep],
                                       -inf, inf, x0=x0), "lm")
    torch.testing.assert_close(masked.x[0], own.x, rtol=1e-9, atol=1e-12)


def _blocks(R: int, seed: int = 3):
    """R decays that share their rate ``s``: per-block ``z = (a, c)``, shared ``s = (k,)``."""
    g = torch.Generator().manual_seed(seed)
    a = 1.0 + torch.rand(R, generator=g, dtype=torch.float64)
    c = 0.2 * torch.randn(R, generator=g, dtype=torch.float64)
    k = 0.8
    Y = a[:, None] * torch.exp(-k * T) + c[:, None] + 1e-3 * torch.randn(R, T.numel(), generator=g, dtype=torch.float64)

    def fun(Z: torch.Tensor, s: torch.Tensor):
        e = torch.exp(-s[0] * T)[None].expand(R, -1)
        r = Z[:, :1] * e + Z[:, 1:] - Y
        Jz = torch.stack([e, torch.ones_like(e)], -1)
        Js = (-Z[:, :1] * T * e)[..., None]
        return r, Jz, Js
    return fun, torch.stack([a, c], 1), torch.tensor([k], dtype=torch.float64)


def test_the_arrow_step_solves_what_the_dense_step_solves():
    R = 6
    fun, Zt, st = _blocks(R)
    Z0, s0 = Zt * 1.2, st * 1.3
    zfree = torch.ones(R, 2, dtype=torch.bool)
    zfree[4, 1] = False  # a block with a fixed entry
    sfree = torch.ones(1, dtype=torch.bool)
    arrow = lm_arrow(fun, Z0, s0, zfree, sfree)

    # the same problem assembled densely: x = [z_1 … z_R, s], J (R m, 2 R + 1)
    def split(X):
        return X[0, : 2 * R].reshape(R, 2), X[0, 2 * R:]

    def residuals(X, idx):
        return fun(*split(X))[0].reshape(1, -1)

    def jacobian(X, idx):
        _, Jz, Js = fun(*split(X))
        J = torch.zeros(R, T.numel(), 2 * R + 1, dtype=torch.float64)
        for r in range(R):
            J[r, :, 2 * r: 2 * r + 2] = Jz[r]
        J[:, :, 2 * R:] = Js
        return J.reshape(1, -1, 2 * R + 1)

    x0 = torch.cat([Z0.flatten(), s0])[None]
    free = torch.cat([zfree.flatten(), sfree])[None]
    inf = torch.full((2 * R + 1,), float("inf"), dtype=torch.float64)
    dense = lm_batched(residuals, jacobian, x0, free, -inf, inf, LMBatchedOptions(max_iter=200))
    assert arrow.converged and bool(dense.converged[0])
    Zd, sd = split(dense.x)
    torch.testing.assert_close(arrow.Z, Zd, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(arrow.s, sd, rtol=1e-9, atol=1e-12)
    assert float(arrow.Z[4, 1]) == float(Z0[4, 1])
    assert abs(float(arrow.s[0]) - 0.8) < 0.05  # near the shared rate (block 4 holds its offset off its truth)


def test_one_damping_rule():
    """Every LM starts from the one default damping (torchcal.damping.TAU), and a settings record and its
    keywords are the same call."""
    from torchcal.damping import TAU
    from torchcal.optim import get_solver

    assert LMBatchedOptions().tau == TAU
    assert get_solver("lm").opt.tau == TAU
    assert get_solver("lm", max_iter=7).opt == get_solver("lm", settings=LMBatchedOptions(max_iter=7)).opt
    truth, Y = _data(1)
    b = Batch(lambda X, i: _res(X, Y[i]), lambda X, i: _jac(X), (truth * 1.3), torch.ones(1, 3, dtype=torch.bool),
              torch.full((3,), -float("inf"), dtype=torch.float64), torch.full((3,), float("inf"), dtype=torch.float64))
    assert float(b.mu[0]) == TAU
