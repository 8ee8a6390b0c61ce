"""An effect's start in the loop: its modes as linear (or bilinear) columns beside the geometric
Jacobian, solved in closed form, so that the nonlinear fit starts near the answer."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects import effect_params
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import Context, Model, effect_problem, fit_noise
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, prior_weights
from torchcal.pipelines.loop.parts import assemble, split_params
from torchcal.pipelines.loop.bilinear import bilinear_step
from torchcal.pipelines.loop.linear_cv import LinearCV
from torchcal.pipelines.loop.records import EffectStart
from torchcal.pipelines.loop.screen import fitted_payload, screen_family
from torchcal.pipelines.crossval.scores import T_ACCEPT, compare, penalised
from torchcal.problems.effect_calibration import EffectCalibrationProblem

__all__ = ["effect_start"]


# ----------------------------------------------------------------------------- an effect's start
def _basis_columns(ctx: Context, prob: EffectCalibrationProblem, eff) -> tuple[Tensor, list[list[int]], int]:
    """``(3 n_obs, L)`` the effect's linear coordinates' columns in the observations' residuals,
    with the joint deflections carried through the current model (``prob``)."""
    robot, params = ctx.robot, prob.params
    geo = params.values[: robot.n_params]
    basis = eff.linear_basis(eff.prepare(ctx.data.q, ctx.data.covariates))
    L = sum(len(g) for g in basis.groups)
    N, M = len(ctx.data), len(robot.marker_names)
    D = torch.zeros(N, M, 3, L, dtype=robot.dtype, device=robot.device)  # every marker's displacement
    Rb, _ = robot.base_transform(geo)
    if basis.dq is not None:
        q = prob.joint_values(params.values[None])[0]
        Jq = robot.joint_jacobian(q, geo, check=False)[:, :, :3, :]  # instrument frame, (N, M, 3, dof)
        D = D + Jq @ basis.dq[:, None]
    if basis.dp is not None:
        D = D + Rb @ basis.dp
    p = prob.marker_positions(params.values[None])[0]
    out = prob.obs.project(p, D, params.values[prob.K:prob.K + prob.S])
    return out.reshape(-1, L), basis.groups, basis.shared


def _bilinear_starts(lin: Tensor) -> list[Tensor]:
    """Starts for the shared parameters ``s`` of a bilinear effect from its linear solution,
    rows ``[a_k, b_k]`` with ``b_k ≈ c_k s`` and ``a_k ≈ c_k``: the a²-weighted ratio, the
    leading singular direction of ``B`` scaled to ``a``, and zero."""
    a, B = lin[:, 0], lin[:, 1:]
    out = [torch.zeros(B.shape[1], dtype=lin.dtype, device=lin.device)]
    den = float((a * a).sum())
    if den > 0:
        out.append((a[:, None] * B).sum(0) / den)
    if B.abs().sum() > 0:
        U, S, Vh = torch.linalg.svd(B, full_matrices=False)
        u, v = U[:, 0], Vh[0] * S[0]
        lam = float(a @ u) / float(u @ u)
        if abs(lam) > 1e-300:
            out.append(v / lam)
    return out


# A mode's prior σ when a family is kept softly, as multiples of the noise: the RMS displacement
# each mode may cause at the markers (chosen by the penalised CV error)
SOFT_SCALES = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)


def _soft_option(lcv: LinearCV, forced: list[int], ctx: Context, baseline, hard: dict, shared: int) -> dict | None:
    """Every mode of a linear family at once under a Gaussian prior whose scale the penalised CV
    error chooses (:data:`SOFT_SCALES`), when it beats the hard selection ``hard`` and passes the
    rule against ``baseline``; None otherwise (the ridge is then left off). On noisy data many
    small modes held by a prior can explain what no single mode shows clearly."""
    if shared or not ctx.soft or not lcv.allow_whole:  # a bilinear or screened family: chosen mode by mode
        return None
    n3 = 3 * ctx.n_obs
    opt = lcv.soft(forced, ctx.n_obs, [1.0 / (m * (n3 ** 0.5)) for m in SOFT_SCALES])
    if opt is None:
        return None
    t, pen_ok, _ = compare(baseline[0], opt["scores"], baseline[1], opt["k"], ctx.n_obs)
    pen_hard = hard["pen"] if hard["new"] else penalised(*baseline, ctx.n_obs)
    if not (t > T_ACCEPT and pen_ok and opt["pen"] < pen_hard):
        lcv.set_prior(lcv.prior)
        return None
    m = 1.0 / (opt["ridge"] * n3 ** 0.5)
    return dict(opt, sigma_mm=1e3 * m * ctx.sigma, t=t, pen_hard=pen_hard, pen_soft=opt["pen"])


def _fitted_shared(eff, superseded: list, parts: list) -> Tensor | None:
    """``(1 + shared,)`` the point a bilinear family's new modes are linearised at: 1 for the mode's
    own coordinate, then each shared coordinate (the payload's and each load's mass moments, in the
    order of its linear basis) as an effect it supersedes fitted it (``parts``: their parameters),
    NaN where none did (a load offered this round); None when none of them is known."""
    info = eff.param_info()
    labels = [info[i][0] for i in eff.shared() if not info[i][0].startswith("gravity.")]
    known = {}
    for s_, p in zip(superseded, parts):
        known.update({lab: float(v) for (lab, _), v in zip(s_.param_info(), p.values.tolist())})
    if not any(lab in known for lab in labels):
        return None
    return torch.tensor([1.0] + [known.get(lab, float("nan")) for lab in labels], dtype=torch.float64)


def _at_fitted(cols: Tensor, at: Tensor) -> Tensor:
    """A new mode's columns ``(3 n_obs, 1 + shared)`` linearised at ``at`` (:func:`_fitted_shared`):
    its deflection at the fitted shared coordinates (one column: at zero compliance no shared
    coordinate moves it), then the columns of those not fitted yet (their products with the
    compliance, as the bilinear basis has them)."""
    fitted = ~torch.isnan(at)
    one = cols[:, fitted] @ at[fitted].to(cols)
    return torch.cat([one[:, None], cols[:, ~fitted]], 1)


def _group_columns(ctx: Context, prob, eff, forced: list[int], superseded: list, parts: list
                   ) -> tuple[list[Tensor], list[Tensor] | None, int]:
    """Each mode's columns for the selection, the bilinear columns of every mode where they differ
    (None where not) and the number of shared coordinates. A mode joining a family whose payload an
    effect it supersedes fitted (``parts``: their parameters) is judged by what it adds at that
    payload (:func:`_at_fitted`): its products with the payload's moments are nine unknowns where
    the mode is one."""
    cols_all, groups, shared = _basis_columns(ctx, prob, eff)
    gcols = [cols_all[:, g] for g in groups]
    at = _fitted_shared(eff, superseded, parts) if shared and eff.selectable else None
    if at is None:
        return gcols, None, shared
    return [c if g in forced else _at_fitted(c, at) for g, c in enumerate(gcols)], gcols, shared


def _linear_step(lcv: LinearCV, chosen: list[int], eff, shared: int) -> Tensor:
    """The base parameters' step ``(kb,)`` with the ``chosen`` modes in; the effect's start values
    set (a bilinear family's through :func:`~torchcal.pipelines.loop.bilinear.bilinear_step`)."""
    coef, kb = lcv.coefficients(chosen), lcv.kb
    if not shared:
        eff.theta = eff.from_linear(coef[kb:]).to(eff.robot.dtype)
        return coef[:kb]
    step, own, sv = bilinear_step(lcv, chosen, _bilinear_starts(coef[kb:].reshape(len(chosen), 1 + shared)))
    eff.theta = eff.from_bilinear(own, sv).to(eff.robot.dtype)
    return step


def _new_shared(eff, superseded: list) -> bool:
    """Whether ``eff`` holds shared parameters that none of the effects it supersedes had (a load of
    its own): the modes it takes over are then a new model even where the selection adds no mode,
    and the cross-validated rule, not the selection, judges it (the selection's baseline already
    holds the new parameters in its linear columns)."""
    info = eff.param_info()
    had = {n for s_ in superseded for n, _ in s_.param_info()}
    return any(info[i][0] not in had for i in eff.shared())


def _step_words(h: dict, labels: list[str]) -> dict:
    """One selection step for the report: what was tried (each mode's t) and added, or which mode
    left or was exchanged for which, and the threshold."""
    if "removed" in h:
        return {"threshold": h["threshold"], "removed": [labels[g] for g in h["removed"]], "t": h["t"]}
    if "exchanged" in h:
        return {"threshold": h["threshold"], "exchanged": [labels[g] for g in h["exchanged"]], "t": h["t"]}
    name = lambda g: "all modes at once" if g == -1 else labels[g]  # noqa: E731
    return {"threshold": h["threshold"], "added": None if h["added"] is None else [labels[g] for g in h["added"]],
            "t": {name(g): t for g, t in h["tried"].items()}}


def _screened(ctx: Context, current: Model, prob, eff, lin: tuple, superseded: list):
    """A screened family (:mod:`~torchcal.pipelines.loop.screen`) expanded into the pairs that
    explain something around the model without the ``superseded`` effects (``prob`` and ``lin``: its
    problem, residuals, Jacobian, IRLS weights and free values), its torques with the payload an
    accepted effect fitted; None when no pair passes. A family accepted before is screened around
    ``current``, which holds it (without it, what it took would swamp the noise the next pairs are
    judged against), and keeps its accepted terms."""
    accepted = [t for s_ in superseded if s_.name == eff.name for t in s_.terms]
    if accepted:
        prob, lin = _around_current(ctx, current)
    r, Jb, w, x = lin
    load = fitted_payload(current.effects, current.params)
    if load is not None:  # the gravity torques as the accepted model knows them: with its payload and loads
        payload, link, loads = load
        eff = eff.with_payload(payload, link, ctx.data, loads)
    # the noise the current model leaves (the context's may date from a model far coarser)
    out = screen_family(eff, ctx.data, lambda e: _basis_columns(ctx, prob, e)[0], r, Jb, w, fit_noise(prob, x), ctx.c,
                        rows=prob.rows)
    if out is not None and accepted:
        out.terms = list(dict.fromkeys(list(accepted) + out.terms))
    return out


def _around_current(ctx: Context, current: Model):
    """The current model's problem and its linearisation (residuals, Jacobian, IRLS weights, free
    values): what a family already accepted is screened around, so that its next pairs are judged
    against the noise the current model leaves, its own accepted terms in."""
    prior = prior_weights(ctx.robot, current.params, current.prior_mm, ctx.sigma, current.effects)
    prob = effect_problem(ctx, current.params, current.effects, ctx.data, prior)
    x = prob.x0
    return prob, (prob.residual_vectors(current.params.values[None])[0], prob.data_jacobian(x),
                  prob.observation_weights(x), x)


def _screened_rule(lcv: LinearCV, eff) -> None:
    """The selection of a screened family: at the Bonferroni threshold of the whole space it
    searched, and never all of its pairs at once, nor all of them under a prior (they span
    unrelated parameters: no finding). Other effects keep the rule as it is."""
    if getattr(eff, "screened", False):
        lcv.n_searched = eff.n_searched
        lcv.allow_whole = False


def _relinearised(eff, geometry: Tensor):
    """A family whose columns are the geometry's Jacobian, taken again where the linear step has
    moved the geometry (a model that absorbed a 12 mm tool change turns the flange by mrad, which
    those columns feel), its start values kept."""
    theta, out = eff.theta, eff.at_geometry(geometry)
    out.theta = theta
    return out


def effect_start(ctx: Context, current: Model, eff, superseded: list, tabu=frozenset()) -> EffectStart:
    """Where a candidate effect starts (:class:`~torchcal.pipelines.loop.records.EffectStart`):
    modes chosen (for a family) and start values from the linear step around ``current`` without
    the ``superseded`` effects. Modes in ``tabu`` (labels) are not offered."""
    robot = ctx.robot
    geo, parts = split_params(current.params, robot, current.effects)
    keep = [(e, p) for e, p in zip(current.effects, parts) if e not in superseded]
    base_effects = [e for e, _ in keep]
    base = assemble(geo, [p for _, p in keep])
    prior = prior_weights(robot, base, current.prior_mm, ctx.sigma, base_effects)
    prob = effect_problem(ctx, base, base_effects, ctx.data, prior)
    x = prob.x0
    r = prob.residual_vectors(base.values[None])[0]
    Jb = prob.data_jacobian(x)
    w = prob.observation_weights(x)
    pb = None if prior is None else prior[base.free_index]
    if getattr(eff, "screened", False) and (eff := _screened(ctx, current, prob, eff, (r, Jb, w, x), superseded)) is None:
        return EffectStart(effect=None, prior_mm=current.prior_mm, reason="no (parameter, driver) pair passed the screening")
    labels = [lab for lab, _ in eff.modes()]
    forced = [labels.index(lab) for s_ in superseded for lab, _ in s_.modes() if lab in labels] \
        if eff.selectable else []
    gcols, full, shared = _group_columns(ctx, prob, eff, forced, superseded,
                                         [p for e, p in zip(current.effects, parts) if e in superseded])
    lcv = LinearCV(r, w, Jb, x, pb, gcols, prob.rows, len(ctx.data), ctx.folds, ctx.c)
    _screened_rule(lcv, eff)
    out = EffectStart(effect=None, prior_mm=current.prior_mm)
    if eff.selectable:
        for g, lab in enumerate(labels):  # modes a later finding explained away do not come back
            if lab in tabu and g not in forced:
                lcv.usable[g] = False

        # what to beat: the model as it is, at the prior its own CV chose (so a prior that moves
        # with the effect lends it nothing the current model could have had alone)
        baseline = (lcv.scores(forced), lcv.k_eff(forced))

        def select(s_mm):
            w_ = prior_weights(robot, base, s_mm, ctx.sigma, base_effects)
            lcv.set_prior(None if w_ is None else w_[base.free_index])
            chosen, hist, sc, k = lcv.forward(forced, ctx.n_obs, baseline)
            return {"chosen": chosen, "hist": hist, "pen": penalised(sc, k, ctx.n_obs), "prior_mm": s_mm,
                    "new": [g for g in chosen if g not in forced]}

        best = select(current.prior_mm)
        if current.prior_mm is not None:
            # the effect may want another prior on the geometry: climb the grid while the effect
            # is still selected and the penalised score falls
            i0 = PRIOR_SCALES_MM.index(current.prior_mm)
            for step in (1, -1):
                i = i0 + step
                while 0 <= i < len(PRIOR_SCALES_MM):
                    cand = select(PRIOR_SCALES_MM[i])
                    if not cand["new"] or (best["new"] and cand["pen"] >= best["pen"]):
                        break
                    best, i = cand, i + step
                if best["prior_mm"] != current.prior_mm:
                    break
        w_ = prior_weights(robot, base, best["prior_mm"], ctx.sigma, base_effects)
        lcv.set_prior(None if w_ is None else w_[base.free_index])
        chosen, hist = best["chosen"], best["hist"]
        out.prior_mm = best["prior_mm"]
        out.selection = [_step_words(h, labels) for h in hist]
        soft = _soft_option(lcv, forced, ctx, baseline, best, shared)
        if soft is not None:
            chosen = soft["chosen"]
            out.soft = {k: soft[k] for k in ("sigma_mm", "t", "k", "pen_hard", "pen_soft")}
        elif not best["new"] and not (forced and _new_shared(eff, superseded)):
            out.reason = "no mode passed the selection"
            return out
        if soft is None:
            out.aliases = {labels[g]: [labels[h] for h in hs] for g, hs in lcv.aliases(chosen).items()
                           if g in best["new"]}
        ok, why = eff.proposes([labels[g] for g in chosen])
        if not ok:
            out.reason = why
            return out
        chosen = sorted(chosen)  # the restricted effect keeps the catalogue's order
        eff = eff.with_modes([labels[g] for g in chosen])
        if soft is not None:  # the prior the selection chose, on the effect's own parameters
            eff.ridge = soft["ridge"] * lcv.scale[[c for g in chosen for c in lcv.slices[g]]]
            eff.ridge_mm = soft["sigma_mm"]
    else:
        chosen = list(range(len(groups)))
    if full is not None:  # the start solves the bilinear model of the chosen modes, as for any family
        prior_now = lcv.prior
        lcv = LinearCV(r, w, Jb, x, pb, full, prob.rows, len(ctx.data), ctx.folds, ctx.c)
        lcv.set_prior(prior_now)
    step = _linear_step(lcv, chosen, eff, shared)
    start = base.clone()
    start.values[base.free_index] = base.values[base.free_index] + step
    if getattr(eff, "screened", False):
        eff = _relinearised(eff, start.values[: robot.n_params])
    # the geometry is judged again with the effect in: what the rigid model's misfit hid may show now
    start.free[: ctx.n_geo] = current.info["candidates"]
    params = ParamSet.concat(start, effect_params([eff]))
    out.effect, out.params, out.effects = eff, params, base_effects + [eff]
    out.info = {"candidates": current.info["candidates"]}
    return out
