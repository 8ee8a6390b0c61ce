"""Fitting with identifiability: judge which free parameters the data can see, fit those,
judge again at the solution, and refit while the identifiable set grows."""
from __future__ import annotations

from typing import Callable

from .optim import Problem, Result, get_solver
from .params import ParamSet

__all__ = ["reduce_free", "fit_identified"]


def reduce_free(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, markers=(), kind="position",
                prefer=None):
    """Fix the free parameters of ``params`` that the problem's Jacobian cannot identify.

    Returns (a copy of ``params`` with them fixed, the identifiability report)."""
    from .identifiability import analyse_jacobian

    prob = make_problem(params)
    J = prob.jacobian(prob.x0)
    units = [params.units[i] for i in params.free_index.tolist()]
    rep = analyse_jacobian(J, params.free_names, units, markers=markers, kind=kind, prefer=prefer)
    out = params.clone()
    if rep.dropped:
        out.fix(*rep.dropped)
    return out, rep


def fit_identified(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, method: str = "lm",
                   options: dict | None = None, seed: int = 0, progress: bool = False, markers=(),
                   kind: str = "position", prefer=None, reduce: bool = True, rounds: int = 3,
                   solve: Callable | None = None) -> tuple[ParamSet, Result, object]:
    """Fit the identifiable subset of ``params``' free entries.

    Identifiability depends on where it is judged (a marker guessed on a joint axis hides that
    joint's offset), so it is judged at the start, then again at each solution; while the
    identifiable set grows the fit is repeated from the current values.

    Args:
        make_problem: builds a problem for a ParamSet (its free flags choose the unknowns).
        solve: optional ``(problem) -> Result`` replacing the plain solver call.
    Returns:
        (fitted ParamSet, the solver's Result, the last identifiability report or None).
    """
    candidates = params.clone()

    def run(p: ParamSet):
        prob = make_problem(p)
        res = solve(prob) if solve is not None else \
            get_solver(method, seed=seed, progress=progress, **dict(options or {})).minimize(prob)
        out = p.clone()
        out.values = prob.full(res.x).detach()
        return out, res

    if not reduce:
        p, res = run(params)
        return p, res, None
    p, rep = reduce_free(make_problem, candidates, markers=markers, kind=kind, prefer=prefer)
    for _ in range(rounds):
        p, res = run(p)
        nxt = candidates.clone()
        nxt.values = p.values.clone()
        nxt, rep2 = reduce_free(make_problem, nxt, markers=markers, kind=kind, prefer=prefer)
        if set(nxt.free_names) <= set(p.free_names):
            break
        p, rep = nxt, rep2
    return p, res, rep
