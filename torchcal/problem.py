"""The calibration problem: robot + parameter set + residual blocks, as an optimiser
:class:`~torchcal.optim.Problem` over the free parameters."""
from __future__ import annotations

import math

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
        self.fitness_is_sse = fitness == "sse"  # lets LM reuse its own sum of squares
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


class EffectCalibrationProblem(Problem):
    """Geometry and effect models fitted together on position measurements.

    ``params`` holds the robot's K geometric entries followed by every effect's parameters
    (:func:`torchcal.effects.effect_params`); its free flags choose what moves. The model:
    ``q_true = q + Σ Δq_effect``, robot-base positions from the kinematics, position maps
    (thermal) applied, then the instrument frame.

    Jacobian: geometric columns analytic (``param_jacobian`` at the corrected joint values,
    times the per-row position scale of position effects); effect columns by central
    differences, all perturbations evaluated in one population call.
    """

    def __init__(self, robot, params: ParamSet, effects: list, data, loss=None, fd_step: float = 1e-6,
                 ridge: float = 0.0):
        from .measurement import Loss, PositionResidual

        idx = params.free_index
        if idx.numel() == 0:
            raise ValueError("no free parameter")
        super().__init__(params.lower[idx], params.upper[idx], params.values[idx], params.free_names)
        self.robot, self.params, self.effects, self.data = robot, params, list(effects), data
        self.fitness_is_sse = True
        self.K = robot.n_params
        if params.names[: self.K] != robot.param_names:
            raise ValueError("params must start with the robot's geometric parameters (robot.params())")
        self.loss = loss or Loss("l2")
        blk = PositionResidual(robot, data)
        self._rows, self._cols, self._meas = blk._rows, blk._cols, blk._meas
        self.obs_cols_measured = blk.obs_index[:, 1]  # index into data.marker_names
        self.n_obs = blk.n_obs
        self.m = 3 * self.n_obs
        self._prep = [e.prepare(data.q, data.covariates) for e in self.effects]
        offs, o = [], self.K
        for e in self.effects:
            offs.append((o, o + e.n_params))
            o += e.n_params
        self._offs = offs
        if o != len(params):
            raise ValueError(f"params has {len(params)} entries, the robot and effects need {o}")
        self.fd_step = fd_step
        # ridge: prior residuals sqrt(ridge) * e for every free joint error (lengths in m, angles
        # through a 1 m lever), pulling what the data barely sees to 0; the base frame and the
        # marker offsets are unknowns of the set-up, not errors of the robot, and stay unpulled
        self.ridge = float(ridge)
        setup = ("base.",) + tuple(f"{m}." for m in robot.marker_names)
        geo_err = torch.tensor([not n.startswith(setup) for n in params.names[: self.K]]
                               + [False] * (len(params) - self.K), device=params.free.device)
        self._ridge_idx = torch.nonzero(geo_err & params.free).flatten() if self.ridge > 0 else None
        if self._ridge_idx is not None:
            self.m += int(self._ridge_idx.numel())
        free = params.free.clone()
        self._geo_free = torch.nonzero(free[: self.K]).flatten()
        self._eff_free = torch.nonzero(free[self.K:]).flatten() + self.K

    def full(self, X: Tensor) -> Tensor:
        return self.params.expand(X)

    def _positions(self, full: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(P, n_obs, 3)`` model positions (instrument frame) and the per-row scale of
        position effects (or None)."""
        geo = full[:, : self.K]
        q = self.data.q[None].expand(full.shape[0], -1, -1)
        dq = None
        scale = None
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            if e.kind == "joint":
                d = e.joint_delta(full[:, a:b], prep)
                dq = d if dq is None else dq + d
        if dq is not None:
            q = q + dq
        p = self.robot.positions(q, geo, check=False, base=False)  # (P, N, M, 3)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            if e.kind == "position":
                s = e.row_scale(full[:, a:b], prep)
                scale = s if scale is None else scale * s
                p = e.position_map(p, full[:, a:b], prep)
        Rb, tb = self.robot.base_transform(geo)
        p = tb[:, None, None] + (Rb[:, None, None] @ p[..., None])[..., 0]
        return p[:, self._rows, self._cols], scale

    def errors(self, full: Tensor) -> Tensor:
        """``(P, n_obs)`` Euclidean errors (m)."""
        p, _ = self._positions(full)
        return (p - self._meas).norm(dim=-1)

    def residuals(self, X: Tensor) -> Tensor:
        full = self.full(X)
        p, _ = self._positions(full)
        r = p - self._meas
        if self.loss.kind != "l2":
            fac, _ = self.loss.scales((r * r).sum(-1))
            r = r * fac[..., None]
        r = r.reshape(r.shape[0], -1)
        if self._ridge_idx is not None:
            r = torch.cat([r, math.sqrt(self.ridge) * full[:, self._ridge_idx]], -1)
        return r

    def jacobian(self, x: Tensor) -> Tensor:
        full = self.full(x)[None]
        cols = []
        if self._geo_free.numel():
            geo = full[0, : self.K]
            q = self.data.q
            for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
                if e.kind == "joint":
                    q = q + e.joint_delta(full[:, a:b], prep)[0]
            Jg = self.robot.param_jacobian(q, geo, kind="position", check=False)[self._rows, self._cols]  # (n, 3, K)
            scale = None
            for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
                if e.kind == "position":
                    s = e.row_scale(full[:, a:b], prep)[0]
                    scale = s if scale is None else scale * s
            if scale is not None:  # p_w = R_b (s p) + t_b: every column but base.x/y/z scales by s
                fac = scale[self._rows][:, None, None].expand_as(Jg).clone()
                fac[..., :3] = 1.0
                Jg = Jg * fac
            cols.append((self._geo_free, Jg[..., self._geo_free].reshape(-1, self._geo_free.numel())))
        if self._eff_free.numel():
            k = self._eff_free.numel()
            h = self.fd_step * torch.clamp(full[0, self._eff_free].abs(), min=1.0)
            E = torch.zeros(2 * k, full.shape[1], dtype=full.dtype, device=full.device)
            ar = torch.arange(k, device=full.device)
            E[ar, self._eff_free] = h
            E[ar + k, self._eff_free] = -h
            p, _ = self._positions(full + E)
            d = (p[:k] - p[k:]) / (2 * h)[:, None, None]  # (k, n, 3)
            cols.append((self._eff_free, d.permute(1, 2, 0).reshape(-1, k)))
        # assemble in the order of the free parameters
        free_full = self.params.free_index
        pos = {int(v): i for i, v in enumerate(free_full.tolist())}
        J = torch.zeros(self.m, free_full.numel(), dtype=full.dtype, device=full.device)  # incl. ridge rows
        for idx, block in cols:
            J[: 3 * self.n_obs, [pos[int(v)] for v in idx.tolist()]] = block
        if self.loss.kind != "l2":
            p, _ = self._positions(full)
            r = p[0] - self._meas
            _, jfac = self.loss.scales((r * r).sum(-1))
            J[: 3 * self.n_obs] = J[: 3 * self.n_obs] * jfac.repeat_interleave(3)[:, None]
        if self._ridge_idx is not None:
            n = self._ridge_idx.numel()
            rows = torch.arange(3 * self.n_obs, 3 * self.n_obs + n, device=J.device)
            J[rows, [pos[int(v)] for v in self._ridge_idx.tolist()]] = math.sqrt(self.ridge)
        return J
