"""Fitting with identifiability: judge which free parameters the data can see, fit those,
judge again at the solution, and refit while the identifiable set grows."""
from __future__ import annotations

import copy
import glob
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.options import Options
from torchcal.measure.setup import SETUP_PREFIXES
from torchcal.optim import Result, get_solver
from torchcal.params import ParamSet
from torchcal.pipelines.precision import imprecise, imprecise_reason
from torchcal.pipelines.rounds import fit_rounds
from torchcal.problems.base import Problem
from torchcal.problems.identifiability import DEFAULT_PREFER, analyse_jacobian
from torchcal.problems.identifiability_report import IdentifiabilityReport
from torchcal.problems.uncertainty import residual_noise

__all__ = ["reduce_free", "rank_judged", "fit_identified", "FitOptions", "too_few_residuals", "nothing_left",
           "setup_first", "SMALL_DATA", "is_small"]

# Measured values per candidate parameter below which a data set is small: there a prior, its scale
# chosen by cross-validation, competes with fitting or fixing each parameter
SMALL_DATA = 10


def is_small(data, n_candidates: int) -> bool:
    """Fewer than :data:`SMALL_DATA` measured values per candidate parameter."""
    return data.n_values < SMALL_DATA * max(n_candidates, 1)


def rank_judged(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, markers=(), kind="position",
                prefer=None) -> tuple[Tensor, list[str], IdentifiabilityReport]:
    """The first half of :func:`reduce_free`: the Jacobian ``(m, k)`` of ``make_problem(params)`` at its
    start over ``params``' free entries, their units, and what the Jacobian can identify
    (:func:`~torchcal.problems.identifiability.analyse_jacobian`), before any precision judgement."""
    prob = make_problem(params)
    # a problem with a prior counts its rows: a prior holds what the data cannot tell apart, and
    # splits an exact tie among its parameters rather than putting all of it on one
    J = prob.jacobian(prob.x0)
    units = [params.units[i] for i in params.free_index.tolist()]
    return J, units, analyse_jacobian(J, params.free_names, units, markers=markers, kind=kind, prefer=prefer)


def reduce_free(make_problem: Callable[[ParamSet], Problem], params: ParamSet, *, markers=(), kind="position",
                prefer=None, noise: float | None = None, plausible: dict | None = None,
                ranked: tuple[Tensor, list[str], IdentifiabilityReport] | None = None):
    """Fix the free parameters of ``params`` that the problem's Jacobian cannot identify: those
    numerically dependent on others (:func:`~torchcal.problems.identifiability.analyse_jacobian`) and, given
    the per-axis ``noise`` (m), those it determines worse than their plausible size
    (:data:`~torchcal.pipelines.precision.PLAUSIBLE`).

    ``ranked``: :func:`rank_judged` of the same problem at the same values, when the caller has it
    (it is not changed).

    Returns (a copy of ``params`` with them fixed, the identifiability report)."""
    if ranked is None:
        J, units, rep = rank_judged(make_problem, params, markers=markers, kind=kind, prefer=prefer)
    else:  # the caller keeps it: the precision judgement below writes to a copy
        J, units, rep = ranked[0], ranked[1], copy.deepcopy(ranked[2])
    out = params.clone()
    if rep.dropped:
        out.fix(*rep.dropped)
    if noise is not None and rep.identifiable:
        pos = [params.free_names.index(n) for n in rep.identifiable]
        # the instrument frame and the set-up's planes and fixed points are never dropped for
        # imprecision (no plausible size: a tracker stands metres from the robot, turned any way):
        # without them the observations that touch them mean nothing
        lim = [units[i] if not params.free_names[i].startswith(("base.", *SETUP_PREFIXES)) else "set-up" for i in pos]
        loose = imprecise(J[:, pos], rep.identifiable, lim, noise, plausible)
        for n, se in loose.items():
            out.fix(n)
            rep.dropped.append(n)
            rep.identifiable.remove(n)
            rep.imprecise.append(n)
            rep.reasons[n] = imprecise_reason(n, units[params.free_names.index(n)], se, noise)
    return out, rep


