"""A candidate fitted on all training rows (identifiable subset, judged at the start and again at
the solution) and K-fold cross-validated from that fit; the prior scale chosen by the same CV.

Fits use the Huber loss with the context's threshold; the folds start from the full fit with the
same free set, all folds in one batched Levenberg-Marquardt (:func:`fit_folds`).
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.optim.lm_batched import lm_batched
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import (Context, Model, effect_problem, fit_noise, noise_sigma_of,
                                                observation_errors)
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, prior_weights
from torchcal.pipelines.crossval.scores import effective_params, penalised, row_scores
from torchcal.pipelines.fitting import fit_identified, setup_first, too_few_residuals
from torchcal.problems.effect_calibration import EffectCalibrationProblem
from torchcal.problems.uncertainty import standard_errors

__all__ = ["fit_params", "fit_folds", "rescore", "evaluate", "cv_mean_mm", "evaluate_prior"]

# a fold's fit, as a fit without identifiability judged again: at most this many trial steps
FOLD_MAX_ITER = 100


def fit_params(ctx: Context, params: ParamSet, effects: list, data: Measurements, prior, reduce: bool,
               max_iter: int | None = None) -> ParamSet:
    """``params``' free entries fitted on ``data`` under the context's loss (``reduce``: the
    identifiable subset, judged at the start and again at each solution; ``max_iter``: trial steps
    at most, 200 when reduced and 100 otherwise by default)."""
    make = lambda p: effect_problem(ctx, p, effects, data, prior)  # noqa: E731
    opts = {"max_iter": max_iter or (200 if reduce else 100)}
    # under a prior nothing is dropped for imprecision: the prior holds what the data barely see;
    # otherwise the noise the candidate itself reaches says how well a parameter is seen
    noise = fit_noise if prior is None else None
    optional = tuple(f"{e.name}." for e in effects)
    ps, _, _ = fit_identified(make, params, reduce=reduce, markers=ctx.robot.marker_names, options=opts, noise=noise,
                              zero_dropped=optional, plausible=ctx.plausible, prefer=setup_first(effects))
    return ps


def fit_folds(ctx: Context, full: ParamSet, prob: EffectCalibrationProblem, jac0: Tensor | None = None
              ) -> list[ParamSet]:
    """Each fold's fit of ``full``'s free set on the other folds' rows, from ``full`` (``prob``: its
    problem on every training row, with the prior; ``jac0``: its Jacobian there, if known), as
    :func:`fit_params` without reduction would give them one by one, but as one batched
    Levenberg-Marquardt: the folds are one problem on every training row, each fold's own rows
    masked out (a zero residual and Jacobian row changes nothing), so the kinematics of every fold
    run in one call per step, and the Jacobian at the shared start is computed once."""
    n_rows, dev = len(ctx.data), ctx.data.q.device
    keep = torch.ones(len(ctx.folds), n_rows, dtype=torch.bool, device=dev)
    for i, f in enumerate(ctx.folds):
        keep[i, f] = False
    obs = keep[:, prob.rows].repeat_interleave(3, dim=1)  # (F, 3 n_obs): residual entries each fold fits
    extra = prob.m - obs.shape[1]  # prior and gauge rows: every fold has them
    mask = torch.cat([obs, obs.new_ones(obs.shape[0], extra)], 1).to(full.values.dtype)
    k = prob.dim
    short = [int(m) for m in mask.sum(1).tolist() if m < k]
    if short:  # as a fold fitted alone would refuse
        raise ValueError(too_few_residuals(short[0], k, reduced=False))

    def residuals(X: Tensor, idx: Tensor) -> Tensor:
        return prob.residuals(X) * mask[idx]

    def jacobian(X: Tensor, idx: Tensor) -> Tensor:
        return prob.jacobians(X) * mask[idx, :, None]

    x0 = prob.x0.expand(mask.shape[0], k)
    jac0 = (prob.jacobian(prob.x0) if jac0 is None else jac0)[None] * mask[:, :, None]
    res = lm_batched(residuals, jacobian, x0, torch.ones_like(x0, dtype=torch.bool), prob.lower, prob.upper,
                     max_iter=FOLD_MAX_ITER, jac0=jac0)
    out = []
    for x in res.x:
        p = full.clone()
        p.values = prob.full(x).detach()
        out.append(p)
    return out


def rescore(ctx: Context, m: Model) -> Tensor:
    """A model's cross-validated per-row scores under the context's (new) threshold, from its
    fold fits."""
    out = torch.zeros(len(ctx.data), dtype=ctx.robot.dtype, device=ctx.robot.device)
    for f, p in zip(ctx.folds, m.fold_fits):
        e, rows = observation_errors(ctx, p, m.effects, ctx.data.subset(f))
        out[f] = row_scores(e.norm(dim=-1), rows, len(f), ctx.c)
    return out


def evaluate(ctx: Context, label: str, start: ParamSet, effects: list, prior_mm: float | None,
             reduce: bool = True, info: dict | None = None, folds: bool = True) -> Model:
    """Fit ``start`` on all training rows (identifiable subset, judged at the start and again
    at the solution), then K-fold cross-validate it from that fit (``folds=False``: the fit alone,
    with no scores, for a caller that reads only its values and effective size)."""
    prior = prior_weights(ctx.robot, start, prior_mm, ctx.sigma, effects)
    full = fit_params(ctx, start, effects, ctx.data, prior, reduce)
    prior = prior_weights(ctx.robot, full, prior_mm, ctx.sigma, effects)
    prob = effect_problem(ctx, full, effects, ctx.data, prior)
    J_all = prob.jacobian(prob.x0)  # the data rows (loss-weighted), then the prior's and the gauge's
    J = J_all[: 3 * prob.n_obs]
    pf = None if prior is None else prior[full.free_index]
    k = effective_params(J, pf)
    info = dict(info or {})
    # how far noise alone moves each value: σ sqrt((JᵀJ + W²)⁻¹_ii) at the fit's robust noise
    se = standard_errors(J, sigma=noise_sigma_of(ctx, full, effects, k), prior=pf, singular="pinv")
    info["se"] = dict(zip(full.free_names, se.tolist()))
    # the free set before identifiability: later fits judge it again, with the noise they see then
    info.setdefault("candidates", start.free[: ctx.n_geo].clone())
    scores = torch.zeros(len(ctx.data), dtype=ctx.robot.dtype, device=ctx.robot.device)
    sq = torch.zeros_like(scores)
    if not folds:
        return Model(label, full, list(effects), prior_mm, k, scores, [], info, sq)
    fits = fit_folds(ctx, full, prob, J_all) if ctx.folds else []
    for f, p in zip(ctx.folds, fits):
        e, rows = observation_errors(ctx, p, effects, ctx.data.subset(f))
        scores[f] = row_scores(e.norm(dim=-1), rows, len(f), ctx.c)
        sq[f] = row_scores(e.norm(dim=-1), rows, len(f), None)
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

