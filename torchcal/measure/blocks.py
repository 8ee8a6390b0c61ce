"""Measurement models: residual blocks that compare a robot model with what an instrument saw.

Every block maps full parameter vectors ``(P, K)`` to residuals ``(P, m)`` (batched over a
population) and gives the analytic Jacobian ``(m, K)`` at one vector. Residuals are in metres;
orientation residuals are converted to metres by a stated weight (m per rad).

Robust losses act per observation (one marker in one row): with ``s = |r|² / c²`` the block
returns ``r · sqrt(ρ(s) / s)``, so the sum of squares is ``c² Σ ρ(s)``, and the Jacobian is
scaled by ``sqrt(ρ'(s))`` (the usual first-order, IRLS-style approximation).
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.kinematics.transforms import quat_to_matrix, so3_left_jacobian_inv, so3_log
from torchcal.measure.data import Measurements

__all__ = ["Loss", "PositionResidual", "PoseResidual", "DistanceResidual", "ResidualBlock"]


class Loss:
    """Robust loss ``ρ(s)`` of a squared, scaled norm ``s``: ``"l2"``, ``"huber"`` or ``"cauchy"``.

    Args:
        scale: ``c`` in metres: observations with ``|r| <~ c`` count as inliers.
    """

    KINDS = ("l2", "huber", "cauchy")

    def __init__(self, kind: str = "l2", scale: float = 1e-3):
        if kind not in self.KINDS:
            raise ValueError(f"loss must be one of {self.KINDS}, got {kind!r}")
        if not scale > 0:
            raise ValueError(f"loss scale must be > 0 (metres), got {scale}")
        self.kind, self.scale = kind, float(scale)

    def rho(self, s: Tensor) -> tuple[Tensor, Tensor]:
        """``ρ(s)`` and ``ρ'(s)``."""
        if self.kind == "l2":
            return s, torch.ones_like(s)
        if self.kind == "huber":
            root = torch.sqrt(s.clamp(min=1.0))
            return torch.where(s <= 1, s, 2 * root - 1), torch.where(s <= 1, torch.ones_like(s), 1 / root)
        return torch.log1p(s), 1 / (1 + s)

    def scales(self, sq_norm: Tensor) -> tuple[Tensor, Tensor]:
        """Factors for residuals and Jacobian rows from squared norms (m²)."""
        if self.kind == "l2":
            one = torch.ones_like(sq_norm)
            return one, one
        s = sq_norm / self.scale ** 2
        rho, drho = self.rho(s)
        safe = torch.where(s > 1e-300, s, torch.ones_like(s))
        r_fac = torch.where(s > 1e-300, torch.sqrt(rho / safe), torch.ones_like(s))
        return r_fac, torch.sqrt(drho)

    def __repr__(self) -> str:
        return f"Loss({self.kind!r}, scale={self.scale:g} m)"


class ResidualBlock:
    """Base class. Subclasses set ``n_obs`` and implement ``_raw`` / ``_raw_jacobian``."""

    name = "block"
    obs_dim = 3

    def __init__(self, robot, data: Measurements, weights: Tensor | None = None, loss: Loss | None = None):
        self.robot, self.data = robot, data
        self.loss = loss or Loss("l2")
        self._weights = weights

    # -- subclass interface: (P, n_obs, d) residuals and (n_obs, d, K) Jacobian
    def _raw(self, params: Tensor) -> Tensor:
        raise NotImplementedError

    def _raw_jacobian(self, params: Tensor) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def observation_weights(self) -> Tensor | None:
        return None if self._weights is None else torch.as_tensor(self._weights, dtype=self.robot.dtype,
                                                                  device=self.robot.device)

    def errors(self, params: Tensor) -> Tensor:
        """``(P, n_obs)`` Euclidean error per observation (m), unweighted and without loss."""
        return self._raw(params).norm(dim=-1)

    def residuals(self, params: Tensor) -> Tensor:
        """``(P, K) -> (P, m)`` weighted, robustified residuals (m)."""
        r = self._raw(params)
        w = self.observation_weights()
        if w is not None:
            r = r * w.sqrt()[:, None]
        if self.loss.kind != "l2":
            fac, _ = self.loss.scales((r * r).sum(-1))
            r = r * fac[..., None]
        return r.reshape(r.shape[0], -1)

    def jacobian(self, params: Tensor) -> Tensor:
        """``(K,) -> (m, K)`` Jacobian of :meth:`residuals` (IRLS approximation under a loss)."""
        r, J = self._raw_jacobian(params)  # (n_obs, d), (n_obs, d, K)
        w = self.observation_weights()
        if w is not None:
            r, J = r * w.sqrt()[:, None], J * w.sqrt()[:, None, None]
        if self.loss.kind != "l2":
            _, jfac = self.loss.scales((r * r).sum(-1))
            J = J * jfac[:, None, None]
        return J.reshape(-1, J.shape[-1])