def setup_first(effects) -> list[list[str]] | None:
    """Preference tiers (``prefer=`` of :func:`~torchcal.problems.identifiability.analyse_jacobian`)
    that keep the effects' set-up parameters (:meth:`~torchcal.effects.base.Effect.setup_parameters`)
    with the set-up's own: a frame per level or in time with the instrument frame, a marker point's
    motion with the points. A robot error the data cannot tell from them is the one dropped, as
    it is for the registration; judged the other way, the fit drifts along the tie (a first joint's
    zero half a radian from where it is, the frames turned back to meet it). None when there are none."""
    roles = {n: r for e in effects for n, r in e.setup_parameters().items()}
    if not roles:
        return None
    exact = {r: [glob.escape(n) for n, rr in roles.items() if rr == r] for r in ("frame", "marker")}
    return [DEFAULT_PREFER[0] + exact["frame"], DEFAULT_PREFER[1] + exact["marker"]]


def nothing_left(loose: dict[str, str]) -> str:
    """Why no candidate is left to fit (``loose``: each parameter fixed for imprecision -> why), and
    the way out."""
    if not loose:
        return "no candidate parameter is identifiable from these rows: measure poses that move every joint"
    n, why = next(iter(loose.items()))
    fix = advice("plausible={'m': …, 'rad': …}", "--plausible-mm / --plausible-mrad")
    return (f"nothing left to fit: every identifiable parameter is pinned down worse than its plausible size "
            f"({len(loose)} fixed, e.g. {why}); loosen the plausible sizes ({fix}) or measure more poses")


def too_few_residuals(m: int, k: int, reduced: bool) -> str:
    """Why a fit of ``k`` free parameters on ``m`` residuals is refused, and the way out."""
    return (f"{m} residuals for {k} free parameters{'' if reduced else ' (no reduction asked)'}: measure more poses, "
            "or fix parameters")


def _nominal(start: ParamSet, names) -> ParamSet:
    """``start`` with ``names`` fixed at their nominal value: 0 for every error, the start for
    the instrument frame (its registration is no error of the robot)."""
    p = start.clone()
    for n in names:
        p[n] = float(start[n]) if n.startswith("base.") else 0.0
    if names:
        p.fix(*names)
    return p


@dataclass(frozen=True)
class FitOptions(Options):
    """How :func:`fit_identified` fits.

    Attributes:
        method, options, seed, progress: the solver (:func:`~torchcal.optim.get_solver`) and its settings.
        solve: optional ``(problem, **creep) -> Result`` replacing the plain solver call; ``creep`` holds the
            precision checkpoint (``checkpoint``, ``checkpoint_every``) when ``noise`` is judged from each
            fit, for a Levenberg-Marquardt solver to take.
        markers, kind, prefer: as for :func:`~torchcal.problems.identifiability.analyse_jacobian`.
        reduce: judge identifiability (False: fit every free parameter once).
        rounds: fits while the identifiable set grows (restarts for imprecision come on top:
            each fixes at least one parameter, so they end).
        noise: the per-axis measurement noise (m) that judges imprecision (:func:`reduce_free`);
            ``"residuals"``: each fit's own (:func:`~torchcal.problems.uncertainty.residual_noise`,
            the σ its standard errors are reported with); a callable ``(problem, x) -> float``: the
            noise it says the fit at ``x`` shows (a robust estimate, say); None: rank alone.
        plausible: the largest plausible error per unit (m, rad), see :func:`reduce_free`.
        zero_dropped: name prefixes of parameters set to 0 when identifiability drops them (a
            model's optional parts, whose start may hold meaningless values along the directions
            the data cannot see).
        checkpoint_every: with ``noise`` judged from each fit and the ``"lm"`` method (or a ``solve``
            that runs LM), the trial steps between precision checkpoints of a fit still going
            (:meth:`_OneProblem._creeping`); None: precision judged at the end of each fit only.
    """

    method: str = "lm"
    options: dict | None = None
    seed: int = 0
    progress: bool = False
    markers: Any = ()
    kind: str = "position"
    prefer: Any = None
    reduce: bool = True
    rounds: int = 3
    solve: Callable | None = None
    noise: float | str | Callable | None = None
    plausible: dict | None = None
    zero_dropped: tuple[str, ...] = ()
    checkpoint_every: int | None = 30


