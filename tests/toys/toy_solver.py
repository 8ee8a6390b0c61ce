"""A toy solver, in one file: steepest descent on the sum of squares with a backtracking line
search. Registering it is all torchcal asks: ``calibrate(method="toy_descent")`` and the command
line's ``--method`` then take it. Loaded by ``tests/structure/test_extension_points.py``."""
from __future__ import annotations

from types import SimpleNamespace

import torch

from torchcal.optim import register
from torchcal.optim.engine import LocalSolver


@register
class ToyDescent(LocalSolver):
    name = "toy_descent"
    population = False

    def __init__(self, *, max_iter: int = 300, **kw):
        super().__init__(**kw)
        self.max_iter = max_iter

    def init(self, problem, g):
        x = problem.x0.clone()
        f = float(problem.fitness(x[None])[0])
        return SimpleNamespace(x=x, best=f, n_evals=1, step=1.0)

    def step(self, problem, st, t, g):
        r = problem.residuals(st.x[None])[0]
        J = problem.jacobian(st.x)
        grad = 2 * J.T @ r
        # the Gauss-Newton length along the gradient: a scale-free first try
        Jg = J @ grad
        st.step = float((grad @ grad) / (2 * (Jg @ Jg)).clamp(min=1e-300))
        for _ in range(30):
            x = (st.x - st.step * grad).clamp(problem.lower, problem.upper)
            f = float(problem.fitness(x[None])[0])
            st.n_evals += 1
            if f < st.best:
                gain, st.x, st.best = st.best - f, x, f
                return (True, "converged: relative gain below 1e-12") if gain <= 1e-12 * f else None
            st.step *= 0.5
        return True, "no descent along the gradient"

    def finish(self, problem, st):
        return st.x, st.best, {}
