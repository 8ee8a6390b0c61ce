"""Fitting with identifiability: judge which free parameters the data can see, fit those,
judge again at the solution, and refit while the identifiable set grows."""
from __future__ import annotations

from typing import Callable

import torch

from torchcal.measure.observations import SETUP_PREFIXES
from torchcal.optim import Result, get_solver
from torchcal.params import ParamSet, display_unit
from torchcal.problems.base import Problem
from torchcal.problems.identifiability import analyse_jacobian

__all__ = ["reduce_free", "fit_identified", "PLAUSIBLE", "imprecise"]

# Plausible size of a geometric error (per unit): a parameter the data pin down only to worse
# than this (one standard error) is not identified by them, whatever its numerical rank. A marker
# a few micrometres off a joint axis makes that joint's offset full-rank and meaningless.
PLAUSIBLE = {"m": 0.01, "rad": 0.01}


def imprecise(J, names: list[str], units: list[str], noise: float, plausible: dict | None = None) -> dict[str, float]:
    """Parameters whose standard error ``noise · sqrt((JᵀJ)⁻¹_ii)`` exceeds their plausible size,
    dropped worst first (each drop makes the others better determined): name -> standard error."""
    plausible = PLAUSIBLE if plausible is None else plausible
    J = torch.as_tensor(J)
    keep = list(range(len(names)))
    out: dict[str, float] = {}
    while keep:
        A = J[:, keep]
        s = A.norm(dim=0).clamp(min=1e-300)
        cov = torch.linalg.pinv((A / s).T @ (A / s)) / (s[:, None] * s[None, :])
        se = noise * cov.diagonal().clamp(min=0).sqrt()
        lim = torch.tensor([plausible.get(units[i], float("inf")) for i in keep], dtype=se.dtype)
        ratio = se / lim
        worst = int(ratio.argmax())
        if not float(ratio[worst]) > 1:
            break
        out[names[keep[worst]]] = float(se[worst])
        keep.pop(worst)
    return out


def reduce_free(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, markers=(), kind="position",
                prefer=None, noise: float | None = None, plausible: dict | None = None):
    """Fix the free parameters of ``params`` that the problem's Jacobian cannot identify: those
    numerically dependent on others (:func:`~torchcal.problems.identifiability.analyse_jacobian`) and, given
    the per-axis ``noise`` (m), those it determines worse than their :data:`PLAUSIBLE` size.

    Returns (a copy of ``params`` with them fixed, the identifiability report)."""
    prob = make_problem(params)
    J = prob.jacobian(prob.x0)
    units = [params.units[i] for i in params.free_index.tolist()]
    rep = analyse_jacobian(J, params.free_names, units, markers=markers, kind=kind, prefer=prefer)
    out = params.clone()
    if rep.dropped:
        out.fix(*rep.dropped)
    if noise is not None and rep.identifiable:
        pos = [params.free_names.index(n) for n in rep.identifiable]
        # the set-up's planes and fixed points are never dropped for imprecision (no plausible size):
        # without them the observations that touch them mean nothing
        lim = [units[i] if not params.free_names[i].startswith(SETUP_PREFIXES) else "set-up" for i in pos]
        loose = imprecise(J[:, pos], rep.identifiable, lim, noise, plausible)
        for n, se in loose.items():
            out.fix(n)
            rep.dropped.append(n)
            rep.identifiable.remove(n)
            f, u = display_unit(units[params.free_names.index(n)])
            rep.reasons[n] = (f"{n} is determined only to ±{se * f:.3g} {u} by these "
                              f"poses (noise {noise * 1e3:.3g} mm), more than such an error can plausibly be")
    return out, rep


def fit_identified(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, method: str = "lm",
                   options: dict | None = None, seed: int = 0, progress: bool = False, markers=(),
                   kind: str = "position", prefer=None, reduce: bool = True, rounds: int = 3,
                   solve: Callable | None = None, noise: float | None = None,
                   plausible: dict | None = None, zero_dropped: tuple[str, ...] = ()
                   ) -> tuple[ParamSet, Result, object]:
    """Fit the identifiable subset of ``params``' free entries.

    Identifiability depends on where it is judged (a marker guessed on a joint axis hides that
    joint's offset), so it is judged at the start, then again at each solution; while the
    identifiable set grows the fit is repeated from the current values.

    Args:
        make_problem: builds a problem for a ParamSet (its free flags choose the unknowns).
        solve: optional ``(problem) -> Result`` replacing the plain solver call.
        noise, plausible: see :func:`reduce_free`.
        zero_dropped: name prefixes of parameters set to 0 when identifiability drops them (a
            model's optional parts, whose start may hold meaningless values along the directions
            the data cannot see).
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
    def zeroed(p: ParamSet) -> ParamSet:
        if zero_dropped:
            for i, (n, f) in enumerate(zip(p.names, p.free.tolist())):
                if not f and n.startswith(zero_dropped) and candidates.free[i]:
                    p.values[i] = 0.0
        return p

    p, rep = reduce_free(make_problem, candidates, markers=markers, kind=kind, prefer=prefer, noise=noise,
                         plausible=plausible)
    p = zeroed(p)
    for _ in range(rounds):
        p, res = run(p)
        nxt = candidates.clone()
        nxt.values = p.values.clone()
        nxt, rep2 = reduce_free(make_problem, nxt, markers=markers, kind=kind, prefer=prefer, noise=noise,
                                plausible=plausible)
        if set(nxt.free_names) <= set(p.free_names):
            break
        p, rep = zeroed(nxt), rep2
    return p, res, rep
