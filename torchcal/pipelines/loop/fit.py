"""The loop's candidate models: fit on the training rows, cross-validate, and the linear step that
starts an effect where it means something.

A :class:`Model` is what the loop compares: which parameters are free, a prior on the geometric
errors (or none), the effects, the fit on all training rows and the cross-validated per-row
scores (:mod:`torchcal.pipelines.loop.selection`). Fits use the Huber loss with the round's threshold; the
folds start from the full fit with the same free set.

**An effect's start.** An effect is added around the current model: the residual is regressed,
to first order, on the model's free parameters and the effect's *linear* coordinates
(:meth:`~torchcal.effects.Effect.linear_basis`), selecting the modes of a family on the way
(:class:`~torchcal.pipelines.loop.selection.LinearCV`). The effect's parameters start from that solution
(:meth:`~torchcal.effects.Effect.from_linear`), so identifiability is then judged at a point
where a bilinear effect's columns do not vanish, and judged again at the solution.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.measure.loss import Loss
from torchcal.measure.setup import Setup
from torchcal.measure.registration import register_base, register_marker_rotations
from torchcal.params import ParamSet
from torchcal.pipelines.fitting import fit_identified, implausible_values
from torchcal.pipelines.loop.selection import effective_params, penalised, rmse_mm, robust_sigma, row_scores
from torchcal.problems.calibration import EffectCalibrationProblem
from torchcal.problems.uncertainty import standard_errors

__all__ = ["Context", "Model", "geometric_start", "observation_model", "observation_errors", "prior_weights",
           "evaluate", "evaluate_prior", "plausible_scale", "fit_params", "fit_noise", "cv_mean_mm", "folds_of",
           "duplicate_groups", "split_params", "assemble", "PRIOR_SCALES_MM"]

# Prior σ of every geometric error when the data cannot carry the full set: mm for lengths, mrad
# for angles (equal at a 1 m lever), strongest first.
PRIOR_SCALES_MM = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0)


@dataclass
class Context:
    """What every fit of a loop run shares: robot, training rows, folds, the Huber threshold
    ``c`` (m), the per-axis noise estimate ``sigma`` (m) the priors are scaled by, the
    set-up's unknowns (planes, fixed points; None for position data), the weight ``rot_weight``
    (m/rad) of measured orientations (None: orientations unused) and whether a family may be kept
    whole under a prior (``soft``)."""

    robot: object
    data: Measurements
    folds: list[Tensor]
    c: float | None
    sigma: float
    setup: Setup | None = None
    rot_weight: float | None = None
    soft: bool = True  # a family may be kept whole under a CV-chosen prior (False: modes chosen one by one)
    plausible: dict | None = None  # the largest plausible joint error per unit (None: fitting.PLAUSIBLE)

    @property
    def n_obs(self) -> float:
        """Observations in 3-D equivalents (measured scalars / 3): a plane contact counts a third
        of a position, a measured orientation one, so penalties weigh what was measured."""
        return (self.data.n_values + 3 * orientation_count(self.data, self.rot_weight)) / 3

    @property
    def n_geo(self) -> int:
        """Entries of the geometry block: the robot's parameters and the set-up's unknowns."""
        return self.robot.n_params + (0 if self.setup is None else self.setup.n_params)

    def at(self, c: float | None, sigma: float | None = None) -> "Context":
        """The same context with another Huber threshold (and noise estimate)."""
        return Context(self.robot, self.data, self.folds, c, self.sigma if sigma is None else sigma, self.setup,
                       self.rot_weight, self.soft, self.plausible)

    def loss(self) -> Loss:
        return Loss("l2") if self.c is None else Loss("huber", self.c)


@dataclass
class Model:
    """A fitted candidate: ``params`` (geometry then each effect's parameters; ``free`` = what
    was fitted), its effects, the geometric prior σ (mm and mrad; None = none), the effective
    number of parameters ``k``, cross-validated per-row ``scores`` (m², what decides), plain
    cross-validated squared errors per row ``sq`` (m², what a person reads as an RMSE) and the
    fold fits."""

    label: str
    params: ParamSet
    effects: list
    prior_mm: float | None
    k: float
    scores: Tensor
    fold_fits: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    sq: Tensor | None = None

    def cv_rmse_mm(self, n_obs: int) -> float:
        """Plain cross-validated RMSE per observation (mm)."""
        return rmse_mm(self.sq if self.sq is not None else self.scores, n_obs)


def folds_of(n: int, k: int, seed: int, groups: Tensor | None = None) -> list[Tensor]:
    """``k`` folds of row indices; rows sharing a group id (duplicates) stay together."""
    g = torch.Generator().manual_seed(seed)
    if groups is None:
        perm = torch.randperm(n, generator=g)
        return [perm[i::k].sort().values for i in range(k)]
    uniq = torch.unique(groups)
    perm = uniq[torch.randperm(len(uniq), generator=g)]
    return [torch.nonzero(torch.isin(groups, perm[i::k])).flatten() for i in range(k)]


def orientation_count(data: Measurements, rot_weight: float | None) -> int:
    """Measured marker orientations the fits use (finite quaternions; none without a weight)."""
    if rot_weight is None or data.quaternions is None:
        return 0
    return int(torch.isfinite(data.quaternions).all(-1).sum())


def duplicate_groups(data: Measurements) -> Tensor:
    """A group id per row: rows with identical commands share one (they must share a fold)."""
    _, inv = torch.unique(data.q, dim=0, return_inverse=True)
    return inv


def geometric_start(robot, data: Measurements, patterns, setup: Setup | None = None,
                    turns: bool = False) -> ParamSet:
    """The robot's parameters registered to the instrument, free: markers' positions (and, with
    ``turns``, the rotations of markers whose orientation was measured, started from the mean
    measured one), and the errors matching ``patterns`` (None: the robot's default free set);
    then the set-up's unknowns.

    Without three full positions there is nothing to register: with no position at all (planes,
    distances) the instrument frame is fixed at the robot base, since the planes and fixed points
    absorb where it stands; with partial positions only it starts there and is fitted."""
    p = robot.params()
    for m in robot.marker_names:
        if m not in data.marker_names:
            p.fix(f"{m}.*")
        p.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
    if patterns is not None:
        keep = set(p.free_names)
        p.free[:] = False
        for pat in patterns:
            try:
                p.unfix(pat)
            except KeyError:
                pass
        for m in data.marker_names:
            p.unfix(f"{m}.dx", f"{m}.dy", f"{m}.dz")
        p.free &= torch.tensor([n in keep for n in p.names], device=p.free.device)
    if int(data.seen.sum()) >= 3:
        p = register_base(robot, data, p)
    elif not bool(data.observed.any()):
        p.fix("base.*")
    if turns and orientation_count(data, 1.0):
        p = register_marker_rotations(robot, data, p)
    return p if setup is None else ParamSet.concat(p, setup.params())


def prior_weights(robot, params: ParamSet, prior_mm: float | None, sigma: float,
                  effects: list = ()) -> Tensor | None:
    """Prior weights ``σ_noise / σ_prior`` for every geometric error (not the instrument frame,
    not the marker points: unknowns of the set-up, not errors of the robot); ``σ_prior`` is
    ``prior_mm`` mm for lengths and ``prior_mm`` mrad for angles (equal at a 1 m lever); then the
    ``ridge`` of each of ``effects`` (the last entries of ``params``) that carries one. None when
    there is no prior at all."""
    soft = [e for e in effects if getattr(e, "ridge", None) is not None]
    if prior_mm is None and not soft:
        return None
    w = torch.zeros(len(params), dtype=params.values.dtype, device=params.values.device)
    K = robot.n_params
    if prior_mm is not None:
        setup = ("base.",) + tuple(f"{m}." for m in robot.marker_names)
        is_err = torch.tensor([not n.startswith(setup) for n in params.names[:K]], device=w.device)
        w[:K][is_err] = sigma / (prior_mm * 1e-3)
    o = len(params) - sum(e.n_params for e in effects)
    for e in effects:
        if getattr(e, "ridge", None) is not None:
            w[o:o + e.n_params] = e.ridge.to(w)
        o += e.n_params
    return w


def effect_problem(ctx: Context, params: ParamSet, effects: list, data: Measurements, prior: Tensor | None = None,
                   loss: bool = True) -> EffectCalibrationProblem:
    """The loop's problem for ``params`` and ``effects`` on ``data``: the context's robust loss
    (``loss=False``: plain least squares), set-up unknowns and an optional ``prior`` (row weights)."""
    return EffectCalibrationProblem(ctx.robot, params, effects, data, loss=ctx.loss() if loss else None, prior=prior,
                                    setup=ctx.setup, rot_weight=ctx.rot_weight)


def fit_noise(prob: EffectCalibrationProblem, x: Tensor, k: float | None = None) -> float:
    """The per-axis noise (m) a fit at ``x`` shows: robust (blind to outliers) over the measured
    components of its residuals, for ``k`` fitted parameters (default: its number of free values)."""
    r = prob.residual_vectors(prob.full(x[None]))[0]
    return robust_sigma(r[prob.obs.mask], x.numel() if k is None else int(round(k)))


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


def observation_model(ctx: Context, params: ParamSet, effects: list, data: Measurements) -> EffectCalibrationProblem:
    """The measurement model of ``params`` and ``effects`` on ``data`` (plain squared errors, no
    prior): residual vectors, their observations, Jacobians."""
    return effect_problem(ctx, params, effects, data, loss=False)


def observation_errors(ctx: Context, params: ParamSet, effects: list, data: Measurements) -> tuple[Tensor, Tensor]:
    """Per-observation error vectors ``(n_obs, 3)`` (model − measured, m; zero in components not
    measured) and their rows."""
    prob = effect_problem(ctx, params, effects, data, loss=False)
    return prob.residual_vectors(params.values[None])[0], prob.rows


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


def plausible_scale(ctx: Context, best: Model, tried: list[Model]) -> Model:
    """``best`` (the prior scale CV chose), or, when it moves a joint beyond ``ctx.plausible``, the
    scale among ``tried`` with the lowest penalised CV error that moves none (``best`` when none
    does): a model of this robot moves no joint implausibly far."""
    ok = [m for m in tried if not implausible_values(m.params, ctx.robot, ctx.plausible)]
    if ok and implausible_values(best.params, ctx.robot, ctx.plausible):
        return min(ok, key=lambda m: penalised(m.scores, m.k, ctx.n_obs))
    return best


def noise_sigma_of(ctx: Context, params: ParamSet, effects: list, k: float) -> float:
    """Robust per-axis noise estimate (m) from a fit's training residuals (``k`` parameters), over
    the measured components only."""
    prob = effect_problem(ctx, params, effects, ctx.data, loss=False)
    return fit_noise(prob, prob.x0, k)


def noise_sigma(ctx: Context, m: Model) -> float:
    """Robust per-axis noise estimate (m) from a fitted model's training residuals."""
    return noise_sigma_of(ctx, m.params, m.effects, m.k)


# ----------------------------------------------------------------------------- parameters by effect
def split_params(params: ParamSet, robot, effects: list) -> tuple[ParamSet, list[ParamSet]]:
    """``params`` cut into the geometry (with the set-up's unknowns) and one ParamSet per effect."""
    K = len(params) - sum(e.n_params for e in effects)
    idx = [list(range(K))]
    o = K
    for e in effects:
        idx.append(list(range(o, o + e.n_params)))
        o += e.n_params

    def take(ii):
        return ParamSet([params.names[i] for i in ii], [params.units[i] for i in ii], params.values[ii],
                        params.free[ii], params.lower[ii], params.upper[ii])
    parts = [take(ii) for ii in idx]
    return parts[0], parts[1:]


def assemble(geo: ParamSet, parts: list[ParamSet]) -> ParamSet:
    return ParamSet.concat(geo, *parts) if parts else geo.clone()


