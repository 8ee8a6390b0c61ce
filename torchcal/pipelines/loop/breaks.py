"""Breaks in time or the row order placed again once the model around them is fitted.

A step or a window of a time or row driver (a set-up changed there, a payload swapped) is placed by
the screening: a linear view of what the model left before the change was in it. The fit then moves
every other parameter, and where the change is large (a frame moved by decimetres and turned by a
third of a radian, far from where its columns were taken) or a later finding takes part of the
residual the break was placed on, the screening's place can sit a row or two off. Those rows are
then explained by neither side: the robust loss takes them for outliers and the parameters around
them are pulled.

So after every accepted round each break of the model moves to the neighbouring places a step can
sit at (:func:`~torchcal.effects.shapes.step_breaks` of the training rows), one place at a time
while the robust training objective falls, the model's other parameters fitted again at each place;
a window's two ends each move so. A break's place is a value of the model fitted like the others:
the same parameters, only where the change happens. The place found is kept unless the
cross-validated error says the old one was better.
"""
from __future__ import annotations

from torchcal.effects.shapes import WINDOW, break_words, step_breaks, window_parts, window_tag
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.evaluate import evaluate, fit_params
from torchcal.pipelines.crossval.models import Context, Model, effect_problem
from torchcal.pipelines.crossval.priors import prior_weights
from torchcal.pipelines.crossval.scores import penalised
from torchcal.pipelines.loop.parts import assemble, split_params

__all__ = ["model_breaks", "place_breaks", "renamed", "MAX_MOVES"]

MAX_MOVES = 32   # places a break moves at most, one neighbour at a time (each while the objective falls)
_MIN_INSIDE = 3  # rows a window holds at least (as the screening's windows do)
# trial steps of a fit at a neighbouring place: fewer can only leave its objective higher, so a place
# that wins within them wins converged; the place kept is then fitted to convergence
PROBE_STEPS = 10


def model_breaks(m: Model) -> list[str]:
    """Every break of the model's effects (``<column>~step<k>``, ``<column>~win<a>@<b>``), once."""
    return list(dict.fromkeys(b for e in m.effects for b in e.breaks()))


def renamed(label: str, moves: list[tuple[str, str]]) -> str:
    """A mode's label (``<thing>~<driver>~<shape>``: a driver family's ``time:<column>`` or ``row``, a
    load's part at a break ``load~<column>~<shape>``) after the breaks ``moves`` (``(old, new)``, in
    order) were placed again."""
    for old, new in moves:
        col, _, tag = old.partition("~")
        parts = label.split("~")
        if len(parts) >= 3 and parts[-1] == tag and parts[-2] in (col, f"time:{col}"):
            label = "~".join(parts[:-1] + [new.partition("~")[2]])
    return label


def _moved(ctx: Context, params: ParamSet, effects: list, old: str, new: str) -> tuple[ParamSet, list]:
    """``params`` and ``effects`` with the break ``old`` at ``new`` (values kept)."""
    geo, parts = split_params(params, ctx.robot, effects)
    moved, out = [], []
    for e, p in zip(effects, parts):
        e2 = e.with_break(old, new)
        moved.append(e2)
        out.append(p if e2 is e else ParamSet(list(e2.param_names), p.units, p.values, p.free, p.lower, p.upper))
    return assemble(geo, out), moved


def _objective(ctx: Context, params: ParamSet, effects: list, prior) -> float:
    """The robust training objective (the fit's sum of squares, its prior rows included)."""
    prob = effect_problem(ctx, params, effects, ctx.data, prior)
    return float((prob.residuals(prob.x0[None]) ** 2).sum())


def _neighbours(key: str, places: list[float], x) -> list[str]:
    """The breaks one place away from ``key`` on either side (each end of a window), as keys."""
    col, _, tag = key.partition("~")
    out = []
    if tag.startswith("step"):
        ends = [float(tag[4:])]
    elif tag.startswith(WINDOW):
        ends = list(window_parts(tag))
    else:
        return out
    for e, v in enumerate(ends):
        i = min(range(len(places)), key=lambda k: abs(places[k] - v))
        for j in (i - 1, i + 1):
            if not 0 <= j < len(places) or places[j] == v:
                continue
            if len(ends) == 1:
                out.append(f"{col}~step{places[j]:.10g}")
                continue
            a, b = (places[j], ends[1]) if e == 0 else (ends[0], places[j])
            if a < b and int(((x >= a) & (x < b)).sum()) >= _MIN_INSIDE:
                out.append(f"{col}~{window_tag(a, b)}")
    return out


def _place(ctx: Context, m: Model, key: str) -> tuple[str, ParamSet | None, list, float, float]:
    """The place of the break ``key`` with the lowest objective, reached one neighbour at a time:
    (its key, the fit there or None when it stays, the effects, the objective before and after)."""
    col = key.partition("~")[0]
    x = ctx.data.covariates[col].double()
    places = step_breaks(x)
    prior = prior_weights(ctx.robot, m.params, m.prior_mm, ctx.sigma, m.effects)
    s0 = best_s = _objective(ctx, m.params, m.effects, prior)
    at, here, effects = key, m.params, m.effects
    tried = {key}
    for _ in range(MAX_MOVES):
        step = None
        for cand in _neighbours(at, places, x):
            if cand in tried:
                continue
            tried.add(cand)
            params, effs = _moved(ctx, here, effects, at, cand)
            fit = fit_params(ctx, params, effs, ctx.data, prior, reduce=False, max_iter=PROBE_STEPS)
            s = _objective(ctx, fit, effs, prior)
            if s < best_s:
                best_s, step = s, (cand, fit, effs)
        if step is None:
            break
        at, here, effects = step
    return at, (here if at != key else None), effects, s0, best_s


def place_breaks(ctx: Context, m: Model, say, only=None) -> tuple[Model, list[dict]]:
    """Every break of ``m`` (``only``: those of them) placed again (module docstring): the model with
    the places kept, and a record per break moved."""
    n_obs, moved = ctx.n_obs, []
    for key in model_breaks(m):
        if key not in model_breaks(m) or (only is not None and key not in only):
            continue  # not asked for, or moved with a break before it (two effects held it)
        at, fit, effects, s0, s1 = _place(ctx, m, key)
        if fit is None:
            continue
        cand = evaluate(ctx, m.label, fit, effects, m.prior_mm, reduce=False, info=m.info)
        ok = penalised(cand.scores, cand.k, n_obs) <= penalised(m.scores, m.k, n_obs)
        moved.append({"break": key, "to": at, "objective_drop": 1 - s1 / s0, "cv_rmse_mm_before": m.cv_rmse_mm(n_obs),
                      "cv_rmse_mm_after": cand.cv_rmse_mm(n_obs), "kept": ok})
        say(f"break at {break_words(key)} placed again at {break_words(at)}: training objective "
            f"{100 * (1 - s1 / s0):.1f} % lower, CV {m.cv_rmse_mm(n_obs):.4f} -> {cand.cv_rmse_mm(n_obs):.4f} mm  "
            + ("kept" if ok else "not kept"))
        if ok:
            m = cand
    return m, moved
