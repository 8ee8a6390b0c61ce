"""The loop's steps: try a candidate effect, compare two models on cross-validated row scores, refit
under a tightened threshold, the held-out gain, the ELM's cross-validated residual."""
from __future__ import annotations

import math

import torch
from torch import Tensor
from tqdm.auto import tqdm

from torchcal.elm import ELM
from torchcal.effects import build_effect
from torchcal.measure.setup import Setup
from torchcal.pipelines.crossval.models import Context, Model, noise_sigma, observation_model
from torchcal.pipelines.crossval.evaluate import evaluate, evaluate_prior, rescore
from torchcal.pipelines.loop.loadscan import load_changes
from torchcal.pipelines.loop.records import Candidate, Trial
from torchcal.pipelines.crossval.scores import HUBER_K, compare, penalised, row_scores
from torchcal.pipelines.fitting import setup_first
from torchcal.pipelines.loop.stages import elm_inputs, residual_matrix, stage_stats
from torchcal.pipelines.loop.start import effect_start
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.problems.unseen import unseen

__all__ = ["clipped", "compare_at", "elm_cv", "parameter_table", "progress_bar", "refit", "refresh",
           "test_gain", "try_candidate"]


def parameter_table(ctx: Context, m: Model) -> tuple[list, dict]:
    """The final model's identified parameters (value, unit, standard error) and the condition
    number and observability indices (O1-O4) of their Jacobian."""
    p = m.params
    se = m.info.get("se", {})
    table = [{"name": n, "value": float(v), "unit": u, "std_error": se.get(n)}
             for n, v, u, f in zip(p.names, p.values.tolist(), p.units, p.free.tolist()) if f]
    prob = observation_model(ctx, p, m.effects, ctx.data)
    rep = analyse_jacobian(prob.data_jacobian(prob.x0), p.free_names, [p.units[i] for i in p.free_index.tolist()],
                           markers=ctx.robot.marker_names, prefer=setup_first(m.effects))
    fin = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
    out = {"condition": fin(rep.condition), "O1": fin(rep.O1), "O2": fin(rep.O2), "O3": fin(rep.O3),
           "O4": fin(rep.O4), "rank": rep.rank, "n_params": rep.n_params, "not_seen_by_data": list(rep.dropped)}
    if not ctx.data.positions_only:
        out["not_seen"] = unseen(ctx.robot, ctx.data, p, ctx.setup)
    return table, out


def progress_bar(progress: bool):
    """The diagnosis's bar over the candidate effects (its total set each round, so that tqdm
    estimates the time the round has left), or None."""
    if not progress:
        return None
    return tqdm(desc="diagnosis", unit="candidate")


def try_candidate(ctx: Context, current: Model, name: str, robot, train, n_obs: int, say, rnd: int,
                  tabu=frozenset()) -> Trial:
    """One candidate effect against ``current``: its start (modes chosen), fit, CV and the rule;
    under a geometric prior, the prior is re-chosen among its neighbours with the effect. A candidate
    that waits for what a later round may find (:meth:`~torchcal.effects.base.Effect.waiting`) is
    recorded with its reason and not tried."""
    covering = [e.name for e in current.effects if name in getattr(e, "supersedes", ()) and e.name != name]
    if covering:
        why = f"its modes are part of the accepted {covering[0]}"
        return Trial(name, Candidate(name, "covered", reason=why, round=rnd), covered=True)
    eff = build_effect(name, robot, train, geometry=current.params.values[: robot.n_params])
    changes = []
    if eff.reads_load_changes:
        known = [s for e in current.effects for s in [*e.session_steps(), *getattr(e, "loads", ())]]
        changes = load_changes(ctx, current, known)
    eff = eff.given(current.effects, train, changes)
    for label, _ in eff.break_parts():  # a part that left in this run is not offered again
        if label in tabu:
            eff = eff.without_part(label)
    why = eff.waiting()
    if why is not None:  # recorded, not said: it waits every round until a later finding gives it something
        return Trial(name, Candidate(name, "not proposed", reason=why, round=rnd))
    # a family replaces what it extends: an effect it supersedes, or itself accepted with fewer modes
    superseded = [e for e in current.effects if e.name in eff.supersedes or (eff.selectable and e.name == name)]
    start = effect_start(ctx, current, eff, superseded, tabu)
    if start.effect is None:
        say(f"round {rnd}: {name:<20} {start.reason}")
        return Trial(name, Candidate(name, "not proposed", reason=start.reason, selection=start.selection, round=rnd))
    if start.prior_mm is None:
        best = evaluate(ctx, f"+{name}", start.params, start.effects, None, info=start.info)
    else:  # with the effect in, the geometry may want another prior: its CV chooses again
        best = evaluate_prior(ctx, f"+{name}", start.params, start.effects, start.prior_mm, info=start.info)
    t, pen_ok, ok = compare(current.scores, best.scores, current.k, best.k, n_obs)
    gain = current.cv_rmse_mm(n_obs) - best.cv_rmse_mm(n_obs)
    modes = [lab for lab, _ in best.effects[-1].modes()] if best.effects[-1].selectable else []
    before = {lab for e in superseded for lab, _ in e.modes()}
    say(f"round {rnd}: {name:<20} {best.k:>5.1f} params  CV {best.cv_rmse_mm(n_obs):.4f} mm  gain {gain:+.4f} mm"
        f"  t = {t:.1f}" + (f"  modes: {', '.join(modes)}" if modes else ""))
    line = Candidate(name, "fitted", round=rnd, n_params=int(round(best.k)), cv_rmse_mm=best.cv_rmse_mm(n_obs),
                     cv_gain_mm=gain, t=t, penalised_ok=pen_ok, modes=modes,
                     added_modes=[lab for lab in modes if lab not in before], extends=[e.name for e in superseded],
                     selection=start.selection, aliases=start.aliases, soft=start.soft, prior_mm=best.prior_mm)
    return Trial(name, line, model=best, ok=ok)


