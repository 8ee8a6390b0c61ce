"""A candidate fitted on all training rows (identifiable subset, judged at the start and again at
the solution) and K-fold cross-validated from that fit; the prior scale chosen by the same CV.

Fits use the Huber loss with the context's threshold; the folds start from the full fit with the
same free set.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import (Context, Model, effect_problem, fit_noise, noise_sigma_of,
                                                observation_errors)
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, prior_weights
from torchcal.pipelines.crossval.scores import effective_params, penalised, row_scores
from torchcal.pipelines.fitting import fit_identified
from torchcal.problems.uncertainty import standard_errors

__all__ = ["fit_params", "rescore", "evaluate", "cv_mean_mm", "evaluate_prior"]


def fit_params(ctx: Context, params: ParamSet, effects: list, data: Measurements, prior, reduce: bool) -> ParamSet:
    make = lambda p: effect_problem(ctx, p, effects, data, prior)  # noqa: E731
    opts = {"max_iter": 200 if reduce else 100}
    # under a prior nothing is dropped for imprecision: the prior holds what the data barely see;
    # otherwise the noise the candidate itself reaches says how well a parameter is seen
    noise = fit_noise if prior is None else None
    optional = tuple(f"{e.name}." for e in effects)
    ps, _, _ = fit_identified(make, params, reduce=reduce, markers=ctx.robot.marker_names, options=opts, noise=noise,
                              zero_dropped=optional, plausible=ctx.plausible)
    return ps


def rescore(ctx: Context, m: Model) -> Tensor:
    """A model's cross-validated per-row scores under the context's (new) threshold, from its
    fold fits."""
    out = torch.zeros(len(ctx.data), dtype=ctx.robot.dtype, device=ctx.robot.device)
    for f, p in zip(ctx.folds, m.fold_fits):
        e, rows = observation_errors(ctx, p, m.effects, ctx.data.subset(f))
        out[f] = row_scores(e.norm(dim=-1), rows, len(f), ctx.c)
    return out


def evaluate(ctx: Context, label: str, start: ParamSet, effects: list, prior_mm: float | None,
             reduce: bool = True, info: dict | None = None) -> Model:
    """Fit ``start`` on all training rows (identifiable subset, judged at the start and again
    at the solution), then K-fold cross-validate it from that fit."""
    prior = prior_weights(ctx.robot, start, prior_mm, ctx.sigma, effects)
    full = fit_params(ctx, start, effects, ctx.data, prior, reduce)
    prior = prior_weights(ctx.robot, full, prior_mm, ctx.sigma, effects)
    prob = effect_problem(ctx, full, effects, ctx.data, prior)
    x = prob.x0
    J = prob.data_jacobian(x) * prob.observation_weights(x).repeat_interleave(3)[:, None]
    pf = None if prior is None else prior[full.free_index]
    k = effective_params(J, pf)
    info = dict(info or {})
    # how far noise alone moves each value: σ sqrt((JᵀJ + W²)⁻¹_ii) at the fit's robust noise
    se = standard_errors(J, sigma=noise_sigma_of(ctx, full, effects, k), prior=pf, singular="pinv")
    info["se"] = dict(zip(full.free_names, se.tolist()))
    scores = torch.zeros(len(ctx.data), dtype=ctx.robot.dtype, device=ctx.robot.device)
    sq = torch.zeros_like(scores)
    fits = []
    for f in ctx.folds:
        mask = torch.ones(len(ctx.data), dtype=torch.bool, device=ctx.data.q.device)
        mask[f] = False
        p = fit_params(ctx, full, effects, ctx.data.subset(mask), prior, reduce=False)
        e, rows = observation_errors(ctx, p, effects, ctx.data.subset(f))
        scores[f] = row_scores(e.norm(dim=-1), rows, len(f), ctx.c)
        sq[f] = row_scores(e.norm(dim=-1), rows, len(f), None)
        fits.append(p)
    # the free set before identifiability: later fits judge it again, with the noise they see then
    info.setdefault("candidates", start.free[: ctx.n_geo].clone())
    return Model(label, full, list(effects), prior_mm, k, scores, fits, info, sq)


def cv_mean_mm(ctx: Context, m: Model) -> float | None:
    """Cross-validated mean error (mm) of a model's position observations, from its fold fits."""
    if not m.fold_fits:
        return None
    errs = []
    for f, p in zip(ctx.folds, m.fold_fits):
        prob = effect_problem(ctx, p, m.effects, ctx.data.subset(f), loss=False)
        e = prob.residual_vectors(p.values[None])[0].norm(dim=-1)
        errs.append(e[prob.obs.is_position])
    return 1e3 * float(torch.cat(errs).mean())


def evaluate_prior(ctx: Context, label: str, start: ParamSet, effects: list, prior_mm: float,
                   info: dict | None = None, tried: list | None = None) -> Model:
    """:func:`evaluate` with the prior scale chosen by the penalised CV error: from ``prior_mm``,
    climb :data:`PRIOR_SCALES_MM` up, else down, while it falls (the scale is a setting of the
    model, chosen by the same CV, not a structure the acceptance rule weighs). Every model tried is
    appended to ``tried``."""
    n_obs = ctx.n_obs
    best = evaluate(ctx, label, start, effects, prior_mm, info=info)
    seen = [best]
    i0 = PRIOR_SCALES_MM.index(prior_mm)
    for step in (1, -1):
        i = i0 + step
        while 0 <= i < len(PRIOR_SCALES_MM):
            m = evaluate(ctx, label, start, effects, PRIOR_SCALES_MM[i], info=info)
            seen.append(m)
            if penalised(m.scores, m.k, n_obs) >= penalised(best.scores, best.k, n_obs):
                break
            best, i = m, i + step
        if best.prior_mm != prior_mm:
            break
    if tried is not None:
        tried += seen
    return best

