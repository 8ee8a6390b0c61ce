"""What a fleet solve returns, independent robots or coupled ones: one record the per-robot
results are built from (:class:`~torchcal.pipelines.fleet.views.FleetResults`)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch import Tensor

from torchcal.optim.result import Result

__all__ = ["FleetSolution"]


@dataclass
class FleetSolution:
    """A fleet's fitted parameters and what they were fitted from, batched over its ``R`` robots.

    Attributes:
        X: ``(R, K)`` each robot's geometric parameters (m, rad; the robot model's order).
        free: ``(R, K + E)`` bool, what each robot fitted: its geometry, then its ``E`` effect
            parameters (``E = 0`` without fleet-wide effects).
        se: ``(R, K + E)`` standard errors of the fitted entries (their units); entries not fitted
            hold no standard error a caller may read.
        r: ``(R, N·M·3)`` final training residuals, model minus measured (m), 0 where nothing was seen.
        reasons: per robot, why each candidate it did not fit was dropped (name -> sentence).
        solver: per robot, its solver's :class:`~torchcal.optim.Result`.
        stage: the name of the fitted model (``"geometric"``, ``"geometric + joint_compliance"``).
        n_extra: ``(R,)`` effect parameters each robot fitted beyond its geometry (None: none).
        effects: the fleet-wide effects' parameters per robot and shared ones (None: none).
        prior: the hierarchical prior (fleet mean, scales, noise) when one was fitted.
        test_errors: ``FleetData -> (R, N', M, 3)`` held-out error vectors (m) of the fitted model,
            where it holds more than the geometry (None: the geometry ``X`` alone predicts).
    """

    X: Tensor
    free: Tensor
    se: Tensor
    r: Tensor
    reasons: Sequence[dict[str, str]]
    solver: Sequence[Result]
    stage: str = "geometric"
    n_extra: Tensor | None = None
    effects: dict | None = None
    prior: dict | None = None
    test_errors: Callable | None = None