def compare_at(ctx: Context, best: Model, m: Model, n_obs: int) -> tuple[float, bool, bool]:
    """The rule between ``best`` and ``m``, scored with ``best``'s own Huber threshold: scores
    are held constant beyond a multiple of the threshold, so a threshold set by a better model
    would make every error of a coarse one look alike."""
    c = HUBER_K * noise_sigma(ctx, best)
    if c <= ctx.c:
        return compare(best.scores, m.scores, best.k, m.k, n_obs)
    at = ctx.at(c)
    return compare(rescore(at, best), rescore(at, m), best.k, m.k, n_obs)


def refit(ctx: Context, m: Model) -> Model:
    """``m`` fitted again under the context's threshold, every candidate parameter judged again:
    with less noise left, parameters the rounds before could not see may be seen now."""
    again = m.params.clone()
    again.free[: ctx.n_geo] = m.info["candidates"]
    again.free[ctx.n_geo:] = True
    return evaluate(ctx, m.label, again, m.effects, m.prior_mm, info=m.info)


def refresh(ctx: Context, m: Model, n_obs: int) -> Model:
    """The accepted model with its new effect's features recomputed at the geometry fitted with
    it: the rigid fit it started from had absorbed part of the effect into the geometry (a mean
    joint deflection into a zero offset), and the gravity torques depend on those angles."""
    geo = m.params.values[: ctx.robot.n_params]
    eff = m.effects[-1].at_geometry(geo)
    eff.theta = m.effects[-1].theta.clone()
    again = evaluate(ctx, m.label, m.params, m.effects[:-1] + [eff], m.prior_mm, info=m.info)
    return again if penalised(again.scores, again.k, n_obs) <= penalised(m.scores, m.k, n_obs) else m


def test_gain(robot, current: Model, cand: Model, test, setup: Setup | None = None,
              rot_weight: float | None = None) -> float | None:
    """Held-out mean gain of a candidate over the current model (measured after the decision)."""
    if test is None:
        return None
    a, _ = stage_stats(robot, current.params, current.effects, test, setup=setup, rot_weight=rot_weight)
    b, _ = stage_stats(robot, cand.params, cand.effects, test, setup=setup, rot_weight=rot_weight)
    return a.mean - b.mean


def clipped(r: Tensor, c: float | None) -> Tensor:
    """``(N, 3M)`` residuals with each observation shortened to at most ``c`` (Huber's
    pseudo-observations: a least-squares learner fitted to them is as robust as the loss), NaN -> 0."""
    r3 = torch.nan_to_num(r).reshape(r.shape[0], -1, 3)
    if c is not None:
        n = r3.norm(dim=-1, keepdim=True)
        r3 = r3 * torch.where(n > c, c / n.clamp(min=1e-300), torch.ones_like(n))
    return r3.reshape(r.shape)


def elm_cv(ctx: Context, current: Model, n_hidden: int, seed: int) -> tuple[Tensor, Tensor]:
    """Cross-validated per-row scores (Huber, and plain squared errors) of the current model plus
    a residual ELM fitted per fold."""
    robot, data = ctx.robot, ctx.data
    out = torch.zeros(len(data), dtype=robot.dtype, device=robot.device)
    plain = torch.zeros_like(out)
    for f, p in zip(ctx.folds, current.fold_fits):
        mask = torch.ones(len(data), dtype=torch.bool, device=data.q.device)
        mask[f] = False
        tr, va = data.subset(mask), data.subset(f)
        r_tr = clipped(residual_matrix(robot, p, current.effects, tr), ctx.c)
        model = ELM(n_hidden=n_hidden, ridge=1e-3, seed=seed).fit(elm_inputs(tr), r_tr)
        left = (residual_matrix(robot, p, current.effects, va) - model.predict(elm_inputs(va))).reshape(len(va), -1, 3)
        seen = va.seen
        rows = torch.nonzero(seen)[:, 0]
        out[f] = row_scores(left[seen].norm(dim=-1), rows, len(va), ctx.c)
        plain[f] = row_scores(left[seen].norm(dim=-1), rows, len(va), None)
    return out, plain
