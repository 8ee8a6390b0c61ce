"""The calibration problem: robot + parameter set + residual blocks, as an optimiser
:class:`~torchcal.optim.Problem` over the free parameters."""
from __future__ import annotations

import torch
from torch import Tensor

from .optim import Problem
from .params import ParamSet

__all__ = ["CalibrationProblem"]


class CalibrationProblem(Problem):
    """Minimise the residuals of ``blocks`` over the free entries of ``params``.

    Args:
        params: start values, free flags and bounds (lower/upper are used as given; swarm
            solvers need them finite).
        blocks: residual blocks (:mod:`torchcal.measurement`).
        fitness: ``"sse"`` (sum of squared residuals, m²) or ``"sum_norm"`` (sum of Euclidean
            errors per observation, m — seed 000's objective).
    """

    def __init__(self, robot, params: ParamSet, blocks: list, fitness: str = "sse"):
        if fitness not in ("sse", "sum_norm"):
            raise ValueError(f"fitness must be 'sse' or 'sum_norm', got {fitness!r}")
        if not blocks:
            raise ValueError("a calibration problem needs at least one residual block")
        idx = params.free_index
        if idx.numel() == 0:
            raise ValueError("no free parameter: unfix some with ParamSet.unfix('pattern')")
        self.robot, self.params, self.blocks, self.fitness_kind = robot, params, blocks, fitness
        super().__init__(params.lower[idx], params.upper[idx], params.values[idx], params.free_names)
        self.m = sum(b.n_obs * b.obs_dim for b in blocks)
        if self.m < idx.numel():
            raise ValueError(f"{self.m} residuals for {idx.numel()} free parameters: measure more poses "
                             "or fix parameters")

    def full(self, X: Tensor) -> Tensor:
        """Free values ``(P, k)`` or ``(k,)`` -> full parameter vectors."""
        return self.params.expand(X)

    def residuals(self, X: Tensor) -> Tensor:
        full = self.full(X)
        return torch.cat([b.residuals(full) for b in self.blocks], -1)

    def fitness(self, X: Tensor) -> Tensor:
        if self.fitness_kind == "sse":
            r = self.residuals(X)
            return (r * r).sum(-1)
        full = self.full(X)
        return sum(b.errors(full).sum(-1) for b in self.blocks)

    def jacobian(self, x: Tensor) -> Tensor:
        full = self.full(x)
        J = torch.cat([b.jacobian(full) for b in self.blocks], 0)
        return J[:, self.params.free_index]