def fit_identified(make_problem: Callable[[ParamSet], Problem], params: ParamSet, settings: FitOptions | None = None,
                   **kw) -> tuple[ParamSet, Result, object]:
    """Fit the identifiable subset of ``params``' free entries, in the rounds of
    :func:`~torchcal.pipelines.rounds.fit_rounds`.

    Identifiability is judged at the start, then again at each solution; while the identifiable
    set grows the fit is repeated from the current values (nothing is reset, so the state stays
    consistent). Only once the set has stopped growing is each parameter's precision judged, at
    the noise the model *with* it reaches (a parameter judged at the misfit of a model that lacked
    it would look imprecise). A parameter judged too imprecise is fixed at its nominal value for
    good and the whole fit restarts from the start values: the other values had compensated for
    it, and continuing from them would keep that compensation.

    Args:
        make_problem: builds a problem for a ParamSet (its free flags choose the unknowns).
        settings: a :class:`FitOptions`; ``kw``: its fields, overriding it.
    Returns:
        (fitted ParamSet, the solver's Result, the last identifiability report or None).
    """
    opt = FitOptions.build(settings, **kw)
    if isinstance(opt.noise, str) and opt.noise != "residuals":
        raise ValueError(f"noise must be metres, 'residuals', a callable or None, got {opt.noise!r}")
    one = _OneProblem(make_problem, params, opt)
    if not opt.reduce:
        p, res, _ = one.run(params)
        return p, res, None
    fit_rounds(one, opt.rounds)
    return one.p, one.res, one.rep


