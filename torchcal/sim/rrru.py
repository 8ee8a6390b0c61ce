"""The 3-RRRU with a laser tracker, simulated (seed 004): the controller commands its model's IK,
the true robot (true error parameters) moves, the tracker measures with Gaussian noise (m, σ per
axis). Identifying code receives the commanded angles and the readings only."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU
from torchcal.sim.base import Simulated, expected_noise_norm

__all__ = ["compensation", "simulate_tracker", "TrackerSimulator"]


def simulate_tracker(model: RRRU, targets: Tensor, true_params: Tensor, noise: float = 0.0, *,
                     controller_params: Tensor | None = None,
                     generator: torch.Generator | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Drive the robot to ``targets`` with the controller's model and measure with a tracker.

    The controller commands ``θ = ik(targets, controller_params)`` (nominal by default); the
    real robot (``true_params``) goes to ``fk(θ, true_params)``; the tracker adds independent
    Gaussian noise of ``noise`` (m, σ per axis).

    Args:
        targets: ``(..., 3)`` desired positions (m).

    Returns:
        ``(theta, actual, measured)``: commanded angles ``(..., 3)`` (rad), true positions and
        tracker readings ``(..., 3)`` (m).
    """
    theta = model.ik(targets, controller_params)
    with torch.no_grad():
        actual = model.fk(theta, true_params, p0=targets)
    meas = actual
    if noise > 0:
        meas = actual + noise * torch.randn(actual.shape, generator=generator, dtype=actual.dtype,
                                             device=actual.device)
    return theta, actual, meas


def compensation(model: RRRU, true_params: Tensor, identified: Tensor | None, targets: Tensor,
                 noise: float = 0.0, *, generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """Track ``targets`` with a (calibrated) controller model and measure the error, as the seed's
    Figs. 9-12 do after compensation: the controller inverts its model (``identified``; ``None`` =
    nominal, i.e. before calibration), the true robot moves, the tracker measures.

    Returns:
        dict of ``(..., 3)`` tensors (m): ``measured`` (tracker), ``actual`` (truth),
        ``error`` = measured - target, ``true_error`` = actual - target; and ``(...)``
        ``distance`` = ``|error|`` (the seed's eq. 11) and ``true_distance``.
    """
    _, actual, meas = simulate_tracker(model, targets, true_params, noise, controller_params=identified,
                                       generator=generator)
    err, terr = meas - targets, actual - targets
    return dict(measured=meas, actual=actual, error=err, true_error=terr,
                distance=torch.linalg.vector_norm(err, dim=-1),
                true_distance=torch.linalg.vector_norm(terr, dim=-1))


class TrackerSimulator:
    """Seed 004's measurements behind :class:`~torchcal.sim.base.Simulator`: the robot with true errors
    ``true_params (14,)`` driven along ``targets (n, 3)`` (m) by its nominal controller, measured by
    a tracker with ``noise`` (m, σ per axis)."""

    def __init__(self, model: RRRU, targets: Tensor, true_params: Tensor, noise: float = 0.0):
        self.model, self.targets, self.true_params, self.noise = model, targets, true_params, float(noise)

    def simulate(self, n: int, *, seed: int = 0) -> Simulated:
        """The first ``n`` targets; ``data`` holds the commanded angles ``theta (n, 3)`` rad and the
        tracker readings ``meas (n, 3)`` m, ``truth`` the errors and the true positions."""
        if not 0 < n <= self.targets.shape[0]:
            raise ValueError(f"n must lie in 1..{self.targets.shape[0]} (the targets given), got {n}")
        T = self.targets[:n]
        theta, actual, meas = simulate_tracker(self.model, T, self.true_params, self.noise,
                                               generator=torch.Generator().manual_seed(int(seed)))
        return Simulated({"theta": theta, "meas": meas, "targets": T}, {"params": self.true_params, "actual": actual},
                         noise_floor=expected_noise_norm(self.noise))
