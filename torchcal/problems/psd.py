"""PSD calibration problems (seed 003): the point constraint and the direct spot residual, each a
:class:`~torchcal.problems.base.Problem` over the robot's free errors followed by the block's own
unknowns, batched over populations ``(P, k) -> (P, rows)`` (m) with an analytic Jacobian."""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchcal.kinematics.transforms import so3_exp
from torchcal.measure.laser import (Laser, pair_midpoint, pair_midpoint_jacobian, spot_jacobian,
                                    beam_pair_point, laser_beam_jacobian, laser_beams, plane_intersection)
from torchcal.measure.psd import PSDData, spot_whitening
from torchcal.params import ParamSet
from torchcal.problems.base import Problem
from torchcal.problems.identifiability import analyse_jacobian

__all__ = ["PSDBlock", "PointConstraint", "SpotResidual", "analyse_block"]


# Distance rows compare with point residuals (m); this weight makes one known distance count
# like a well-measured coordinate without dominating the fit.
DISTANCE_WEIGHT = 1.0


# ------------------------------------------------------------------------------- residual blocks
class PSDBlock(Problem):
    """A PSD residual block as a least-squares :class:`~torchcal.problems.base.Problem`. Shared plumbing: robot parameters ``free`` (a ParamSet whose fixed entries keep their
    values) followed by the block's own unknowns; single-vector views for the solver."""

    def __init__(self, robot, laser: Laser, free: ParamSet):
        if free.names != robot.param_names:
            raise ValueError("free must be a ParamSet of this robot (robot.params())")
        self.robot, self.laser, self.free = robot, laser, free
        self.idx = free.free_index
        self.robot_names = free.free_names
        self.robot_units = [free.units[i] for i in self.idx.tolist()]

    def robot_params(self, X: Tensor) -> Tensor:
        """``(P, k)`` or ``(k,)`` block vectors -> full robot vectors ``(P, K)`` / ``(K,)``."""
        return self.free.expand(X[..., : self.idx.numel()])

    def _set_bounds(self) -> None:
        # The unknowns are known only once the subclass has laid them out: unbounded, started
        # at :meth:`start`.
        x0 = self.start()
        inf = torch.full_like(x0, math.inf)
        Problem.__init__(self, -inf, inf, x0=x0, names=self.names)


