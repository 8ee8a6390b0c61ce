"""Fitting with identifiability: judge which free parameters the data can see, fit those,
judge again at the solution, and refit while the identifiable set grows."""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.options import Options
from torchcal.measure.setup import SETUP_PREFIXES
from torchcal.optim import Result, get_solver
from torchcal.params import ParamSet, display_unit
from torchcal.pipelines.rounds import fit_rounds
from torchcal.problems.base import Problem
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.problems.identifiability_report import IdentifiabilityReport
from torchcal.problems.uncertainty import residual_noise, unit_variances

__all__ = ["reduce_free", "rank_judged", "fit_identified", "FitOptions", "PLAUSIBLE", "check_plausible", "imprecise", "drop_imprecise",
           "imprecise_reason", "too_few_residuals", "implausible_values", "implausible_reason", "SMALL_DATA", "is_small"]

# Plausible size of a geometric error (per unit): a parameter the data pin down only to worse
# than this (one standard error) is not identified by them, whatever its numerical rank. A marker
# a few micrometres off a joint axis makes that joint's offset full-rank and meaningless.
PLAUSIBLE = {"m": 0.01, "rad": 0.01}

# Measured values per candidate parameter below which a data set is small: there a prior, its scale
# chosen by cross-validation, competes with fitting or fixing each parameter
SMALL_DATA = 10


def is_small(data, n_candidates: int) -> bool:
    """Fewer than :data:`SMALL_DATA` measured values per candidate parameter."""
    return data.n_values < SMALL_DATA * max(n_candidates, 1)


def check_plausible(plausible: dict | None) -> dict:
    """``plausible`` as a dict unit -> largest plausible error (default :data:`PLAUSIBLE`), or an
    error that says what is wrong."""
    if plausible is None:
        return dict(PLAUSIBLE)
    if not isinstance(plausible, dict):
        raise TypeError(f"plausible must be a dict unit -> size, e.g. {PLAUSIBLE}, got {type(plausible).__name__}")
    bad = [u for u in plausible if u not in PLAUSIBLE]
    if bad:
        raise ValueError(f"plausible: unknown unit(s) {bad}; geometric errors are in {sorted(PLAUSIBLE)} "
                         "(metres and radians), e.g. {'m': 0.01, 'rad': 0.01}")
    neg = {u: v for u, v in plausible.items() if not (isinstance(v, (int, float)) and v > 0)}
    if neg:
        raise ValueError(f"plausible: sizes must be positive numbers (m or rad; inf for no limit), got {neg}")
    return {u: float(v) for u, v in plausible.items()}


