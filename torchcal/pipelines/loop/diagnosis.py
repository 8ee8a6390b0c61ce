"""The loop's diagnosis: rounds in which every candidate effect is tried against the current
model and the best that passes the rule is added, until none passes.

A round tightens the Huber threshold to what the current model leaves, tries the catalogued
effects, and only when none of them passes the general families (``fallback``). An effect that
holds another that passes too (it supersedes it: joint compliance under a logged load holds plain
joint compliance) wins only where it beats that one by the rule: what it adds must be seen, not
only what they share. Candidates gaining within 2 % of the winner's gain are ties, taken by the
fewest parameters, then the registry's order. A family that defers to another (a frame's path to the
drivers' named shapes) wins only where it beats that one by the rule too. After each acceptance every
earlier mode is judged again (:mod:`~torchcal.pipelines.loop.prune`). A break in time or the row order
is placed again (:mod:`~torchcal.pipelines.loop.breaks`) in the round that found it, and once more
after the last round, with every later finding in.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.effects import EFFECTS, build_effect
from torchcal.pipelines.loop.breaks import model_breaks, place_breaks, renamed
from torchcal.measure.data import Measurements
from torchcal.pipelines.loop.covariates import extrapolation
from torchcal.pipelines.loop.geometry import geometry_again
from torchcal.pipelines.crossval.models import Context, Model, noise_sigma
from torchcal.pipelines.loop.prune import prune
from torchcal.pipelines.loop.records import Candidate, Trial
from torchcal.pipelines.crossval.scores import HUBER_K, penalised
from torchcal.pipelines.loop.steps import compare_at, progress_bar, refit, refresh, test_gain, try_candidate

__all__ = ["Step", "Diagnosis", "diagnose", "MAX_ROUNDS"]

MAX_ROUNDS = 20  # diagnosis rounds at most: each accepts one effect (or modes of one family)


@dataclass
class Step:
    """One accepted effect: its name, the model after it, the trial that won its round and how many
    breaks had been placed again when it was accepted (those placed later rename its modes)."""
    name: str
    model: Model
    trial: Trial
    moves_at: int = 0


@dataclass
class Diagnosis:
    """What the rounds leave: the final model and context (its threshold followed the residual),
    the accepted steps in order (each trial keeps the modes pruned after it), every candidate line
    and the extrapolation flags."""
    ctx: Context
    current: Model
    steps: list[Step] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    flags: list[dict] = field(default_factory=list)
    geometry_again: list[dict] = field(default_factory=list)  # the geometry judged again (geometry_again)
    breaks: list[dict] = field(default_factory=list)  # breaks placed again (place_breaks), kept or not
    moves: list[tuple[str, str]] = field(default_factory=list)  # (old, new) of the breaks kept at a new place
    placed: set[str] = field(default_factory=set)  # the breaks placed since the last finding came in


def diagnose(ctx: Context, start: Model, names: list[str], test: Measurements | None, say,
             progress: bool = False, as_measured: Measurements | None = None) -> Diagnosis:
    """The rounds from the geometric model ``start`` over the candidate effects ``names``
    (``test``: held-out rows, only measured: each candidate's held-out gain; ``as_measured``: the
    same rows before another session's time was held, whose covariates the flags judge)."""
    d = Diagnosis(ctx, start)
    pool = _applicable(d, names, test if as_measured is None else as_measured)
    bar = progress_bar(progress)
    tabu: dict[str, set[str]] = {}  # effect -> modes pruned in this run
    for rnd in range(1, MAX_ROUNDS + 1):
        if not pool:
            break
        _follow_threshold(d, once=True)
        trials = _try_round(d, pool, rnd, tabu, say, bar)
        winner = _winner(d.ctx, d.current, trials, names)
        for tr in trials:
            tr.line.accepted = tr is winner
            if tr.model is not None:
                tr.line.test_gain_mm = test_gain(d.ctx.robot, d.current, tr.model, test, d.ctx.setup,
                                                 d.ctx.rot_weight)
            d.candidates.append(tr.line)
        if winner is None:
            break
        pool = _accept(d, winner, pool, tabu, say)
    if bar is not None:
        bar.close()
    _place_again(d, say)
    # the final model, refitted until the Huber threshold has followed its own residual: rows it
    # now explains to the noise shrink the threshold, and outliers pull less
    _follow_threshold(d, once=False)
    return d


def _applicable(d: Diagnosis, names: list[str], test: Measurements | None) -> list[str]:
    """The candidates the training rows allow; the others get their line now."""
    pool = []
    for n in names:
        eff = build_effect(n, d.ctx.robot, d.ctx.data, geometry=d.current.params.values[: d.ctx.robot.n_params])
        ok, why = eff.applicable(d.ctx.data)
        if not ok or eff.n_params == 0:
            d.candidates.append(Candidate(n, "not applicable", reason=why or "no parameters", applicable=False))
            continue
        pool.append(n)
        # whatever the selection decides, the held-out rows cannot check a candidate whose
        # covariates they leave: say so for every candidate tried
        d.flags += extrapolation(eff, test)
    return pool


def _follow_threshold(d: Diagnosis, once: bool) -> None:
    """Tighten the Huber threshold to what the current model leaves and refit it under it, so
    that no candidate is credited with what the tighter threshold alone gains (``once``: one
    refit at the start of a round; else until it settles, at most three)."""
    for _ in range(1 if once else 3):
        sigma = noise_sigma(d.ctx, d.current)
        if abs(HUBER_K * sigma - d.ctx.c) <= 0.1 * d.ctx.c:
            return
        d.ctx = d.ctx.at(HUBER_K * sigma)
        d.current = refit(d.ctx, d.current)
        if d.steps:
            d.steps[-1].model = d.current


def _try_round(d: Diagnosis, pool: list[str], rnd: int, tabu: dict, say, bar) -> list[Trial]:
    """Every candidate of the pool against the current model: the catalogued effects, then the
    general families only when none of those passes (they take what the catalogue leaves)."""
    trials: list[Trial] = []
    if bar is not None:  # at most every candidate of the pool; the general families only when needed
        bar.reset(total=len(pool))
        bar.set_description(f"round {rnd}")
    for tier in ([n for n in pool if not EFFECTS[n].fallback], [n for n in pool if EFFECTS[n].fallback]):
        if any(t.ok for t in trials):
            break
        for n in tier:
            if bar is not None:
                bar.set_description(f"round {rnd}: {n}")
            tr = try_candidate(d.ctx, d.current, n, d.ctx.robot, d.ctx.data, d.ctx.n_obs, say, rnd,
                               tabu.get(n, set()))
            if bar is not None:
                bar.update(1)
            if tr.covered:
                pool.remove(n)
            trials.append(tr)
    return trials


def _winner(ctx: Context, current: Model, trials: list[Trial], names: list[str]) -> Trial | None:
    """The passing trial with the lowest penalised score; trials gaining within 2 % of its gain
    are ties: the fewest parameters, then the registry's order (the plainer effect) take it. A trial
    whose effect supersedes another passing one, or defers to it (:attr:`Effect.defers_to`), stays in
    only where it beats that one by the rule."""
    n_obs = ctx.n_obs
    passing = [t for t in trials if t.ok]
    held = {t.name: t for t in passing}
    passing = [t for t in passing if all(compare_at(ctx, held[s].model, t.model, n_obs)[2]
                                         for s in (*EFFECTS[t.name].supersedes, *EFFECTS[t.name].defers_to)
                                         if s in held)]
    if not passing:
        return None
    best = min(passing, key=lambda t: penalised(t.model.scores, t.model.k, n_obs))
    gain = float(current.scores.mean() - best.model.scores.mean())
    ties = [t for t in passing if float(current.scores.mean() - t.model.scores.mean()) >= 0.98 * gain]
    return min(ties, key=lambda t: (t.model.k, names.index(t.name)))


def _protected(name: str, new_modes: list[str], moves: list[tuple[str, str]]) -> set[tuple[str, str]]:
    """The modes just accepted (``(effect name, label)``): they passed the rule against everything
    before them and are not judged again, unless one sits at a break ``moves`` placed elsewhere: then
    they passed at a place the fit no longer has, and are judged again as older ones are."""
    if any(renamed(lab, moves) != lab for lab in new_modes):
        return set()
    return {(name, lab) for lab in new_modes}


def _place_again(d: Diagnosis, say) -> None:
    """The breaks placed in earlier rounds, placed again with every finding in (those placed after
    the last one came in are where that model puts them). Where one moves, every mode is judged
    again as after an acceptance: the modes at it passed the rule at a place the fit no longer has."""
    old = [b for b in model_breaks(d.current) if b not in d.placed]
    if not old or not d.steps:
        return
    d.current, placed = place_breaks(d.ctx, d.current, say, only=old)
    d.breaks += [dict(b, after="the last round") for b in placed]
    kept = [(b["break"], b["to"]) for b in placed if b["kept"]]
    last = d.steps[-1]
    if kept:
        d.moves += kept
        protect = _protected(last.name, last.trial.line.added_modes or last.trial.line.modes, kept)
        d.current, gone = prune(d.ctx, d.current, protect, say)
        last.trial.pruned = [*last.trial.pruned, *gone]
    last.model = d.current


def _accept(d: Diagnosis, winner: Trial, pool: list[str], tabu: dict, say) -> list[str]:
    """Add the winner, place the breaks it found again, judge every earlier mode again, and return the
    next round's pool."""
    before = set(model_breaks(d.current))
    d.current = refresh(d.ctx, winner.model, d.ctx.n_obs)
    new_modes = winner.line.added_modes or [lab for lab, _ in d.current.effects[-1].modes()]
    d.current, placed = place_breaks(d.ctx, d.current, say, only=set(model_breaks(d.current)) - before)
    d.breaks += [dict(b, after=winner.name) for b in placed]
    kept = [(b["break"], b["to"]) for b in placed if b["kept"]]
    protect = _protected(winner.name, new_modes, kept)
    if kept:
        d.moves += kept
        line = winner.line
        line.modes = [renamed(x, kept) for x in line.modes]
        line.added_modes = [renamed(x, kept) for x in line.added_modes]
    d.current, gone = prune(d.ctx, d.current, protect, say)
    if gone:
        winner.pruned = gone
        for g in gone:  # what left is not tried again in this run
            tabu.setdefault(g["effect"], set()).update(g.get("modes", [g["mode"]]))
        pool = list(dict.fromkeys(pool + [g["effect"] for g in gone]))  # its other modes may still come
    d.ctx, d.current, again = geometry_again(d.ctx, d.current, say)
    if again is not None:
        d.geometry_again.append(dict(again, after=winner.name))
    d.placed = set(model_breaks(d.current)) - before
    d.steps.append(Step(winner.name, d.current, winner, len(d.moves)))
    if not d.current.effects[-1].selectable:  # a family stays a candidate: it may gain modes later
        pool.remove(winner.name)
    say(f"accepted {winner.name}" + (f" ({', '.join(winner.line.added_modes)})" if winner.line.added_modes else ""))
    return pool