class PointConstraint(PSDBlock):
    """The seed's multi-point virtual constraint: all beams at one location meet in one point.

    Rows: for each pair of beams at a location (screened once, at ``params0``, to an angle of at
    least ``min_angle_deg``: near-parallel pairs put their point anywhere along the beams), the
    pair point (:func:`beam_pair_point`) minus the mean of the location's pair points, 3 rows (m);
    then, per known distance ``(a, b, D)``, ``weight · (‖mean_a − mean_b‖ − D)``.

    Args:
        robot, laser: the model; q: ``(N, dof)`` joint values (recorded or modified, rad);
        loc: ``(N,)`` location per row; free: which robot parameters are unknown.
        distances: known distances between location centres ``(a, b, D in m)``;
            distance_weight: their row weight (1: a metre of distance error counts like a metre
            of point residual).
        min_angle_deg: pairs closer to parallel are left out; params0: ``(K,)`` where the pair
            angles are judged (default ``free.values``).
    Attributes:
        names, units: of the unknowns (the free robot parameters).
        pairs: ``(n_pairs, 2)`` beam indices; n_rows: residual rows.
    """

    def __init__(self, robot, laser: Laser, q: Tensor, loc: Tensor, free: ParamSet, *,
                 distances: Sequence[tuple[int, int, float]] = (), distance_weight: float = DISTANCE_WEIGHT,
                 min_angle_deg: float = 5.0, params0: Tensor | None = None):
        super().__init__(robot, laser, free)
        self.q, self.loc = q, loc.long()
        self.m = int(self.loc.max()) + 1
        p0 = free.values if params0 is None else params0
        _, w = laser_beams(robot, laser, q, p0)
        ia, ib = [], []
        cmin = math.cos(math.radians(min_angle_deg))
        for j in range(self.m):
            rows = torch.nonzero(self.loc == j).flatten()
            a, b = torch.triu_indices(rows.numel(), rows.numel(), 1, device=rows.device)
            a, b = rows[a], rows[b]
            keep = (w[a] * w[b]).sum(-1).abs() < cmin
            ia.append(a[keep]), ib.append(b[keep])
        self.ia, self.ib = torch.cat(ia), torch.cat(ib)
        self.pairs = torch.stack([self.ia, self.ib], 1)
        self.ploc = self.loc[self.ia]
        self.count = torch.bincount(self.ploc, minlength=self.m).to(q.dtype)
        if bool((self.count < 1).any()):
            raise ValueError(f"location(s) {torch.nonzero(self.count < 1).flatten().tolist()} have no pair of beams "
                             f"at {min_angle_deg}° or more apart; aim from more varied directions")
        self.distances = [(int(a), int(b), float(D)) for a, b, D in distances]
        for a, b, _ in self.distances:
            if not (0 <= a < self.m and 0 <= b < self.m and a != b):
                raise ValueError(f"a known distance needs two different locations in 0..{self.m - 1}, got ({a}, {b})")
        self.dw = float(distance_weight)
        self.names, self.units = list(self.robot_names), list(self.robot_units)
        self.n_rows = 3 * self.ia.numel() + len(self.distances)
        self._set_bounds()

    def start(self) -> Tensor:
        return self.free.values[self.idx].clone()

    def _means(self, M: Tensor) -> Tensor:
        """``(P, n_pairs, 3)`` -> per-location means ``(P, m, 3)``."""
        S = M.new_zeros(M.shape[0], self.m, 3).index_add_(1, self.ploc, M)
        return S / self.count[:, None]

    def points(self, X: Tensor) -> tuple[Tensor, Tensor]:
        """Pair points ``(P, n_pairs, 3)`` and location means ``(P, m, 3)`` (m)."""
        p, w = laser_beams(self.robot, self.laser, self.q, self.robot_params(X))
        M = pair_midpoint(p[:, self.ia], w[:, self.ia], p[:, self.ib], w[:, self.ib])
        return M, self._means(M)

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, n_rows)`` (m)."""
        M, C = self.points(X)
        r = [(M - C[:, self.ploc]).reshape(X.shape[0], -1)]
        for a, b, D in self.distances:
            r.append(self.dw * ((C[:, a] - C[:, b]).norm(dim=-1, keepdim=True) - D))
        return torch.cat(r, 1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (n_rows, k)``, analytic: beam derivatives from the robot's parameter
        Jacobian, chained with the closed-form pair-point derivatives."""
        th = self.robot_params(x)
        p, w, Jp, Jw = laser_beam_jacobian(self.robot, self.laser, self.q, th)
        Jp, Jw = Jp[..., self.idx], Jw[..., self.idx]
        ia, ib = self.ia, self.ib
        Ga, Gwa, Gb, Gwb = pair_midpoint_jacobian(p[ia], w[ia], p[ib], w[ib])  # (n_pairs, 3, 3) each
        dM = Ga @ Jp[ia] + Gwa @ Jw[ia] + Gb @ Jp[ib] + Gwb @ Jw[ib]  # (n_pairs, 3, k)
        k = dM.shape[-1]
        dC = dM.new_zeros(self.m, 3, k).index_add_(0, self.ploc, dM) / self.count[:, None, None]
        rows = [(dM - dC[self.ploc]).reshape(-1, k)]
        if self.distances:
            M = pair_midpoint(p[ia], w[ia], p[ib], w[ib])
            C = self._means(M[None])[0]
            for a, b, _ in self.distances:
                e = C[a] - C[b]
                rows.append(self.dw * (e / e.norm()) @ (dC[a] - dC[b]))
                rows[-1] = rows[-1][None]
        return torch.cat(rows, 0)