class PositionResidual(ResidualBlock):
    """Position of each seen marker: ``r = p_model − p_measured`` (m), 3 rows per observation; an
    axis that was not measured (NaN in the data) gives a zero residual and a zero Jacobian row.

    ``weights``: optional ``(n_obs,)`` per observation, in the order of ``obs_index``.
    """

    name = "position"

    def __init__(self, robot, data: Measurements, weights=None, loss: Loss | None = None):
        super().__init__(robot, data, weights, loss)
        mk = [robot.marker_names.index(m) for m in data.marker_names]
        self._mk = torch.tensor(mk, device=robot.device)
        seen = data.observed
        self.obs_index = torch.nonzero(seen)  # (n_obs, 2): row, measured-marker index
        self.n_obs = int(self.obs_index.shape[0])
        self._rows, self._cols = self.obs_index[:, 0], self._mk[self.obs_index[:, 1]]
        self._mask = data.axes_seen[seen]  # (n_obs, 3)
        self._meas = torch.nan_to_num(data.positions[seen])  # (n_obs, 3)
        if weights is not None and torch.as_tensor(weights).shape != (self.n_obs,):
            raise ValueError(f"position weights must have one entry per observation ({self.n_obs}), "
                             f"got shape {tuple(torch.as_tensor(weights).shape)}")

    @property
    def rows(self) -> Tensor:
        """``(n_obs,)`` pose row of each observation."""
        return self._rows

    @property
    def cols(self) -> Tensor:
        """``(n_obs,)`` robot marker of each observation."""
        return self._cols

    @property
    def measured(self) -> Tensor:
        """``(n_obs, 3)`` measured positions (m; 0 on axes not measured)."""
        return self._meas

    @property
    def axes_mask(self) -> Tensor:
        """``(n_obs, 3)`` 1 on measured axes, 0 elsewhere."""
        return self._mask

    @property
    def weighted(self) -> bool:
        """Whether rows carry weights."""
        return self._weights is not None

    def _raw(self, params: Tensor) -> Tensor:
        p = self.robot.positions(self.data.q, params, check=False)  # (P, N, M, 3)
        return (p[:, self._rows, self._cols] - self._meas) * self._mask

    def _raw_jacobian(self, params: Tensor) -> tuple[Tensor, Tensor]:
        J, p = self.robot.param_jacobian(self.data.q, params, kind="position", check=False,
                                         return_positions=True)  # (N, M, 3, K), (N, M, 3)
        return (p[self._rows, self._cols] - self._meas) * self._mask, J[self._rows, self._cols] * self._mask[..., None]


