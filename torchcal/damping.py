"""The step arithmetic of damped least squares, stated once.

Two iterations damp a Gauss-Newton step: the one Levenberg-Marquardt iteration
(:func:`~torchcal.optim.lm_batched.lm_batched`: a batch of problems, one damping each; a single
problem is a batch of one and the coupled fleet one problem with an arrow-shaped linear step) and
the inverse kinematics of :mod:`torchcal.kinematics.ik` (one damping per target). They share the
rules here: the initial damping :data:`TAU`, the gain ratio, Nielsen's damping update (Madsen,
Nielsen & Tingleff, *Methods for non-linear least squares problems*, 2004, Alg. 3.16), the floor of
Marquardt's scaling, MINPACK's scale-free gradient test and the ftol/xtol stopping tests.

The rules take Python floats or tensors (one entry per problem) and compute the same expression
either way. IK uses the initial damping only: it takes any step that lowers its error and moves the
damping by fixed factors (see :mod:`torchcal.kinematics.ik`).

Why here, at the top of the package beside :mod:`torchcal.params`: the helpers serve kinematics
(IK) and optim alike, and kinematics comes before optim in the data path (kinematics -> measure ->
problems -> optim), so a module under ``optim/`` could not serve IK. Nothing here imports from
torchcal.
"""
from __future__ import annotations

import math
from typing import TypeVar

import torch
from torch import Tensor

__all__ = ["TAU", "gain_ratio", "predicted_decrease", "nielsen_update", "damp_harder", "initial_damping",
           "scaling_floor", "gradient_cosine", "small_decrease", "small_step"]

Num = TypeVar("Num", float, Tensor)

#: The default initial damping, for every LM in torchcal. With Marquardt's scaling (the default)
#: ``mu0 = TAU`` is dimensionless: the scaling carries the problem's units. Small, because every
#: start torchcal fits from is close (registered to the instrument, or the last fit): a large mu0
#: spends its first steps as gradient descent, while a too-small one costs one rejected step (Nielsen's
#: rule doubles its way up). With identity scaling, ``mu0 = TAU * max diag(JᵀJ)``.
TAU = 1e-6
#: Nielsen's smallest damping factor after a good step: mu never falls by more than 3x at once.
_MIN_SHRINK = 1.0 / 3.0
#: Marquardt scaling is floored at this fraction of its largest entry, so that a direction the
#: data barely sees stays damped instead of running off.
_SCALING_FLOOR = 1e-6


def predicted_decrease(h_dot_g: Num, Jh_sq: Num) -> Num:
    """``S(0) - S_model(h) = -2 hᵀg - |J h|²``: the decrease of the sum of squares the linear model
    predicts for the step ``h`` (``g = Jᵀr``)."""
    return -2.0 * h_dot_g - Jh_sq


def gain_ratio(gain: Num, pred: Num, S_new: Num) -> Num:
    """``rho = (S(x) - S(x + h)) / predicted decrease``, or ``-1`` (a failed step) where the
    prediction is not a decrease or the new sum of squares is not finite."""
    if isinstance(pred, Tensor):
        return torch.where((pred > 0) & torch.isfinite(S_new), gain / pred, torch.full_like(pred, -1.0))
    return gain / pred if (pred > 0 and math.isfinite(S_new)) else -1.0


def damp_harder(mu: Num, nu: Num, where: Tensor | None = None) -> tuple[Num, Num]:
    """After a failed step (or a failed factorisation): ``mu *= nu``, ``nu *= 2`` (only ``where``
    that is true, for tensors)."""
    if where is None:
        return mu * nu, nu * 2.0
    return torch.where(where, mu * nu, mu), torch.where(where, nu * 2.0, nu)


def nielsen_update(mu: Num, nu: Num, rho: Num, grow: Tensor | None = None) -> tuple[Num, Num]:
    """Nielsen's rule: a step with ``rho > 0`` is taken, then ``mu *= max(1/3, 1 - (2 rho - 1)³)``
    and ``nu = 2``; otherwise :func:`damp_harder`. For tensors ``grow`` (default: every rejected
    entry) says which rejected entries damp harder; the others keep ``mu`` and ``nu``."""
    if not isinstance(rho, Tensor):
        if rho > 0:
            return mu * max(_MIN_SHRINK, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
        return damp_harder(mu, nu)
    acc = rho > 0
    mu_rej, nu_rej = damp_harder(mu, nu, ~acc if grow is None else grow)
    mu_acc = mu * torch.clamp(1.0 - (2.0 * rho - 1.0) ** 3, min=_MIN_SHRINK)
    return torch.where(acc, mu_acc, mu_rej), torch.where(acc, torch.full_like(nu, 2.0), nu_rej)


def initial_damping(tau: float, diag_max: Num) -> Num:
    """``mu0 = tau * max(diag(JᵀJ))`` (``tau`` alone where JᵀJ is zero): a damping relative to the
    problem's scale, for identity scaling."""
    if isinstance(diag_max, Tensor):
        return tau * torch.where(diag_max > 0, diag_max, torch.ones_like(diag_max))
    return tau * (diag_max if diag_max > 0 else 1.0)


def scaling_floor(dA: Tensor, dmax: Tensor) -> Tensor:
    """Marquardt's scaling ``diag(JᵀJ)`` ``dA (..., k)`` floored at 1e-6 of its largest entry
    ``dmax (..., 1)`` (all ones where JᵀJ is zero)."""
    return torch.where(dmax > 0, torch.maximum(dA, _SCALING_FLOOR * dmax), torch.ones_like(dA))


def gradient_cosine(ge: Tensor, dA: Tensor, S: Tensor) -> Tensor:
    """MINPACK's scale-free gradient test: the largest cosine between ``r`` and a column of ``J``,
    ``max_i |J_iᵀr| / (|J_i| |r|)``, from the (projected) gradient ``ge (..., k)``, the columns'
    squared norms ``dA (..., k)`` and ``S = |r|² (...)``; 0 where ``S`` is 0."""
    if ge.shape[-1] == 0:  # no parameter left to fit: no column, no gradient
        return torch.zeros_like(S)
    den = torch.sqrt(dA.clamp(min=1e-300) * S.clamp(min=1e-300)[..., None])
    return torch.where(S > 0, (ge.abs() / den).amax(-1), torch.zeros_like(S))


def small_decrease(gain: Num, pred: Num, S: Num, rho: Num, ftol: float) -> Num:
    """ftol's test: both the actual and the predicted relative decrease of ``S`` are below ``ftol``
    (and the model was not far off, ``rho <= 2``)."""
    return (abs(gain) <= ftol * S) & (pred <= ftol * S) & (rho <= 2.0)


def small_step(h_norm: Num, x_norm: Num, xtol: float) -> Num:
    """xtol's test: ``|h| <= xtol (|x| + xtol)``."""
    return h_norm <= xtol * (x_norm + xtol)
