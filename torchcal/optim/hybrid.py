"""Hybrid solver: a swarm for the global search, then a local solver (LM) to polish.

Swarms find the right basin but converge slowly inside it (~1e-3 relative accuracy after a
reasonable budget); Levenberg-Marquardt converges quadratically once it starts in the basin.
Running one after the other gets both.
"""
from __future__ import annotations

import copy
from typing import Any, Callable

import torch

from torchcal.optim.base import Solver, get_solver, register
from torchcal.optim.result import Result
from torchcal.problems.base import Problem

__all__ = ["Hybrid"]


@register
class Hybrid(Solver):
    """Swarm search followed by a local polish started at the swarm's best point.

    Stage 1 runs ``swarm`` (any registered swarm solver, default ``"pso"``) on the problem.
    Stage 2 runs ``polish`` (default ``"lm"``, Levenberg-Marquardt, which needs a problem with
    residuals) on a shallow copy of the problem whose ``x0`` is the swarm's best ``x``.

    The returned ``x``/``fun`` are those of the stage with the lower problem fitness (the polish
    normally; the swarm's if the polish made things worse, e.g. when the problem's fitness is
    not the sum of squared residuals LM minimises). ``history`` is the swarm's history followed
    by the polish's; ``n_evals`` and ``n_iter`` are the sums; ``Result.extra`` has ``"swarm"``
    and ``"polish"``, the two stages' :class:`Result` objects, and ``"chosen"``.

    Args:
        swarm: registered name of the global solver.
        swarm_options: options for it (``seed``/``progress`` default to this solver's).
        polish: registered name of the local solver.
        polish_options: options for it (same defaults).
        seed, progress: passed to both stages unless their options say otherwise.
        callback: ``callback(it, best)``, called by both stages with the iteration count
            continuing across them (polish iteration ``j`` is reported as ``swarm n_iter + j``).
    """

    name = "hybrid"
    population = True  # a swarm first, then LM from its best
    aliases = ("pso+lm",)

    def __init__(self, *, swarm: str = "pso", swarm_options: dict[str, Any] | None = None,
                 polish: str = "lm", polish_options: dict[str, Any] | None = None,
                 seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None):
        super().__init__(seed=seed, progress=progress, callback=callback)
        self.swarm = swarm
        self.swarm_options = dict(swarm_options or {})
        self.polish = polish
        self.polish_options = dict(polish_options or {})

    def _stage_options(self, options: dict[str, Any], offset: Callable[[], int]) -> dict[str, Any]:
        opts: dict[str, Any] = {"seed": self.seed, "progress": self.progress}
        if self.callback is not None:
            cb = self.callback
            opts["callback"] = lambda it, best: cb(offset() + it, best)
        opts.update(options)
        return opts

    def _run(self, problem: Problem) -> Result:
        problem.require_finite_bounds(self.name)
        sw = get_solver(self.swarm, **self._stage_options(self.swarm_options, lambda: 0))
        r1 = sw.minimize(problem)

        # Start the polish at the swarm's best without mutating the caller's problem.
        p2 = copy.copy(problem)
        p2.x0 = r1.x.detach().clone()
        pol = get_solver(self.polish, **self._stage_options(self.polish_options, lambda: r1.n_iter))
        r2 = pol.minimize(p2)

        # Compare on the problem's own fitness (one extra evaluation, counted): the polish may
        # minimise a different objective (LM: sum of squares) than the swarm's fitness.
        with torch.no_grad():
            f2 = float(problem.fitness(r2.x.detach()[None].to(problem.dtype))[0])
        chosen, x, fun = ("polish", r2.x, f2) if f2 <= r1.fun else ("swarm", r1.x, r1.fun)
        return Result(
            x=x.detach().clone(), fun=fun, history=list(r1.history) + list(r2.history),
            n_evals=r1.n_evals + r2.n_evals + 1, n_iter=r1.n_iter + r2.n_iter,
            converged=r2.converged,
            message=f"{self.swarm}: {r1.message}; {self.polish}: {r2.message}; kept the {chosen} result",
            extra={"swarm": r1, "polish": r2, "chosen": chosen})