class _OneProblem:
    """:func:`fit_identified`'s pieces of a round (:class:`~torchcal.pipelines.rounds.Rounds`) for
    one problem. ``loose``: the parameters fixed at nominal for good (imprecise, or tied at a
    solution), and why."""

    def __init__(self, make_problem: Callable[[ParamSet], Problem], params: ParamSet, opt: FitOptions):
        self.make, self.opt = make_problem, opt
        self.candidates = params.clone()
        self.judged = opt.noise is not None and not isinstance(opt.noise, (int, float))
        self.fixed_nz = None if self.judged else opt.noise  # a noise known before any fit
        self.loose: dict[str, str] = {}
        self.vague: set[str] = set()  # those of self.loose fixed for imprecision (not for rank)
        self.p, self.res, self.prob, self.rep = params, None, None, None
        self.grown: tuple | None = None
        self.ranked: tuple | None = None  # (free, values, rank_judged there) of the last judgement

    def run(self, p: ParamSet):
        """One solve of ``p``'s free entries: (fitted ParamSet, Result, the problem)."""
        opt = self.opt
        if not p.free_names:
            raise ValueError(self._nothing_left())
        prob = self.make(p)
        m, k = getattr(prob, "m", None), len(p.free_names)
        if m is not None and m < k:
            raise ValueError(too_few_residuals(m, k, opt.reduce))
        creep = {} if not (self.judged and opt.checkpoint_every) else \
            {"checkpoint": self._creeping(prob, p), "checkpoint_every": opt.checkpoint_every}
        if opt.solve is not None:
            res = opt.solve(prob, **creep)
        else:
            res = get_solver(opt.method, seed=opt.seed, progress=opt.progress, **dict(opt.options or {}),
                             **(creep if opt.method == "lm" else {})).minimize(prob)
        out = p.clone()
        out.values = prob.full(res.x).detach()
        return out, res, prob

    def _nothing_left(self) -> str:
        return nothing_left(self.loose)

    def reduce(self, p: ParamSet, noise):
        opt = self.opt
        # a judgement of rank and one of precision at the same values follow each other (after a fit
        # whose set stopped growing): the Jacobian and the rank analysis are the same, made once
        last = self.ranked
        if not (last and torch.equal(last[0], p.free) and torch.equal(last[1], p.values)):
            last = self.ranked = (p.free.clone(), p.values.clone(),
                                  rank_judged(self.make, p, markers=opt.markers, kind=opt.kind, prefer=opt.prefer))
        return reduce_free(self.make, p, noise=noise, plausible=opt.plausible, ranked=last[2])

    def zeroed(self, p: ParamSet) -> ParamSet:
        """``p`` with the optional parts identifiability dropped set to 0."""
        if self.opt.zero_dropped:
            for i, (n, f) in enumerate(zip(p.names, p.free.tolist())):
                if not f and n.startswith(self.opt.zero_dropped) and self.candidates.free[i]:
                    p.values[i] = 0.0
        return p

    def noise(self) -> float:
        """The per-axis noise the last fit shows."""
        return self._noise_at(self.prob, self.res.x)

    def _noise_at(self, prob, x: Tensor) -> float:
        if self.opt.noise == "residuals":
            return float(residual_noise(prob.residuals(x[None])[0], x.numel()))
        return float(self.opt.noise(prob, x))

    def _creeping(self, prob, p: ParamSet) -> Callable[[Tensor], str | None]:
        """The solver's checkpoint for a fit that has not converged after many steps: precision
        judged where it stands, as :meth:`judge` would judge it at the end. A fit still going is
        usually creeping along a valley of nearly equal solutions that a combination of parameters
        the data barely see spans (a few dozen poses, a full set): it would walk on for hundreds
        of steps, far from any plausible value, to be judged imprecise there. Stopped at the first
        checkpoint where a fitted parameter is pinned down worse than its plausible size, it is
        judged (and refitted without it) at once; a fit where none is goes on unchanged."""
        def check(x: Tensor) -> str | None:
            at = p.clone()
            at.values = prob.full(x).detach()
            _, rep = self.judge_at(at, self._noise_at(prob, x))
            vague = [n for n in rep.imprecise if n in at.free_names and n not in self.loose]
            return None if not vague else (f"stopped while creeping: {', '.join(vague)} pinned down worse than "
                                           "the plausible size")
        return check

    def judge_at(self, p: ParamSet, noise):
        """Rank (and, with ``noise``, precision) at ``p``'s values over the candidates not fixed
        for good."""
        nxt = self.candidates.clone()
        nxt.values = p.values.clone()
        if self.loose:
            nxt.fix(*self.loose)
        return self.reduce(nxt, noise)

    def keep_reasons(self, rep):
        for n, why in self.loose.items():
            if n not in rep.reasons:
                rep.dropped.append(n)
                rep.reasons[n] = why
            if n in self.vague and n not in rep.imprecise:  # fixed in an earlier round, for imprecision
                rep.imprecise.append(n)
        return rep

    # ------------------------------------------------------------------ the Rounds hooks
    def start(self) -> None:
        p, self.rep = self.reduce(self.candidates, self.fixed_nz)
        self.p = self.zeroed(p)

    def solve(self) -> None:
        self.p, self.res, self.prob = self.run(self.p)

    def judge(self, last: bool) -> str | None:
        """``"grow"``: fit the grown set from here; ``"restart"``: a fitted parameter left for
        good; None: final. Precision is judged only when the set does not grow (or cannot)."""
        p = self.p
        nxt, rep2 = self.judge_at(p, self.fixed_nz)
        late = [n for n in nxt.free_names if n not in p.free_names]
        if late and not last:
            self.grown = (nxt, rep2)
            return "grow"
        if self.judged:  # precision at the noise of the model as fitted
            nxt, rep2 = self.judge_at(p, self.noise())
        for n in late:  # seen only now, after the last round: never fitted, so never judged either
            if n in rep2.identifiable:
                rep2.identifiable.remove(n)
                rep2.dropped.append(n)
                rep2.reasons[n] = (f"{n} became identifiable only at the last solution, after {self.opt.rounds} "
                                   "rounds: not fitted")
            if n in nxt.free_names:
                nxt.fix(n)
        imp = [n for n in rep2.imprecise if n not in self.loose]
        tied = [n for n in p.free_names if n not in nxt.free_names and n not in imp]
        self.loose.update({n: rep2.reasons[n] for n in imp})
        self.vague.update(imp)
        self.loose.update({n: rep2.reasons.get(n, f"{n} depends on other parameters at the solution") for n in tied})
        self.rep = self.keep_reasons(rep2)
        return "restart" if [n for n in imp if n in p.free_names] or tied else None

    def advance(self, change: str, last: bool) -> bool:
        if change == "grow":
            nxt, rep2 = self.grown
            self.rep, self.p = self.keep_reasons(rep2), self.zeroed(nxt)
            return False
        # restart from a consistent state: every value from its start, the dropped at nominal
        p, rep = self.reduce(_nominal(self.candidates, list(self.loose)), self.fixed_nz)
        self.p, self.rep = self.zeroed(p), self.keep_reasons(rep)
        return True
