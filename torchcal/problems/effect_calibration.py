"""The loop's problem: the geometry, the set-up's unknowns (planes, fixed points) and effect models
fitted together on what an instrument measured, with an optional prior and a robust loss
(:class:`EffectCalibrationProblem`); its Jacobians analytic for the geometry and the set-up, and
through the joint Jacobian for the effects, batched over points."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.measure.loss import Loss
from torchcal.measure.observations import Observations
from torchcal.measure.setup import Setup
from torchcal.kinematics.slots import BASE_NAMES
from torchcal.params import ParamSet
from torchcal.problems.base import Problem
from torchcal.problems.row_frames import base_columns, row_frames, turned

__all__ = ["EffectCalibrationProblem", "GAUGE_WEIGHT"]

# Residual (m) of a 100 % change of the robot's size when plane contacts alone cannot see it
# (:class:`~torchcal.measure.setup.Setup`): stiff enough that noise moves the size by < 1e-6.
GAUGE_WEIGHT = 10.0
# the marker frames of up to this many points are kept for the next call (:meth:`EffectCalibrationProblem._points`)
_KEPT_POINTS = 16


class EffectCalibrationProblem(Problem):
    """Geometry, set-up unknowns and effect models fitted together on what an instrument measured.

    ``params`` holds the robot's K geometric entries, then the set-up's S unknowns (plane poses and
    fixed points, :class:`~torchcal.measure.setup.Setup`; none for position data), then every
    effect's parameters (:func:`torchcal.effects.effect_params`); its free flags choose what
    moves. The model: ``q_true = q + Σ Δq_effect``, robot-base positions from the kinematics (with
    each row's marker points moved on their links by ``Σ point_delta``) plus ``Σ Δp_effect``, then
    the instrument frame, then each observation's residual vector
    (:class:`~torchcal.measure.observations.Observations`: positions, partial positions, plane contacts,
    distances; ``(n_obs, 3)``, m, zero where nothing was measured).

    Args:
        loss: a :class:`~torchcal.measure.loss.Loss` per observation (Huber in the loop).
        prior: ``(len(params),)`` weights ``w_i ≥ 0`` (m per unit of the parameter): a Gaussian
            prior ``x_i ~ N(0, (σ_noise / w_i)²)`` enters as the residual ``w_i x_i`` of every free
            parameter with ``w_i > 0`` (MAP); 0 = no prior.
        setup: the set-up whose unknowns follow the geometry in ``params``.
        rot_weight: m/rad; with it, measured marker orientations are observations too
            (:class:`~torchcal.measure.observations.Observations`). Effects that displace points
            (bending, growth) turn no frame: only joint deflections and the geometry do.

    Jacobian: geometric columns analytic (``param_jacobian`` at the corrected joint values and the
    moved marker points, carried through each observation; position effects do not depend on the
    geometry, whose features are computed once); set-up columns analytic; effect columns by central
    differences of the effects alone, all perturbations in one population call, carried through the
    joint Jacobian (deflections), the instrument frame (displacements) or the marker points' own
    columns at the current geometry (points moved on their links).
    """

    def __init__(self, robot, params: ParamSet, effects: list, data, loss=None, fd_step: float = 1e-6,
                 prior: Tensor | None = None, setup: Setup | None = None, rot_weight: float | None = None):
        idx = params.free_index
        if idx.numel() == 0:
            raise ValueError("no free parameter")
        super().__init__(params.lower[idx], params.upper[idx], params.values[idx], params.free_names)
        self.robot, self.params, self.effects, self.data = robot, params, list(effects), data
        self.fitness_is_sse = True
        self.K = robot.n_params
        if params.names[: self.K] != robot.param_names:
            raise ValueError("params must start with the robot's geometric parameters (robot.params())")
        self.setup = setup
        self.S = 0 if setup is None else setup.n_params
        if self.S and params.names[self.K:self.K + self.S] != setup.names:
            raise ValueError("params must hold the set-up's unknowns (setup.params()) right after the geometry")
        self.loss = loss or Loss("l2")
        self.obs = Observations(robot, data, setup, rot_weight)
        self.rows, self.cols = self.obs.rows, self.obs.marker  # (n_obs,) row and robot marker of each observation
        self.n_obs = self.obs.n
        self.m = 3 * self.n_obs
        self._prep = [e.prepare(data.q, e.clamped(data.covariates)) for e in self.effects]
        offs, o = [], self.K + self.S
        for e in self.effects:
            offs.append((o, o + e.n_params))
            o += e.n_params
        self._offs = offs
        if o != len(params):
            raise ValueError(f"params has {len(params)} entries, the robot, set-up and effects need {o}")
        self.fd_step = fd_step
        self._prior = None
        if prior is not None:
            w = torch.as_tensor(prior, dtype=params.values.dtype, device=params.values.device)
            if w.shape != (len(params),):
                raise ValueError(f"prior weights must have shape ({len(params)},), got {tuple(w.shape)}")
            pick = torch.nonzero((w > 0) & params.free).flatten()
            if pick.numel():
                self._prior = (pick, w[pick])
                self.m += int(pick.numel())
        free = params.free.clone()
        K, S = self.K, self.S
        self._geo_free = torch.nonzero(free[:K]).flatten()
        self._geo_cols = tuple(self._geo_free.tolist())  # the kinematics' column plan is keyed on the host
        # effects that move marker points on their links: their columns are the points' own columns
        # at the current geometry, computed in the same kinematic pass as the geometry's
        self._jac_cols, self._mk_cols = self._geo_cols, None
        if any(e.point_delta(params.values.new_zeros(1, e.n_params), p) is not None
               for e, p in zip(self.effects, self._prep)):
            mk = [robot.param_names.index(f"{m}.{a}") for m in robot.marker_names for a in ("dx", "dy", "dz")]
            self._jac_cols = self._geo_cols + tuple(c for c in mk if c not in self._geo_cols)
            at = {c: i for i, c in enumerate(self._jac_cols)}
            self._mk_cols = torch.tensor([at[c] for c in mk], device=params.values.device)
        # effects that move the instrument frame per row: each row's frame is carried exactly
        self._base_idx = [robot.param_names.index(n) for n in BASE_NAMES]
        self._moves_frame = any(e.frame_delta(params.values.new_zeros(1, e.n_params), p) is not None
                                for e, p in zip(self.effects, self._prep))
        self._gauge = None
        if setup is not None and setup.scale_gauge is not None:
            g = setup.scale_gauge[self._geo_free]
            if bool((g != 0).any()):
                self._gauge = (g, setup.reference[self._geo_free])
                self.m += 1
        self._set_free = torch.nonzero(free[K:K + S]).flatten() + K
        self._eff_free = torch.nonzero(free[K + S:]).flatten() + K + S
        self._memo = None  # (full (B, K'), its marker frames): see _points
        self._extra_rows = None  # the Jacobian's prior and gauge rows: see _fixed_rows

    def full(self, X: Tensor) -> Tensor:
        return self.params.expand(X)

    def joint_values(self, full: Tensor) -> Tensor:
        """``(P, N, dof)`` commands plus the joint deflections of the effects."""
        q = self.data.q[None].expand(full.shape[0], -1, -1)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.joint_delta(full[:, a:b], prep)
            if d is not None:
                q = q + d
        return q

    def point_offsets(self, full: Tensor) -> Tensor | None:
        """``(P, N, M, 3)`` each row's marker points moved on their links by the effects (m, along the
        points' own error translations), or None when no effect moves them."""
        if self._mk_cols is None:
            return None
        total = None
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.point_delta(full[:, a:b], prep)
            if d is not None:
                total = d if total is None else total + d
        return total

    def _row_frames(self, full: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
        """Each row's instrument frame (rotation, translation, left Jacobian; :func:`row_frames`) when
        an effect moves it, else None (one frame for every row)."""
        if not self._moves_frame:
            return None
        return row_frames(full[:, self._base_idx], self._row_motion(full))

    def _instrument(self, full: Tensor) -> tuple[Tensor, Tensor]:
        """The instrument frame of every row, ``(P, N|1, 1, 3, 3)`` and ``(P, N|1, 1, 3)`` (broadcast over
        the markers): each row's own when an effect moves it, else the one frame."""
        fr = self._row_frames(full)
        if fr is not None:
            return fr[0][:, :, None], fr[1][:, :, None]
        Rb, tb = self.robot.base_transform(full[:, : self.K])
        return Rb[:, None, None], tb[:, None, None]

    def _row_motion(self, full: Tensor) -> Tensor:
        """``(P, N, 6)`` each row's offsets of the instrument frame's parameters, the effects' together."""
        total = full.new_zeros(full.shape[0], len(self.data), 6)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.frame_delta(full[:, a:b], prep)
            if d is not None:
                total = total + d
        return total

    def marker_positions(self, full: Tensor) -> Tensor:
        """``(P, N, M, 3)`` model positions of every marker in every row (m, instrument frame)."""
        geo = full[:, : self.K]
        p = self.robot.positions(self.joint_values(full), geo, check=False, base=False,
                                 points=self.point_offsets(full))  # (P, N, M, 3)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.position_delta(full[:, a:b], prep)
            if d is not None:
                p = p + d
        Rb, tb = self._instrument(full)
        return tb + (Rb @ p[..., None])[..., 0]

    def marker_frames(self, full: Tensor) -> tuple[Tensor, Tensor]:
        """``(P, N, M, 3, 3)`` marker rotations and ``(P, N, M, 3)`` positions (m), instrument frame;
        the effects' point displacements move the positions only."""
        geo = full[:, : self.K]
        R, p = self.robot.fk_rt(self.joint_values(full), geo, check=False, base=False, points=self.point_offsets(full))
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.position_delta(full[:, a:b], prep)
            if d is not None:
                p = p + d
        Rb, tb = self._instrument(full)
        return Rb @ R, tb + (Rb @ p[..., None])[..., 0]

    def _points(self, full: Tensor) -> tuple[Tensor | None, Tensor]:
        """Marker rotations (None without measured orientations) and positions at ``full``. The last
        few points (a single fit's, or a batch of CV folds') are kept: a least-squares solver asks for
        the Jacobian (and the loss's weights) where it has just evaluated the residuals, and the
        kinematics need not run again."""
        memo = self._memo
        few = full.shape[0] <= _KEPT_POINTS and not full.requires_grad  # (a graph is never kept)
        if few and memo is not None and memo[0].shape == full.shape and torch.equal(memo[0], full):
            return memo[1]
        out = self.marker_frames(full) if self.obs.has_orientation else (None, self.marker_positions(full))
        if few:
            self._memo = (full.clone(), out)
        return out

    def residual_vectors(self, full: Tensor) -> Tensor:
        """``(P, n_obs, 3)`` model − measured per observation (m; zero where nothing was measured)."""
        R, p = self._points(full)
        return self.obs.residuals(p, full[:, self.K:self.K + self.S], R)

    def errors(self, full: Tensor) -> Tensor:
        """``(P, n_obs)`` Euclidean error of each observation's measured components (m)."""
        return self.residual_vectors(full).norm(dim=-1)

    def residuals(self, X: Tensor) -> Tensor:
        full = self.full(X)
        r = self.loss.apply(self.residual_vectors(full))
        r = r.reshape(r.shape[0], -1)
        if self._prior is not None:
            idx, w = self._prior
            r = torch.cat([r, w * full[:, idx]], -1)
        if self._gauge is not None:
            g, ref = self._gauge
            r = torch.cat([r, GAUGE_WEIGHT * ((full[:, self._geo_free] - ref) @ g)[:, None]], -1)
        return r

    def data_jacobian(self, x: Tensor) -> Tensor:
        """``(3 n_obs, n_free)`` Jacobian of the raw residual vectors (no loss, no prior rows)."""
        return self.data_jacobians(x[None])[0]

    def data_jacobians(self, X: Tensor) -> Tensor:
        """:meth:`data_jacobian` at each of ``B`` points ``X (B, n_free)``: ``(B, 3 n_obs, n_free)``, the
        kinematics of every point in one call (a batch of CV folds costs little more than one fold)."""
        full = self.full(X)
        B = full.shape[0]
        K, S = self.K, self.S
        turns = self.obs.has_orientation
        R, p = self._points(full)
        s = full[:, K:K + S]
        dq, dp, dl, df = self._effect_deltas(full) if self._eff_free.numel() else (None, None, None, None)
        Jq = Jmk = Jg = None
        if self._jac_cols or dq is not None:  # one kinematic pass for every Jacobian, the columns needed only
            Jg = self.robot.param_jacobian(self.joint_values(full), full[:, :K], kind="pose" if turns else "position",
                                           check=False, joints=dq is not None, columns=self._jac_cols,
                                           points=self.point_offsets(full))
            if dq is not None:
                Jg, Jq = Jg
            if self._mk_cols is not None:  # each marker's own three columns: (B, N, M, r, 3)
                n = len(self.robot.marker_names)
                Jmk = Jg[..., self._mk_cols].unflatten(-1, (n, 3)).diagonal(dim1=2, dim2=-2).movedim(-1, 2)
                Jg = Jg[..., : len(self._geo_cols)]
        frames, rows = self._row_frames(full), None
        if frames is not None:  # every column at its row's instrument frame, the base's own taken there
            Rr, tr, Jl = frames
            Mr = Rr @ self.robot.base_transform(full[:, :K])[0].transpose(-1, -2)[:, None]
            Jg, Jq, Jmk = (None if J is None else turned(J, Mr) for J in (Jg, Jq, Jmk))
            rows = Rr  # the robot-base displacements of the effects turn with each row's frame
            frames = base_columns(p, tr, Jl, turns)  # (B, N, M, 3|6, 6)
            for j, c in enumerate(self._geo_cols if Jg is not None else ()):
                if c in self._base_idx:
                    Jg[..., j] = frames[..., self._base_idx.index(c)]

        def per_point(f) -> Tensor:  # (B, 3 n_obs, c) from each point's (n_obs, 3, c)
            out = [f(b).reshape(3 * self.n_obs, -1) for b in range(B)]
            return out[0][None] if B == 1 else torch.stack(out)
        # the free entries run geometry, set-up, effects (free_index ascends): the columns are three blocks
        blocks = []
        if self._geo_free.numel():
            D, W = (Jg[..., :3, :], Jg[..., 3:, :]) if turns else (Jg, None)
            blocks.append(per_point(lambda b: self.obs.project(p[b], D[b], s[b], None if W is None else W[b],
                                                               None if R is None else R[b])))
        if self._set_free.numel():
            blocks.append(per_point(lambda b: self.obs.setup_jacobian(p[b], s[b])[..., self._set_free - K]))
        if self._eff_free.numel():
            blocks.append(self._effect_columns(full, p, s, R, Jq, dq, dp, Jmk, dl, frames, df, rows))
        if not blocks:
            return full.new_zeros(B, 3 * self.n_obs, 0)
        return blocks[0] if len(blocks) == 1 else torch.cat(blocks, -1)

    def _effect_deltas(self, full: Tensor) -> tuple[Tensor | None, ...]:
        """Central differences of the effects' joint deflections ``(B, k, N, dof)``, robot-base point
        displacements ``(B, k, N, M, 3)``, marker points moved on their links ``(B, k, N, M, 3)`` and
        offsets of the instrument frame's parameters ``(B, k, N, 6)`` by their free parameters at ``full (B, K')`` (None:
        no effect moves that), every perturbation in one population call of the effects alone."""
        B, k = full.shape[0], self._eff_free.numel()
        h = self.fd_step * torch.clamp(full[:, self._eff_free].abs(), min=1.0)  # (B, k)
        E = torch.zeros(B, 2 * k, full.shape[1], dtype=full.dtype, device=full.device)
        ar = torch.arange(k, device=full.device)
        E[:, ar, self._eff_free] = h
        E[:, ar + k, self._eff_free] = -h
        F = (full[:, None] + E).reshape(B * 2 * k, -1)
        out = []
        for kind in ("joint_delta", "position_delta", "point_delta", "frame_delta"):
            total = None
            for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
                d = getattr(e, kind)(F[:, a:b], prep)
                if d is not None:
                    total = d if total is None else total + d
            if total is not None:
                total = total.reshape(B, 2 * k, *total.shape[1:])
                hh = (2 * h).reshape(B, k, *([1] * (total.ndim - 2)))
                total = (total[:, :k] - total[:, k:]) / hh
            out.append(total)
        return out[0], out[1], out[2], out[3]

    def _effect_columns(self, full: Tensor, p: Tensor, s: Tensor, R: Tensor | None, Jq: Tensor | None,
                        dq: Tensor | None, dp: Tensor | None, Jmk: Tensor | None = None,
                        dl: Tensor | None = None, Jf: Tensor | None = None, df: Tensor | None = None,
                        rows: Tensor | None = None) -> Tensor:
        """``(B, 3 n_obs, k)`` effect columns: the effects' deflections ``dq``, displacements ``dp`` and
        marker points moved on their links ``dl`` per unit parameter (:meth:`_effect_deltas`, no
        kinematics run for them), carried to the observations through the markers' joint Jacobian
        ``Jq (B, N, M, 3|6, dof)`` at the deflected joints, the instrument frame, and each marker's
        own point columns ``Jmk (B, N, M, 3|6, 3)`` at the current geometry, and the base's columns ``Jf
        (B, N, M, 3|6, 6)`` at each row's frame (its rotation ``rows (B, N, 3, 3)``) for the frame's offsets
        ``df``; points turn no frame."""
        K, B, k = self.K, full.shape[0], self._eff_free.numel()
        turns = self.obs.has_orientation
        # displacements in the robot base frame turn with each row's frame, or with the one frame
        Rb = None if dp is None else (rows if rows is not None else
                                      self.robot.base_transform(full[:, :K])[0][:, None].expand(B, len(self.data), 3, 3))
        out = full.new_zeros(B, 3 * self.n_obs, k)
        for b in range(B):
            D, W = 0.0, 0.0
            if dq is not None:
                D = torch.einsum("nmrd,knd->nmrk", Jq[b, :, :, :3], dq[b])
                W = torch.einsum("nmrd,knd->nmrk", Jq[b, :, :, 3:], dq[b]) if turns else 0.0
            if dp is not None:
                D = D + torch.einsum("nij,knmj->nmik", Rb[b], dp[b])
            if dl is not None:
                D = D + torch.einsum("nmra,knma->nmrk", Jmk[b, :, :, :3], dl[b])
            if df is not None:
                D = D + torch.einsum("nmrc,knc->nmrk", Jf[b, :, :, :3], df[b])
                W = W + torch.einsum("nmrc,knc->nmrk", Jf[b, :, :, 3:], df[b]) if turns else 0.0
            W = (torch.zeros_like(D) if isinstance(W, float) else W) if turns else None
            out[b] = self.obs.project(p[b], D, s[b], W, None if R is None else R[b]).reshape(-1, k)
        return out

    def observation_weights(self, x: Tensor) -> Tensor:
        """``(n_obs,)`` the loss's IRLS factor per observation at ``x`` (1 for l2)."""
        if self.loss.kind == "l2":
            return torch.ones(self.n_obs, dtype=x.dtype, device=x.device)
        r = self.residual_vectors(self.full(x)[None])[0]
        return self.loss.scales((r * r).sum(-1))[1]

    def jacobian(self, x: Tensor) -> Tensor:
        return self.jacobians(x[None])[0]

    def jacobians(self, X: Tensor) -> Tensor:
        """:meth:`jacobian` at each of ``B`` points ``X (B, n_free)``: ``(B, m, n_free)``."""
        J = self.data_jacobians(X)
        if self.loss.kind != "l2":
            r = self.residual_vectors(self.full(X))
            J = self.loss.jacobian(r, J.unflatten(1, (self.n_obs, 3))).flatten(1, 2)
        extra = self._fixed_rows()
        if extra is None:
            return J
        return torch.cat([J, extra.expand(J.shape[0], -1, -1)], 1)

    def _fixed_rows(self) -> Tensor | None:
        """``(1, rows, n_free)`` the Jacobian's prior and gauge rows, which no point changes (built
        once); None without either."""
        if self._prior is None and self._gauge is None:
            return None
        if self._extra_rows is None:
            free = self.params.free_index
            pos = {int(v): i for i, v in enumerate(free.tolist())}
            rows = []
            if self._prior is not None:
                idx, w = self._prior
                P = w.new_zeros(idx.numel(), free.numel())
                P[torch.arange(idx.numel(), device=w.device), [pos[int(v)] for v in idx.tolist()]] = w
                rows.append(P)
            if self._gauge is not None:
                row = self._gauge[0].new_zeros(1, free.numel())
                row[0, [pos[int(v)] for v in self._geo_free.tolist()]] = GAUGE_WEIGHT * self._gauge[0]
                rows.append(row)
            self._extra_rows = torch.cat(rows)[None]
        return self._extra_rows