class PoseResidual(ResidualBlock):
    """Full pose of each seen marker: position error (m) and ``rot_weight · log(R R_meas^T)``
    (rotation vector, rad, times ``rot_weight`` in m/rad; default 0.1 m/rad: 1 mrad counts like
    0.1 mm). 6 rows per observation. Needs quaternion columns in the data."""

    name = "pose"
    obs_dim = 6

    def __init__(self, robot, data: Measurements, rot_weight: float = 0.1, weights=None, loss: Loss | None = None):
        if data.quaternions is None:
            raise ValueError("a pose residual needs orientation columns <marker>.qw/.qx/.qy/.qz in the data; "
                             "use a position residual otherwise")
        super().__init__(robot, data, weights, loss)
        mk = [robot.marker_names.index(m) for m in data.marker_names]
        seen = data.seen & ~torch.isnan(data.quaternions).any(-1)
        self.obs_index = torch.nonzero(seen)
        self.n_obs = int(self.obs_index.shape[0])
        mk_t = torch.tensor(mk, device=robot.device)
        self._rows, self._cols = self.obs_index[:, 0], mk_t[self.obs_index[:, 1]]
        self._meas_p = data.positions[seen]
        self._meas_R = quat_to_matrix(data.quaternions[seen])
        self.rot_weight = float(rot_weight)

    def _raw(self, params: Tensor) -> Tensor:
        R, t = self.robot.fk_rt(self.data.q, params, check=False)
        R, t = R[:, self._rows, self._cols], t[:, self._rows, self._cols]
        rot = so3_log(R @ self._meas_R.transpose(-1, -2))
        return torch.cat([t - self._meas_p, self.rot_weight * rot], -1)

    def errors(self, params: Tensor) -> Tensor:
        """Position error per observation (m); orientation errors are in :meth:`angle_errors`."""
        return self._raw(params)[..., :3].norm(dim=-1)

    def angle_errors(self, params: Tensor) -> Tensor:
        """``(P, n_obs)`` orientation error per observation (rad)."""
        return self._raw(params)[..., 3:].norm(dim=-1) / self.rot_weight

    def _raw_jacobian(self, params: Tensor) -> tuple[Tensor, Tensor]:
        J = self.robot.param_jacobian(self.data.q, params, kind="pose", check=False)[self._rows, self._cols]
        r = self._raw(params[None])[0]
        Jinv = so3_left_jacobian_inv(r[:, 3:] / self.rot_weight)
        J = torch.cat([J[:, :3], self.rot_weight * (Jinv @ J[:, 3:])], 1)
        return r, J


class DistanceResidual(ResidualBlock):
    """Distances between two measured points (ball bar, distance-only methods):
    ``r = |p_i − p_j|_model − d_measured`` (m), one row per pair.

    Args:
        pairs: ``(n, 2)`` row indices into ``data``; ``marker``: which marker; ``distances``: ``(n,)`` m.
    """

    name = "distance"
    obs_dim = 1

    def __init__(self, robot, data: Measurements, pairs, distances, marker: str | None = None,
                 weights=None, loss: Loss | None = None):
        super().__init__(robot, data, weights, loss)
        self.pairs = torch.as_tensor(pairs, device=robot.device).long()
        self.dist = torch.as_tensor(distances, dtype=robot.dtype, device=robot.device)
        if self.pairs.ndim != 2 or self.pairs.shape[1] != 2 or self.pairs.shape[0] != self.dist.shape[0]:
            raise ValueError("pairs must be (n, 2) row indices with one distance each")
        if int(self.pairs.max()) >= len(data) or int(self.pairs.min()) < 0:
            raise ValueError(f"pair indices must be rows 0..{len(data) - 1}")
        name = marker or robot.marker_names[0]
        if name not in robot.marker_names:
            raise ValueError(f"unknown marker {name!r}; the robot has {robot.marker_names}")
        self._m = robot.marker_names.index(name)
        self.n_obs = int(self.pairs.shape[0])

    def _raw(self, params: Tensor) -> Tensor:
        p = self.robot.positions(self.data.q, params, check=False)[:, :, self._m]  # (P, N, 3)
        d = (p[:, self.pairs[:, 0]] - p[:, self.pairs[:, 1]]).norm(dim=-1)
        return (d - self.dist)[..., None]

    def _raw_jacobian(self, params: Tensor) -> tuple[Tensor, Tensor]:
        J, p = self.robot.param_jacobian(self.data.q, params, kind="position", check=False, return_positions=True)
        J, p = J[:, self._m], p[:, self._m]  # (N, 3, K), (N, 3)
        diff = p[self.pairs[:, 0]] - p[self.pairs[:, 1]]
        n = diff.norm(dim=-1, keepdim=True)
        u = diff / n
        Jd = (u[:, :, None] * (J[self.pairs[:, 0]] - J[self.pairs[:, 1]])).sum(1, keepdim=True)  # (n, 1, K)
        return n - self.dist[:, None], Jd
