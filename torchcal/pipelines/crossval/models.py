"""What every cross-validated fit of a data set shares (:class:`Context`: robot, training rows,
folds, the Huber threshold, the noise the priors are scaled by), the record of a fitted candidate
(:class:`Model`), and the measurement model of a candidate's parameters and effects on some rows.

Used by the loop (every candidate it compares) and by ``calibrate``'s prior on small data, which
chooses a prior scale as the loop does.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.measure.loss import Loss
from torchcal.measure.noise import robust_sigma
from torchcal.measure.setup import Setup
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.scores import rmse_mm
from torchcal.problems.effect_calibration import EffectCalibrationProblem

__all__ = ["Context", "Model", "folds_of", "orientation_count", "duplicate_groups", "effect_problem", "fit_noise",
           "observation_model", "observation_errors", "noise_sigma_of", "noise_sigma"]


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
    plausible: dict | None = None  # the largest plausible joint error per unit (None: precision.PLAUSIBLE)

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


def observation_model(ctx: Context, params: ParamSet, effects: list, data: Measurements) -> EffectCalibrationProblem:
    """The measurement model of ``params`` and ``effects`` on ``data`` (plain squared errors, no
    prior): residual vectors, their observations, Jacobians."""
    return effect_problem(ctx, params, effects, data, loss=False)


def observation_errors(ctx: Context, params: ParamSet, effects: list, data: Measurements) -> tuple[Tensor, Tensor]:
    """Per-observation error vectors ``(n_obs, 3)`` (model − measured, m; zero in components not
    measured) and their rows."""
    prob = effect_problem(ctx, params, effects, data, loss=False)
    return prob.residual_vectors(params.values[None])[0], prob.rows


def noise_sigma_of(ctx: Context, params: ParamSet, effects: list, k: float) -> float:
    """Robust per-axis noise estimate (m) from a fit's training residuals (``k`` parameters), over
    the measured components only."""
    prob = effect_problem(ctx, params, effects, ctx.data, loss=False)
    return fit_noise(prob, prob.x0, k)


def noise_sigma(ctx: Context, m: Model) -> float:
    """Robust per-axis noise estimate (m) from a fitted model's training residuals."""
    return noise_sigma_of(ctx, m.params, m.effects, m.k)

