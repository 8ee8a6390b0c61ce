"""``calibrate``'s Gaussian prior on small data, chosen as the loop chooses it.

With few measured values per parameter, the all-or-nothing choice (fit a parameter or fix it)
is a poor one: a parameter the data see weakly is either left at zero or fitted to whatever the
noise says. A Gaussian prior on every geometric error (σ in mm for lengths and mrad for angles,
:func:`~torchcal.pipelines.crossval.priors.prior_weights`) holds such parameters near zero by as much as
the data ask. Its scale is chosen by the penalised cross-validated error over
:data:`~torchcal.pipelines.crossval.priors.PRIOR_SCALES_MM`, against the same parameters without a
prior, with the loop's folds (rows with identical commands share a fold) and scores.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.measure.data import Measurements
from torchcal.params import ParamSet
from torchcal.pipelines.fitting import SMALL_DATA, is_small
from torchcal.pipelines.precision import implausible_values
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, plausible_scale
from torchcal.pipelines.crossval.models import Context, Model, duplicate_groups, effect_problem, fit_noise, folds_of
from torchcal.pipelines.crossval.evaluate import evaluate, evaluate_prior
from torchcal.pipelines.crossval.scores import penalised

__all__ = ["PriorChoice", "choose_prior"]

PRIOR_MARGIN = 0.01
EXACT_M = 1e-7  # a fit leaving less noise than this (m) is exact: simulated data without noise


@dataclass
class PriorChoice:
    """The prior ``calibrate`` chose: its scale (mm and mrad; None = no prior), the fit on all
    rows with it, its standard errors (m or rad), why, and every scale tried with its CV error."""

    prior_mm: float | None
    params: ParamSet
    std_errors: dict[str, float]
    reason: str
    tried: list[dict] = field(default_factory=list)


def choose_prior(robot, data: Measurements, start: ParamSet, fitted: ParamSet, c: float | None, *, seed: int = 0,
                 folds: int = 5, plausible: dict | None = None) -> PriorChoice:
    """The penalised-CV choice between ``start``'s free parameters without a prior and under each
    prior scale, among the models that move no joint beyond ``plausible`` when any does.
    ``fitted``: the plain fit, whose robust noise scales the priors; ``c``: the Huber threshold of
    the fits and scores (m; None: squared errors)."""
    fl = folds_of(len(data), min(folds, len(data)), seed, duplicate_groups(data))
    ctx = Context(robot, data, fl, c, 1.0, plausible=plausible)
    prob = effect_problem(ctx, fitted, [], data, loss=False)
    ctx = ctx.at(c, fit_noise(prob, prob.x0))
    if ctx.sigma < EXACT_M:
        return PriorChoice(None, fitted, {}, f"no prior: the plain fit leaves {1e3 * ctx.sigma:.2g} mm of noise, "
                                             "an exact fit that no prior can improve")
    n_obs = ctx.n_obs
    plain = evaluate(ctx, "no prior", start, [], None)
    tried: list[Model] = []
    best = evaluate_prior(ctx, "prior", start, [], PRIOR_SCALES_MM[len(PRIOR_SCALES_MM) // 2], tried=tried)
    table = [{"prior_mm": None, "k_eff": plain.k, "cv_rmse_mm": plain.cv_rmse_mm(n_obs),
              "penalised_mm2": 1e6 * penalised(plain.scores, plain.k, n_obs)}]
    table += [{"prior_mm": m.prior_mm, "k_eff": m.k, "cv_rmse_mm": m.cv_rmse_mm(n_obs),
               "penalised_mm2": 1e6 * penalised(m.scores, m.k, n_obs)} for m in sorted(tried, key=lambda m: m.prior_mm)]
    best = plausible_scale(ctx, best, tried)
    pen_plain, pen_prior = penalised(plain.scores, plain.k, n_obs), penalised(best.scores, best.k, n_obs)
    if implausible_values(plain.params, robot, plausible) and not implausible_values(best.params, robot, plausible):
        pen_plain = float("inf")  # a model of this robot moves no joint implausibly far
    # a prior that changes nothing measurable must not change the model: it must lower the
    # penalised CV error by PRIOR_MARGIN (noise-free data score every scale alike)
    chosen = best if pen_prior < (1 - PRIOR_MARGIN) * pen_plain else plain
    small = is_small(data, len(start.free_names))
    why = (f"{data.n_values} measured values for {len(start.free_names)} candidate parameters"
           + (f" (fewer than {SMALL_DATA} each)" if small else "") + ": the prior was chosen by "
           f"{len(fl)}-fold cross-validation; ")
    if chosen is best and pen_plain == float("inf"):
        why += (f"without a prior the fit moves a joint beyond its plausible size; {best.prior_mm:g} mm/mrad keeps "
                f"every joint plausible (k_eff {best.k:.1f}, CV {best.cv_rmse_mm(n_obs):.4f} mm)")
    elif chosen is best:
        why += (f"{best.prior_mm:g} mm/mrad (k_eff {best.k:.1f}, CV {best.cv_rmse_mm(n_obs):.4f} mm) beat no prior "
                f"(k {plain.k:.0f}, CV {plain.cv_rmse_mm(n_obs):.4f} mm)")
    else:
        why += (f"no prior (k {plain.k:.0f}, CV {plain.cv_rmse_mm(n_obs):.4f} mm) beat every scale (best "
                f"{best.prior_mm:g} mm/mrad, CV {best.cv_rmse_mm(n_obs):.4f} mm)")
    return PriorChoice(chosen.prior_mm, chosen.params, dict(chosen.info.get("se", {})), why, table)
