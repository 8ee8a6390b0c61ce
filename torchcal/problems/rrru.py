"""Calibration of the 3-RRRU robot (seed 004): the seed's trajectories, a simulated laser
tracker, the calibration :class:`~torchcal.optim.Problem` with an implicit-function Jacobian, the
identifiability analysis of the 14 error parameters, and compensation errors.

Units: metres and radians (the seed's millimetres appear only in reports). The tracker measures
the platform position ``p`` (3-D; the platform only translates) in the robot base frame: as in
the seed, the tracker frame is taken as registered, so no base-frame parameters are fitted.

Which of the 14 parameters positions can identify (see :func:`identifiability`):

* ``R`` and ``r`` enter the loop closure only as ``r - R``, so ``dR`` and ``dr`` are one
  parameter: ``dr`` is dropped and ``dR`` identifies ``ΔR - Δr``. At most 13 of 14.
* The other 12 are per branch. Their loop-closure derivatives are, with ``ψ_i`` the direction of
  ``A_i2 → B_i`` in the radial plane and ``y_i`` the tangential offset, ``∂h_i/∂Δθ_i1 =
  -L_i1 sin(ψ_i - θ_i1)``, ``∂h_i/∂ΔL_i1 = -cos(ψ_i - θ_i1)``, ``∂h_i/∂ΔL_i2 = -1``,
  ``∂h_i/∂ΔL_i3 = -L_i3/sqrt(L_i3² - y_i²)`` and ``∂h_i/∂(r - R) = cos ψ_i``: different functions
  of the pose, so all 12 are identifiable from poses that vary ``ψ_i``, ``θ_i1`` and ``y_i`` for
  every branch. ``ΔL_i2`` and ``ΔL_i3`` separate only through ``y_i``: the constant ``-1`` against
  ``-1/sqrt(1 - (y_i/L_i3)²)``, which differs from ``-1`` by ``y_i²/(2 L_i3²)`` (0.4 % at
  ``y = 0.07 m``), so they are the weakest pair; branch 1's ``y_1 = p_y`` is constant along
  the seed's lines, which is why line data see it so poorly.
* The seed's own tables give equal ``ΔL_i1``, ``ΔL_i2``, ``ΔL_i3`` for the three branches because it
  *assumes* equal link errors (same machine tool); :func:`shared_lengths` maps that 7-parameter
  model onto the 14.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_params import N_PARAMS, PARAM_NAMES, PARAM_UNITS
from torchcal.problems.base import Problem
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.problems.identifiability_report import IdentifiabilityReport
from torchcal.problems.uncertainty import covariance

__all__ = ["RRRUCalibration", "DecorrelatedProblem", "identifiability",
           "prediction_std", "covariance", "shared_lengths", "param_index", "PREFER"]

#: Preference tiers for :func:`~torchcal.problems.identifiability.analyse_jacobian`: keep the drive
#: offsets and link lengths first, then ``dR`` (so ``dr`` is the one dropped).
PREFER: list[list[str]] = [["dtheta_*", "dL_*"], ["dR"], ["dr"]]


def param_index(names: Sequence[str]) -> list[int]:
    """Positions of ``names`` in :data:`~torchcal.kinematics.rrru.PARAM_NAMES`."""
    try:
        return [PARAM_NAMES.index(n) for n in names]
    except ValueError:
        bad = [n for n in names if n not in PARAM_NAMES]
        raise KeyError(f"unknown parameter(s) {bad}; names are {', '.join(PARAM_NAMES)}") from None


def shared_lengths(dtheta: Sequence[float], dL: Sequence[float], dR: float = 0.0,
                   dr: float = 0.0) -> Tensor:
    """The seed's 7-parameter model (equal link errors in every branch) as a ``(14,)`` vector:
    ``dtheta`` (3, rad), ``dL = (ΔL_1, ΔL_2, ΔL_3)`` (m) repeated for each branch, ``dR``, ``dr`` (m)."""
    dL = list(dL)
    return torch.tensor(list(dtheta) + dL * 3 + [dR, dr], dtype=torch.float64)


def identifiability(model: RRRU, theta: Tensor, params: Tensor | None = None, *,
                    free: Sequence[str] | None = None, p0: Tensor | None = None,
                    rtol: float = 1e-9) -> IdentifiabilityReport:
    """Which error parameters the platform positions at drive angles ``theta`` identify.

    The stacked Jacobian ``∂p/∂params`` (implicit function theorem, :meth:`RRRU.param_jacobian`)
    of all poses goes to :func:`torchcal.problems.identifiability.analyse_jacobian`: rank, identifiable
    subset (drive offsets and link lengths preferred, then ``dR``), a reason per dropped
    parameter, observability indices O1-O4 on unit-RMS columns.

    Args:
        theta: ``(N, 3)`` commanded drive angles (rad).
        params: linearisation point ``(14,)`` (default nominal).
        free: names to analyse (default all 14).
        p0: FK warm start ``(N, 3)`` (m), e.g. the targets.
    """
    names = list(PARAM_NAMES) if free is None else list(free)
    idx = param_index(names)
    J = model.param_jacobian(theta, params, p0=p0).reshape(-1, N_PARAMS)[:, idx]
    return analyse_jacobian(J, names, [PARAM_UNITS[i] for i in idx], rtol=rtol, prefer=PREFER)


class RRRUCalibration(Problem):
    """Fit error parameters to tracker positions: residuals ``fk(θ_k, params) - m_k``.

    Batched: a population ``X (P, k)`` runs one Newton solve for all ``P × N`` (parameter
    vector, pose) pairs. The Jacobian is analytic: ``∂p/∂params = -Hp⁻¹ Hq`` at each pose.

    Args:
        model: the robot.
        theta: ``(N, 3)`` commanded drive angles (rad).
        measured: ``(N, 3)`` tracker positions (m).
        free: names of the fitted parameters (default: the 13 identifiable ones, all but ``dr``);
            the others stay at ``fixed``.
        fixed: ``(14,)`` values of the parameters not fitted (default zero: nominal).
        bound: half-width of the search box per unit, ``{"rad": 0.02, "m": 0.003}`` by default
            (about 10x the seed's identified values; swarm solvers need finite bounds).
        p0: ``(N, 3)`` FK warm start (m), e.g. the targets; default the measurements.
        objective: ``"sse"`` (sum of squared residuals, m², what LM minimises) or
            ``"distance"`` (mean Euclidean distance, m: the seed's eq. 11) for :meth:`fitness`.
        x0: start point ``(k,)`` (default zero: nominal).
    """

    def __init__(self, model: RRRU, theta: Tensor, measured: Tensor, *,
                 free: Sequence[str] | None = None, fixed: Tensor | None = None,
                 bound: dict[str, float] | None = None, p0: Tensor | None = None,
                 objective: str = "sse", x0: Tensor | None = None):
        free = [n for n in PARAM_NAMES if n != "dr"] if free is None else list(free)
        self.free_idx = param_index(free)
        half = {"rad": 0.02, "m": 0.003} | dict(bound or {})
        hw = torch.tensor([half[PARAM_UNITS[i]] for i in self.free_idx], dtype=model.dtype, device=model.device)
        super().__init__(-hw, hw, x0=x0, names=free)
        if objective not in ("sse", "distance"):
            raise ValueError(f"objective must be 'sse' or 'distance', got {objective!r}")
        self.model = model
        self.theta = torch.as_tensor(theta, dtype=model.dtype, device=model.device).reshape(-1, 3)
        self.measured = torch.as_tensor(measured, dtype=model.dtype, device=model.device).reshape(-1, 3)
        if self.theta.shape != self.measured.shape:
            raise ValueError(f"theta {tuple(self.theta.shape)} and measured {tuple(self.measured.shape)} "
                             "must both be (N, 3)")
        self.p0 = self.measured if p0 is None else torch.as_tensor(p0, dtype=model.dtype).reshape(-1, 3)
        self.fixed = model.zero_params() if fixed is None else torch.as_tensor(fixed, dtype=model.dtype).clone()
        self.objective = objective

    def full(self, X: Tensor) -> Tensor:
        """``(..., k)`` fitted values -> ``(..., 14)`` parameter vectors."""
        out = self.fixed.expand(X.shape[:-1] + (N_PARAMS,)).clone()
        out[..., self.free_idx] = X
        return out

    def positions(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, N, 3)`` model positions (m); NaN where a parameter vector has no
        assembly at some pose (a failed evaluation for the optimisers)."""
        return self.model.fk(self.theta, self.full(X), p0=self.p0, on_failure="nan")

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, 3N)`` model minus measured (m), pose-major."""
        return (self.positions(X) - self.measured).reshape(X.shape[0], -1)

    def fitness(self, X: Tensor) -> Tensor:
        r = self.residuals(X)
        if self.objective == "sse":
            return (r * r).sum(-1)
        return torch.linalg.vector_norm(r.reshape(X.shape[0], -1, 3), dim=-1).mean(-1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (3N, k)`` analytic (implicit-function) Jacobian of the residuals."""
        J = self.model.param_jacobian(self.theta, self.full(x), p0=self.p0)   # (N, 3, 14)
        return J.reshape(-1, N_PARAMS)[:, self.free_idx]


class DecorrelatedProblem(Problem):
    """A least-squares problem in decorrelated, normalised coordinates, for swarm solvers.

    With the SVD ``J(x_c) = U S Vᵀ`` of the base problem's Jacobian at ``x_c``, the new variable is
    ``z = S Vᵀ (x - x_c)`` (``x = x_c + V S⁻¹ z``): a unit step in any ``z_k`` moves the stacked
    residual by one unit (m), and to first order the cost is ``|r0 + U z|²``, isotropic. The seed's
    GA uses a normalised real coding (each gene scaled to its range); this takes the normalisation
    one step further and removes the correlations as well, which a GA with 30 individuals cannot
    learn: in raw coordinates the 3-RRRU problem has a condition number of several hundred and the
    GA stalls far from the optimum (``scripts/seed004_rrru_ga.py`` reports both).

    Box: ``|z_k| ≤ width · |r0|`` with ``r0`` the residual at ``x_c``. For a linear model the
    optimum is ``z* = -Uᵀ r0``, so every ``|z*_k| ≤ |r0|``; the factor ``width`` (1.5) leaves room
    for the non-linearity. Only ``|r0|`` is used, no direction. The base problem's own bounds are
    not enforced in ``z``.

    Args:
        base: a problem with residuals and a Jacobian.
        x_c: linearisation point (default ``base.start()``).
        width: box half-width in units of ``|r0|``.
    """

    def __init__(self, base: Problem, x_c: Tensor | None = None, width: float = 1.5):
        self.base = base
        self.x_c = base.start() if x_c is None else torch.as_tensor(x_c, dtype=base.dtype)
        J = base.jacobian(self.x_c)
        r0 = base.residuals(self.x_c[None])[0]
        _, s, Vh = torch.linalg.svd(J, full_matrices=False)
        if float(s[-1]) <= 1e-12 * float(s[0]):
            raise ValueError("the base problem's Jacobian is rank deficient at x_c: reduce it to its "
                             "identifiable parameters first")
        self.M = Vh.mT / s                                   # (k, k): x = x_c + M z
        hw = float(width) * float(torch.linalg.vector_norm(r0)) * torch.ones_like(s)
        super().__init__(-hw, hw, names=[f"z{k + 1}" for k in range(s.numel())])

    def to_x(self, Z: Tensor) -> Tensor:
        """``(..., k)`` decorrelated -> base coordinates."""
        return self.x_c + Z @ self.M.mT

    def residuals(self, Z: Tensor) -> Tensor:
        return self.base.residuals(self.to_x(Z))

    def fitness(self, Z: Tensor) -> Tensor:
        return self.base.fitness(self.to_x(Z))

    def jacobian(self, z: Tensor) -> Tensor:
        return self.base.jacobian(self.to_x(z)) @ self.M


def prediction_std(J_cal: Tensor, J_eval: Tensor, sigma: float = 1.0) -> Tensor:
    """Standard deviation (m) of the calibrated model's position error at other poses, from
    tracker noise alone: parameters fitted to rows ``J_cal (m, k)`` with noise ``sigma`` (m, per
    row) have covariance ``σ² (JᵀJ)⁻¹``; at poses with Jacobian ``J_eval (N, 3, k)`` the position
    error has ``std = sqrt(trace(J_e C J_eᵀ))``. Returns ``(N,)``; with ``sigma = 1`` it is the
    factor by which a data set amplifies the tracker noise at each pose."""
    C = covariance(J_cal, torch.zeros(J_cal.shape[0], dtype=J_cal.dtype), sigma=sigma)
    P = torch.einsum("nik,kl,njl->nij", J_eval, C, J_eval)
    return P.diagonal(dim1=-2, dim2=-1).sum(-1).sqrt()
