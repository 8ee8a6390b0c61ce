"""Gaussian priors on a candidate's geometric errors: their weights, the scales the CV chooses
among, and the plausibility check on the scale it chose."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import Context, Model
from torchcal.pipelines.crossval.scores import penalised
from torchcal.pipelines.precision import implausible_values

__all__ = ["PRIOR_SCALES_MM", "prior_weights", "plausible_scale"]

# Prior σ of every geometric error when the data cannot carry the full set: mm for lengths, mrad
# for angles (equal at a 1 m lever), strongest first.
PRIOR_SCALES_MM = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0)



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


def plausible_scale(ctx: Context, best: Model, tried: list[Model]) -> Model:
    """``best`` (the prior scale CV chose), or, when it moves a joint beyond ``ctx.plausible``, the
    scale among ``tried`` with the lowest penalised CV error that moves none (``best`` when none
    does): a model of this robot moves no joint implausibly far."""
    ok = [m for m in tried if not implausible_values(m.params, ctx.robot, ctx.plausible)]
    if ok and implausible_values(best.params, ctx.robot, ctx.plausible):
        return min(ok, key=lambda m: penalised(m.scores, m.k, ctx.n_obs))
    return best

