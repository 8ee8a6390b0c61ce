"""PSD measurements (seed 003): the recorded joints, spots and locations, and the expected error of
each spot (encoder noise through the arm and the laser's lever, plus PSD noise), in m and rad."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from torchcal.measure.laser import Laser, spot_jacobian, laser_beams

__all__ = ["PSDData", "spot_covariance", "spot_sensitivity", "spot_whitening"]


# ------------------------------------------------------------------------------- data
@dataclass
class PSDData:
    """PSD measurements: recorded joints, spots and the location of each sample.

    Attributes:
        q: ``(N, dof)`` recorded joint values (rad).
        uv: ``(N, 2)`` measured spots on the PSD surface (m, PSD coordinates).
        loc: ``(N,)`` long, the PSD location (``0 .. n_locations-1``) of each sample.
        n_locations: ``m``.
    """

    q: Tensor
    uv: Tensor
    loc: Tensor
    n_locations: int

    def __post_init__(self):
        N = self.q.shape[0]
        if self.uv.shape != (N, 2) or self.loc.shape != (N,):
            raise ValueError(f"PSDData: q {tuple(self.q.shape)}, uv {tuple(self.uv.shape)} and loc "
                             f"{tuple(self.loc.shape)} must describe the same N samples: (N, dof), (N, 2), (N,)")
        self.loc = self.loc.long()
        if N and (int(self.loc.min()) < 0 or int(self.loc.max()) >= self.n_locations):
            raise ValueError(f"loc must lie in 0..{self.n_locations - 1}")

    def subset(self, locations: Sequence[int], k: int) -> "PSDData":
        """The first ``k`` samples of each of ``locations``, renumbered ``0 .. len-1``."""
        rows, new = [], []
        for j, L in enumerate(locations):
            idx = torch.nonzero(self.loc == L).flatten()[:k]
            if idx.numel() < k:
                raise ValueError(f"location {L} has {idx.numel()} samples, fewer than k = {k}")
            rows.append(idx)
            new.append(torch.full((k,), j, dtype=torch.long))
        i = torch.cat(rows)
        return PSDData(self.q[i], self.uv[i], torch.cat(new), len(locations))


# ------------------------------------------------------------------------------- expected spot errors
def spot_sensitivity(robot, laser: Laser, q: Tensor, loc: Tensor, psd_R: Tensor, psd_c: Tensor,
                     params: Tensor) -> Tensor:
    """``(N, 2, dof)``: derivative of each spot ``(u, v)`` (m) w.r.t. the joint values (rad), with
    the robot model at ``params (K,)`` and PSD poses ``psd_R (m, 3, 3)``, ``psd_c (m, 3)`` (m)."""
    R, _ = robot.fk_rt(q, params, check=False)
    i = laser.index(robot)
    p, w = laser_beams(robot, laser, q, params)
    Jq = robot.joint_jacobian(q, params, check=False)[:, i]  # (N, 6, dof)
    ro = R[:, i] @ laser.origin.to(R)
    v, om = Jq[:, :3], Jq[:, 3:]
    dp = v + torch.linalg.cross(om, ro[..., None].expand_as(om), dim=1)
    dw = torch.linalg.cross(om, w[..., None].expand_as(om), dim=1)
    zero = torch.zeros_like(p)
    Gp, Gw, _, _ = spot_jacobian(p, w, zero, psd_c[loc], psd_R[loc])
    return Gp @ dp + Gw @ dw


def spot_covariance(robot, laser: Laser, q: Tensor, loc: Tensor, psd_R: Tensor, psd_c: Tensor, params: Tensor,
                    *, q_noise: float, uv_noise: float) -> Tensor:
    """``(N, 2, 2)`` expected covariance (m²) of each spot residual: encoder noise ``q_noise``
    (rad, std per joint, independent) carried through :func:`spot_sensitivity`, plus PSD noise
    ``uv_noise`` (m, std per axis)."""
    G = spot_sensitivity(robot, laser, q, loc, psd_R, psd_c, params)
    eye = torch.eye(2, dtype=G.dtype, device=G.device)
    return q_noise ** 2 * (G @ G.transpose(-1, -2)) + uv_noise ** 2 * eye


def spot_whitening(cov: Tensor) -> Tensor:
    """``(N, 2, 2)`` matrices ``W`` with ``W Σ Wᵀ = I`` (``W = L⁻¹`` for ``Σ = L Lᵀ``): a whitened
    residual ``W r`` has unit covariance, so least squares on it is generalised least squares."""
    L = torch.linalg.cholesky(cov)
    eye = torch.eye(2, dtype=cov.dtype, device=cov.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)
