"""The SCARA's joint torques simulated along a trajectory (seed 001): the true lumped parameters
drive the regressor; encoders and the torque measurement add Gaussian noise. Identification
receives the noisy regressor and torques only (``W``, ``tau_meas``)."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.dynamics import scara
from torchcal.dynamics.excitation import FourierExcitation
from torchcal.sim.base import Simulated

__all__ = ["simulate", "ScaraTorqueSimulator"]


# -- 2. data ----------------------------------------------------------------------------------
def simulate(ex: FourierExcitation, x: Tensor, xi: Tensor, friction: bool, cfg, g: torch.Generator, n: int = 1000,
             periods: float = 2.0) -> dict:
    """True states, noisy states, noise-free and noisy torques along trajectory ``x`` (Fourier
    coefficients of ``ex``), ``n`` samples over ``periods``. ``cfg`` gives the noise σ:
    ``noise_q`` rad, ``noise_qd`` rad/s, ``noise_qdd`` rad/s², ``noise_tau`` N m. Returns ``t``, the
    true ``q, qd, qdd``, ``W_true``, ``tau``, and what identification may read: ``W`` (from the
    noisy states) and ``tau_meas``."""
    t = ex.times(n, periods)
    q, qd, qdd = ex.evaluate(x, t)
    W_true = scara.regressor(q, qd, qdd, friction)
    tau = W_true @ xi
    noise = lambda s, like: s * torch.randn(like.shape, generator=g, dtype=like.dtype)  # noqa: E731
    qm, qdm, qddm = q + noise(cfg.noise_q, q), qd + noise(cfg.noise_qd, qd), qdd + noise(cfg.noise_qdd, qdd)
    return dict(t=t, q=q, qd=qd, qdd=qdd, W_true=W_true, tau=tau,
                W=scara.regressor(qm, qdm, qddm, friction), tau_meas=tau + noise(cfg.noise_tau, tau))


class ScaraTorqueSimulator:
    """Seed 001's data behind :class:`~torchcal.sim.base.Simulator`: the SCARA with lumped parameters
    ``xi`` following trajectory ``x`` of ``ex``, with the noise of ``cfg`` (see :func:`simulate`)."""

    def __init__(self, ex: FourierExcitation, x: Tensor, xi: Tensor, friction: bool, cfg, periods: float = 2.0):
        self.ex, self.x, self.xi, self.friction, self.cfg, self.periods = ex, x, xi, friction, cfg, periods

    def simulate(self, n: int, *, seed: int = 0) -> Simulated:
        """``n`` samples; ``data`` holds the noisy regressor ``W`` and torques ``tau_meas`` (N m)."""
        d = simulate(self.ex, self.x, self.xi, self.friction, self.cfg, torch.Generator().manual_seed(int(seed)), n,
                     self.periods)
        return Simulated({"W": d["W"], "tau_meas": d["tau_meas"], "t": d["t"]}, {"xi": self.xi, **d})
