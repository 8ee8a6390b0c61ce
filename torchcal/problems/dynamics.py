"""Identification of linear-in-parameter dynamics ``τ = W ξ``: least squares, recursive least
squares, and the torque-fit problem for the swarm solvers of :mod:`torchcal.optim`.

Shapes: ``N`` samples, ``J`` joints, ``k`` parameters; a regressor is ``(N, J, k)`` and torques
``(N, J)`` (N·m). Because the model is linear in ξ, ordinary least squares *is* the minimiser of
the torque residual sum of squares: every other method here can at best match it on the data
it was fitted to.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.problems.base import Problem
from torchcal.dynamics import scara

__all__ = ["ols", "rls", "torque_rmse", "physical_box", "TorqueFitProblem"]


def _flat(W: Tensor, tau: Tensor) -> tuple[Tensor, Tensor]:
    if W.ndim == 3:
        return W.reshape(-1, W.shape[-1]), tau.reshape(-1)
    return W, tau


def ols(W: Tensor, tau: Tensor) -> Tensor:
    """``(k,)`` ordinary least-squares estimate ``argmin ||W ξ − τ||²`` (QR-based LAPACK
    solve). ``W`` ``(N, J, k)`` or stacked ``(m, k)``; ``tau`` ``(N, J)`` or ``(m,)``."""
    A, y = _flat(W, tau)
    return torch.linalg.lstsq(A, y[:, None]).solution[:, 0]


def rls(W: Tensor, tau: Tensor, forgetting: float = 1.0, delta: float = 1e6,
        xi0: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Recursive least squares over the samples in order, one ``J``-row block per sample::

        K = P Wₙᵀ (λ I + Wₙ P Wₙᵀ)⁻¹,   ξ ← ξ + K (τₙ − Wₙ ξ),   P ← (P − K Wₙ P) / λ

    with ``P₀ = δ I`` and ``ξ₀`` (default 0). With ``λ = 1`` the final estimate is the ridge
    solution ``argmin ||Wξ − τ||² + ||ξ − ξ₀||²/δ``, which tends to :func:`ols` as ``δ → ∞``;
    ``λ < 1`` discounts old samples (tracking), which costs accuracy on a time-invariant model.

    Args:
        W: ``(N, J, k)`` regressor; tau: ``(N, J)`` torques.
        forgetting: ``λ ∈ (0, 1]``.  delta: initial covariance scale ``δ``.
        xi0: ``(k,)`` initial estimate.
    Returns:
        ``(ξ, history)``: the final ``(k,)`` estimate and the ``(N, k)`` estimate after each sample.
    """
    N, J, k = W.shape
    xi = torch.zeros(k, dtype=W.dtype) if xi0 is None else xi0.clone().to(W.dtype)
    P = delta * torch.eye(k, dtype=W.dtype)
    eye = torch.eye(J, dtype=W.dtype)
    hist = torch.empty(N, k, dtype=W.dtype)
    # Sequential by definition; each step is a tiny k×k update.
    for n in range(N):
        Wn = W[n]
        PWt = P @ Wn.T
        K = torch.linalg.solve(forgetting * eye + Wn @ PWt, PWt.T).T
        xi = xi + K @ (tau[n] - Wn @ xi)
        P = (P - K @ Wn @ P) / forgetting
        P = 0.5 * (P + P.T)  # keep P symmetric against rounding drift
        hist[n] = xi
    return xi, hist


def torque_rmse(W: Tensor, tau: Tensor, xi: Tensor, per_joint: bool = False) -> Tensor:
    """Root-mean-square torque error ``W ξ − τ`` (N·m): a scalar over all samples and joints,
    or ``(J,)`` per joint. ``W`` ``(N, J, k)``, ``tau`` ``(N, J)``, ``xi`` ``(k,)``."""
    e = W @ xi - tau
    return (e * e).mean(0).sqrt() if per_joint else (e * e).mean().sqrt()


def physical_box(a1: float = 0.325, a2: float = 0.275, m1_max: float = 15.0, m2_max: float = 10.0,
                 friction_max: tuple[float, float] | None = None) -> tuple[Tensor, Tensor]:
    """Bounds on the seed's lumped parameters ξ from coarse physical limits only.

    Assumptions: link masses ``0 ≤ m_i ≤ m_i,max`` (kg; defaults 15 and 10, about the whole arm
    mass of a 600 mm SCARA), COMs on the links (``0 ≤ x_i ≤ a_i``), inertias about the COM at most
    that of a rod of the link's length about its end (``I_i ≤ m_i,max a_i²/3``). Interval
    arithmetic on :func:`torchcal.dynamics.scara.base_params` then gives ``A ∈ [0, A_max]``,
    ``B ∈ [0, m2,max a1 a2]``, ``C ∈ [0, I2,max + m2,max a2²]``, mapped onto ξ = (A, C, B, C, C, B).
    For the Cobra s600 defaults the box is about ξ1 ≤ 4.2, ξ2,4,5 ≤ 1.0, ξ3,6 ≤ 0.89 kg·m²,
    and the illustrative true values sit at 14–25 % of each range (not at the centre).

    ``friction_max = (fv_max, fc_max)`` appends ``[0, fv_max]``, ``[0, fc_max]`` per joint.
    Returns ``(lower, upper)``, each ``(6,)`` or ``(10,)``.
    """
    I1, I2 = m1_max * a1 ** 2 / 3, m2_max * a2 ** 2 / 3
    A = I1 + I2 + m1_max * a1 ** 2 + m2_max * (a1 ** 2 + a2 ** 2)
    B = m2_max * a1 * a2
    C = I2 + m2_max * a2 ** 2
    hi = scara.BASE_TO_SEED @ torch.tensor([A, B, C], dtype=torch.float64)
    if friction_max is not None:
        fv, fc = friction_max
        hi = torch.cat([hi, torch.tensor([fv, fc, fv, fc], dtype=torch.float64)])
    return torch.zeros_like(hi), hi


class TorqueFitProblem(Problem):
    """Fit ξ to measured torques: residuals ``W ξ − τ`` and fitness = torque **RMSE** (N·m)
    over all samples and joints (the square root of the mean of the squared residuals: the same
    minimiser as the sum of squares, and directly comparable with :func:`torque_rmse`).

    Args:
        W: ``(N, J, k)`` regressor along the measured trajectory.
        tau: ``(N, J)`` measured torques (N·m).
        lower, upper: ``(k,)`` bounds on ξ (e.g. :func:`physical_box`); the swarm solvers
            need them finite.
        x0: optional start point.
    """

    def __init__(self, W: Tensor, tau: Tensor, lower: Tensor, upper: Tensor,
                 x0: Tensor | None = None, names: list[str] | None = None):
        super().__init__(lower, upper, x0, names)
        self.A, self.y = _flat(W, tau)

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, N J)`` torque residuals, N·m."""
        return X @ self.A.T - self.y

    def fitness(self, X: Tensor) -> Tensor:
        r = self.residuals(X)
        return (r * r).mean(-1).sqrt()