def drop_imprecise(J: Tensor, keep: Tensor, limit: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
    """Among each problem's ``keep`` columns, drop the one whose standard error
    ``noise · sqrt((JᵀJ)⁻¹_ii)`` exceeds its ``limit`` by the largest factor, and repeat while any
    does (each drop makes the others better determined). Batched over problems (a fleet).

    The inverse over the kept columns comes once from a QR factor
    (:func:`~torchcal.problems.uncertainty.unit_variances`); dropping column ``j`` then updates it
    by ``H − H e_j e_jᵀ H / H_jj``, the inverse of the Gram matrix without ``j``.

    Args:
        J: ``(B, m, k)`` Jacobians (m per unit); keep: ``(B, k)`` bool, full column rank;
        limit: ``(k,)`` plausible sizes (inf: none); noise: ``(B,)`` per-axis noise (m).
    Returns:
        ``(step (B, k) long: the round in which a column was dropped, −1 for the others;
        standard errors (B, k) when dropped)``.
    """
    keep = keep.clone()
    B, k = keep.shape
    step = torch.full((B, k), -1, dtype=torch.long, device=keep.device)
    se_at = J.new_zeros(B, k)
    s = J.norm(dim=1).clamp(min=1e-300)
    An = J / s[:, None, :]
    H = unit_variances(An, keep, full=True)  # (B, k, k) inverse Gram over the kept columns
    rows = torch.arange(B, device=keep.device)
    for t in range(k):
        se = noise[:, None] * H.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt() / s
        ratio = torch.where(keep, se / limit, torch.full_like(se, -1.0))
        worst_ratio, worst = ratio.max(-1)
        hit = worst_ratio > 1
        if not bool(hit.any()):
            break
        r, j = rows[hit], worst[hit]
        step[r, j] = t
        se_at[r, j] = se[hit, j]
        keep[r, j] = False
        h = H[r, :, j]
        H[r] = H[r] - h[:, :, None] * h[:, None, :] / h[torch.arange(r.numel()), j][:, None, None]
    return step, se_at


def imprecise(J, names: list[str], units: list[str], noise: float, plausible: dict | None = None) -> dict[str, float]:
    """Parameters whose standard error ``noise · sqrt((JᵀJ)⁻¹_ii)`` exceeds their plausible size,
    dropped worst first (:func:`drop_imprecise`): name -> standard error, in the order dropped."""
    plausible = PLAUSIBLE if plausible is None else plausible
    J = torch.as_tensor(J)
    lim = torch.tensor([plausible.get(u, float("inf")) for u in units], dtype=J.dtype, device=J.device)
    keep = torch.ones(1, len(names), dtype=torch.bool, device=J.device)
    step, se = drop_imprecise(J[None], keep, lim, torch.tensor([float(noise)], dtype=J.dtype, device=J.device))
    order = sorted((t, i) for i, t in enumerate(step[0].tolist()) if t >= 0)
    return {names[i]: float(se[0, i]) for _, i in order}


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
    the per-axis ``noise`` (m), those it determines worse than their :data:`PLAUSIBLE` size.

    ``ranked``: :func:`rank_judged` of the same problem at the same values, when the caller has it
    (it is not changed).

    Returns (a copy of ``params`` with them fixed, the identifiability report)."""
    J, units, rep = ranked or rank_judged(make_problem, params, markers=markers, kind=kind, prefer=prefer)
    rep = copy.deepcopy(rep)
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
            rep.imprecise.append(n)
            rep.reasons[n] = imprecise_reason(n, units[params.free_names.index(n)], se, noise)
    return out, rep


def too_few_residuals(m: int, k: int, reduced: bool) -> str:
    """Why a fit of ``k`` free parameters on ``m`` residuals is refused, and the way out."""
    return (f"{m} residuals for {k} free parameters{'' if reduced else ' (no reduction asked)'}: measure more poses, "
            "or fix parameters")


def imprecise_reason(name: str, unit: str, se: float, noise: float) -> str:
    """Why a parameter of full rank is not identified: its standard error ``se`` (its unit) at
    the per-axis ``noise`` (m) exceeds what such an error can plausibly be."""
    f, u = display_unit(unit)
    return (f"{name} is determined only to ±{se * f:.3g} {u} by these poses (noise {noise * 1e3:.3g} mm), more "
            "than such an error can plausibly be")


def implausible_values(params: ParamSet, robot, plausible: dict | None = None) -> dict[str, float]:
    """Fitted errors of the robot's joints (origin shifts, turns, zero offsets, DH errors) larger than
    their plausible size: name -> value (its unit). The instrument frame and the marker points are
    unknowns of the set-up, not errors of the robot, and are never judged here."""
    plausible = PLAUSIBLE if plausible is None else plausible
    joints = set(robot.joint_names)
    out = {}
    for n, v, u, f in zip(params.names, params.values.tolist(), params.units, params.free.tolist()):
        if f and n.split(".")[0] in joints and abs(v) > plausible.get(u, float("inf")):
            out[n] = v
    return out


def implausible_reason(values: dict[str, float], units: dict[str, str], plausible: dict) -> str:
    """Why a model with ``values`` (name -> value) is refused, in words, with the way out."""
    def one(n):
        f, u = display_unit(units[n])
        return f"{n} = {values[n] * f:+.4g} {u}"
    lim = ", ".join(f"{plausible[u] * display_unit(u)[0]:g} {display_unit(u)[1]}" for u in sorted(plausible))
    return (f"the fit moves or turns joints by more than a plausible error ({lim}): "
            + ", ".join(one(n) for n in list(values)[:6]) + (" …" if len(values) > 6 else "")
            + ". The data cannot support this model: measure more poses spread over the joint ranges, fit fewer "
              "parameters, or, if errors this large are real, raise the limit ("
            + advice("plausible={'m': …, 'rad': …}", "--plausible-mm, --plausible-mrad") + ")")


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
        solve: optional ``(problem) -> Result`` replacing the plain solver call.
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
        checkpoint_every: with ``noise`` judged from each fit and the ``"lm"`` method, the trial
            steps between precision checkpoints of a fit still going (:meth:`_OneProblem._creeping`);
            None: precision judged at the end of each fit only.
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
        if opt.solve is not None:
            res = opt.solve(prob)
        else:
            extra = {} if not (self.judged and opt.method == "lm" and opt.checkpoint_every) else \
                {"checkpoint": self._creeping(prob, p), "checkpoint_every": opt.checkpoint_every}
            res = get_solver(opt.method, seed=opt.seed, progress=opt.progress, **dict(opt.options or {}),
                             **extra).minimize(prob)
        out = p.clone()
        out.values = prob.full(res.x).detach()
        return out, res, prob

    def _nothing_left(self) -> str:
        """Why no candidate is left to fit, and the way out."""
        if not self.loose:
            return "no candidate parameter is identifiable from these rows: measure poses that move every joint"
        n, why = next(iter(self.loose.items()))
        fix = advice("plausible={'m': …, 'rad': …}", "--plausible-mm / --plausible-mrad")
        return (f"nothing left to fit: every identifiable parameter is pinned down worse than its plausible size "
                f"({len(self.loose)} fixed, e.g. {why}); loosen the plausible sizes ({fix}) or measure more poses")

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