class SpotResidual(PSDBlock):
    """Measured spots used directly: predicted minus measured ``(u, v)`` (m), with the PSD pose
    of every location among the unknowns.

    Unknowns: the free robot parameters, then per location ``psd{j}.rx/.ry/.rz`` (rad, a rotation
    vector applied on the left of the start rotation ``R0_j``: ``R_j = exp(r) R0_j``) and
    ``psd{j}.x/.y/.z`` (m, the centre). Per known distance ``(a, b, D)`` one more row
    ``weight · (‖c_a − c_b‖ − D)``.

    Args:
        robot, laser, data: the model and measurements; free: which robot parameters are unknown
            (none for a pure PSD-pose fit).
        R0, c0: ``(m, 3, 3)``, ``(m, 3)`` start PSD poses (:func:`fit_psd_poses`).
        whiten: optional ``(N, 2, 2)`` per-beam matrices ``W`` applied to each spot residual and
            its Jacobian rows (``W r``): beam weights, e.g. from the expected spot covariance
            (:func:`spot_whitening`); then the rows are unitless and a
            distance row should be weighted by one over its noise std (``distance_weight``).
    """

    def __init__(self, robot, laser: Laser, data: PSDData, free: ParamSet, R0: Tensor, c0: Tensor, *,
                 distances: Sequence[tuple[int, int, float]] = (), distance_weight: float = DISTANCE_WEIGHT,
                 whiten: Tensor | None = None):
        super().__init__(robot, laser, free)
        if whiten is not None and whiten.shape != (data.q.shape[0], 2, 2):
            raise ValueError(f"whiten must have shape ({data.q.shape[0]}, 2, 2), got {tuple(whiten.shape)}")
        self.whiten = whiten
        self.data, self.m = data, data.n_locations
        self.R0, self.c0 = R0.to(data.q), c0.to(data.q)
        self.kr = self.idx.numel()
        self.names = list(self.robot_names) + [f"psd{j}.{s}" for j in range(self.m)
                                               for s in ("rx", "ry", "rz", "x", "y", "z")]
        self.units = list(self.robot_units) + ["rad", "rad", "rad", "m", "m", "m"] * self.m
        self.distances = [(int(a), int(b), float(D)) for a, b, D in distances]
        self.dw = float(distance_weight)
        self.n_rows = 2 * data.q.shape[0] + len(self.distances)
        self._set_bounds()

    def start(self) -> Tensor:
        z = torch.zeros(self.m, 6, dtype=self.data.q.dtype, device=self.data.q.device)
        z[:, 3:] = self.c0
        return torch.cat([self.free.values[self.idx], z.reshape(-1)])

    def psd_poses(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """PSD rotations ``(m, 3, 3)`` and centres ``(m, 3)`` (m) of a block vector ``(k,)``."""
        e = x[self.kr:].reshape(self.m, 6)
        return so3_exp(e[:, :3]) @ self.R0, e[:, 3:]

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, n_rows)`` (m)."""
        P = X.shape[0]
        p, w = laser_beams(self.robot, self.laser, self.data.q, self.robot_params(X))  # (P, N, 3)
        e = X[:, self.kr:].reshape(P, self.m, 6)
        R = so3_exp(e[..., :3]) @ self.R0  # (P, m, 3, 3)
        c = e[..., 3:]
        L = self.data.loc
        _, uv = plane_intersection(p, w, c[:, L], R[:, L])
        d = uv - self.data.uv
        if self.whiten is not None:
            d = (self.whiten @ d[..., None])[..., 0]
        r = [d.reshape(P, -1)]
        for a, b, D in self.distances:
            r.append(self.dw * ((c[:, a] - c[:, b]).norm(dim=-1, keepdim=True) - D))
        return torch.cat(r, 1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (n_rows, k)``, analytic through the robot's parameter Jacobian and the
        closed-form spot."""
        N, L = self.data.q.shape[0], self.data.loc
        th = self.robot_params(x)
        e = x[self.kr:].reshape(self.m, 6)
        if self.kr:
            p, w, Jp, Jw = laser_beam_jacobian(self.robot, self.laser, self.data.q, th)
        else:
            p, w = laser_beams(self.robot, self.laser, self.data.q, th)
        Gp, Gw, Gr, Gc = spot_jacobian(p, w, e[L, :3], e[L, 3:], self.R0[L])  # (N, 2, 3) each
        J = x.new_zeros(N, 2, x.numel())
        if self.kr:
            J[..., : self.kr] = Gp @ Jp[..., self.idx] + Gw @ Jw[..., self.idx]
        cols = self.kr + 6 * L[:, None] + torch.arange(6, device=x.device)  # (N, 6)
        J.scatter_(2, cols[:, None, :].expand(N, 2, 6), torch.cat([Gr, Gc], -1))
        if self.whiten is not None:
            J = self.whiten @ J
        rows = [J.reshape(2 * N, -1)]
        for a, b, _ in self.distances:
            d = x.new_zeros(1, x.numel())
            u = e[a, 3:] - e[b, 3:]
            u = u / u.norm()
            d[0, self.kr + 6 * a + 3: self.kr + 6 * a + 6] = self.dw * u
            d[0, self.kr + 6 * b + 3: self.kr + 6 * b + 6] = -self.dw * u
            rows.append(d)
        return torch.cat(rows, 0)


def analyse_block(block: "PointConstraint | SpotResidual", x: Tensor | None = None, *, rtol: float = 1e-9,
                  prefer=None):
    """Which unknowns of a residual block the data identify (:func:`~torchcal.problems.identifiability.analyse_jacobian`
    on the block's Jacobian at ``x``, default its start).

    Evaluate it on noise-free *design* data (simulated with the nominal model): on inconsistent
    data a point constraint seems to see the scale, because shrinking the robot shrinks every
    residual (``r → s·r``). PSD poses are kept first (they absorb the rigid-motion gauge).
    """
    x = block.start() if x is None else x
    pref = ([["psd*"]] if isinstance(block, SpotResidual) else []) + list(prefer or [])
    return analyse_jacobian(block.jacobian(x), block.names, block.units, rtol=rtol, prefer=pref or None)
