"""The calibration problem: robot + parameter set + residual blocks, as an optimiser
:class:`~torchcal.optim.Problem` over the free parameters."""
from __future__ import annotations


import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.kinematics.fk_compact import PositionKernel
from torchcal.measure.blocks import Loss, PositionResidual
from torchcal.measure.observations import Observations
from torchcal.measure.setup import Setup
from torchcal.params import ParamSet
from torchcal.problems.base import Problem

__all__ = ["CalibrationProblem", "EffectCalibrationProblem", "GAUGE_WEIGHT"]

# Residual (m) of a 100 % change of the robot's size when plane contacts alone cannot see it
# (:class:`~torchcal.measure.setup.Setup`): stiff enough that noise moves the size by < 1e-6.
GAUGE_WEIGHT = 10.0


class CalibrationProblem(Problem):
    """Minimise the residuals of ``blocks`` over the free entries of ``params``.

    Args:
        params: start values, free flags and bounds (lower/upper are used as given; swarm
            solvers need them finite).
        blocks: residual blocks (:mod:`torchcal.measure.blocks`).
        fitness: ``"sse"`` (sum of squared residuals, m²) or ``"sum_norm"`` (sum of Euclidean
            errors per observation, m — seed 000's objective).
        compact: evaluate position-only fitness through the compact kinematics path
            (:class:`~torchcal.kinematics.fk_compact.PositionKernel`); ``False`` uses the general path.
    """

    def __init__(self, robot, params: ParamSet, blocks: list, fitness: str = "sse", compact: bool = True):
        if fitness not in ("sse", "sum_norm"):
            raise ValueError(f"fitness must be 'sse' or 'sum_norm', got {fitness!r}")
        if not blocks:
            raise ValueError("a calibration problem needs at least one residual block")
        idx = params.free_index
        if idx.numel() == 0:
            raise ValueError("no free parameter: every parameter is fixed; choose some to identify ("
                             + advice("free=['pattern'] in calibrate, or ParamSet.unfix('pattern')",
                                      "--free PATTERN, e.g. --free '*.offset'") + ")")
        self.robot, self.params, self.blocks, self.fitness_kind = robot, params, blocks, fitness
        self.compact = compact
        self.fitness_is_sse = fitness == "sse"  # lets LM reuse its own sum of squares
        super().__init__(params.lower[idx], params.upper[idx], params.values[idx], params.free_names)
        # residuals are counted against the free parameters where a fit starts, after the
        # identifiability reduction (pipelines.fitting), never here: the Jacobian of a problem with
        # more unknowns than residuals is what that reduction reads
        self.m = sum(b.n_obs * b.obs_dim for b in blocks)

    def full(self, X: Tensor) -> Tensor:
        """Free values ``(P, k)`` or ``(k,)`` -> full parameter vectors."""
        return self.params.expand(X)

    def residuals(self, X: Tensor) -> Tensor:
        full = self.full(X)
        return torch.cat([b.residuals(full) for b in self.blocks], -1)

    def fitness(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P,)``: the sum of squares of :meth:`residuals`, or the sum of Euclidean
        errors (m). Position blocks go through a :class:`~torchcal.kinematics.fk_compact.PositionKernel`
        (built on the first call, rebuilt when the parameter set changes), whose per-call cost
        follows ``P``; other blocks, and populations that carry gradients, through the general
        residuals."""
        # The kernel writes into its own buffers: no autograd graph, no torch.func transform.
        plain = not X.requires_grad and not torch._C._functorch.is_functorch_wrapped_tensor(X)
        kernels = self._kernels() if self.compact and plain else None
        if kernels is None:
            if self.fitness_kind == "sse":
                r = self.residuals(X)
                return (r * r).sum(-1)
            full = self.full(X)
            return sum(b.errors(full).sum(-1) for b in self.blocks)
        total = None
        for kern, meas in kernels:
            d = kern(X) - meas  # (P, n_obs, 3)
            f = (d * d).sum((1, 2)) if self.fitness_is_sse else torch.linalg.vector_norm(d, dim=-1).sum(-1)
            total = f if total is None else total + f
        return total

    def _kernels(self) -> list | None:
        """One ``(PositionKernel, measured (n_obs, 3))`` per block when every block is an
        unweighted, non-robust position block with every axis measured (the fitness is then a plain function of the
        positions), else ``None``. Keyed by the parameter set's tensors and their in-place
        version counters, so changing fixed values or free flags rebuilds them."""
        ps = self.params
        key = tuple((id(t), t._version) for t in (ps.values, ps.free))
        if getattr(self, "_kernel_key", None) == key:
            return self._kernel_cache
        # partial axes are masked in the general path only
        ok = all(type(b) is PositionResidual and bool(b.axes_mask.all()) and (not self.fitness_is_sse or
                 (not b.weighted and b.loss.kind == "l2")) for b in self.blocks)
        kern = None
        if ok:
            kern = [(PositionKernel(b.robot, b.data.q, ps.values, ps.free_index, b.rows, b.cols), b.measured)
                    for b in self.blocks]
        self._kernel_key, self._kernel_cache = key, kern
        return kern

    def jacobian(self, x: Tensor) -> Tensor:
        full = self.full(x)
        J = torch.cat([b.jacobian(full) for b in self.blocks], 0)
        return J[:, self.params.free_index]


class EffectCalibrationProblem(Problem):
    """Geometry, set-up unknowns and effect models fitted together on what an instrument measured.

    ``params`` holds the robot's K geometric entries, then the set-up's S unknowns (plane poses and
    fixed points, :class:`~torchcal.measure.setup.Setup`; none for position data), then every
    effect's parameters (:func:`torchcal.effects.effect_params`); its free flags choose what
    moves. The model: ``q_true = q + Σ Δq_effect``, robot-base positions from the kinematics plus
    ``Σ Δp_effect``, then the instrument frame, then each observation's residual vector
    (:class:`~torchcal.measure.observations.Observations`: positions, partial positions, plane contacts,
    distances; ``(n_obs, 3)``, m, zero where nothing was measured).

    Args:
        loss: a :class:`~torchcal.measure.blocks.Loss` per observation (Huber in the loop).
        prior: ``(len(params),)`` weights ``w_i ≥ 0`` (m per unit of the parameter): a Gaussian
            prior ``x_i ~ N(0, (σ_noise / w_i)²)`` enters as the residual ``w_i x_i`` of every free
            parameter with ``w_i > 0`` (MAP); 0 = no prior.
        setup: the set-up whose unknowns follow the geometry in ``params``.
        rot_weight: m/rad; with it, measured marker orientations are observations too
            (:class:`~torchcal.measure.observations.Observations`). Effects that displace points
            (bending, growth) turn no frame: only joint deflections and the geometry do.

    Jacobian: geometric columns analytic (``param_jacobian`` at the corrected joint values, carried
    through each observation; position effects do not depend on the geometry, whose features are
    computed once); set-up columns analytic; effect columns by central differences, all
    perturbations evaluated in one population call.
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
        self._gauge = None
        if setup is not None and setup.scale_gauge is not None:
            g = setup.scale_gauge[self._geo_free]
            if bool((g != 0).any()):
                self._gauge = (g, setup.reference[self._geo_free])
                self.m += 1
        self._set_free = torch.nonzero(free[K:K + S]).flatten() + K
        self._eff_free = torch.nonzero(free[K + S:]).flatten() + K + S

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

    def marker_positions(self, full: Tensor) -> Tensor:
        """``(P, N, M, 3)`` model positions of every marker in every row (m, instrument frame)."""
        geo = full[:, : self.K]
        p = self.robot.positions(self.joint_values(full), geo, check=False, base=False)  # (P, N, M, 3)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.position_delta(full[:, a:b], prep)
            if d is not None:
                p = p + d
        Rb, tb = self.robot.base_transform(geo)
        return tb[:, None, None] + (Rb[:, None, None] @ p[..., None])[..., 0]

    def marker_frames(self, full: Tensor) -> tuple[Tensor, Tensor]:
        """``(P, N, M, 3, 3)`` marker rotations and ``(P, N, M, 3)`` positions (m), instrument frame;
        the effects' point displacements move the positions only."""
        geo = full[:, : self.K]
        R, p = self.robot.fk_rt(self.joint_values(full), geo, check=False, base=False)
        for e, prep, (a, b) in zip(self.effects, self._prep, self._offs):
            d = e.position_delta(full[:, a:b], prep)
            if d is not None:
                p = p + d
        Rb, tb = self.robot.base_transform(geo)
        return Rb[:, None, None] @ R, tb[:, None, None] + (Rb[:, None, None] @ p[..., None])[..., 0]

    def residual_vectors(self, full: Tensor) -> Tensor:
        """``(P, n_obs, 3)`` model − measured per observation (m; zero where nothing was measured)."""
        if self.obs.has_orientation:
            R, p = self.marker_frames(full)
            return self.obs.residuals(p, full[:, self.K:self.K + self.S], R)
        return self.obs.residuals(self.marker_positions(full), full[:, self.K:self.K + self.S])

    def errors(self, full: Tensor) -> Tensor:
        """``(P, n_obs)`` Euclidean error of each observation's measured components (m)."""
        return self.residual_vectors(full).norm(dim=-1)

    def residuals(self, X: Tensor) -> Tensor:
        full = self.full(X)
        r = self.residual_vectors(full)
        if self.loss.kind != "l2":
            fac, _ = self.loss.scales((r * r).sum(-1))
            r = r * fac[..., None]
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
        full = self.full(x)[None]
        J = torch.zeros(3 * self.n_obs, self.params.free_index.numel(), dtype=full.dtype, device=full.device)
        pos = {int(v): i for i, v in enumerate(self.params.free_index.tolist())}
        K, S = self.K, self.S
        turns = self.obs.has_orientation
        if self._geo_free.numel() or self._set_free.numel():
            R, p = (self.marker_frames(full) if turns else (None, self.marker_positions(full)))
            R, p = (None if R is None else R[0]), p[0]
            s = full[0, K:K + S]
        if self._geo_free.numel():
            q = self.joint_values(full)[0]
            Jg = self.robot.param_jacobian(q, full[0, :K], kind="pose" if turns else "position",
                                           check=False)[..., self._geo_free]
            D, W = (Jg[..., :3, :], Jg[..., 3:, :]) if turns else (Jg, None)
            J[:, [pos[int(v)] for v in self._geo_free.tolist()]] = self.obs.project(p, D, s, W, R).reshape(
                -1, self._geo_free.numel())
        if self._set_free.numel():
            Js = self.obs.setup_jacobian(p, s)[..., self._set_free - K]
            J[:, [pos[int(v)] for v in self._set_free.tolist()]] = Js.reshape(-1, self._set_free.numel())
        if self._eff_free.numel():
            k = self._eff_free.numel()
            h = self.fd_step * torch.clamp(full[0, self._eff_free].abs(), min=1.0)
            E = torch.zeros(2 * k, full.shape[1], dtype=full.dtype, device=full.device)
            ar = torch.arange(k, device=full.device)
            E[ar, self._eff_free] = h
            E[ar + k, self._eff_free] = -h
            r = self.residual_vectors(full + E)
            d = (r[:k] - r[k:]) / (2 * h)[:, None, None]  # (k, n, 3)
            J[:, [pos[int(v)] for v in self._eff_free.tolist()]] = d.permute(1, 2, 0).reshape(-1, k)
        return J

    def observation_weights(self, x: Tensor) -> Tensor:
        """``(n_obs,)`` the loss's IRLS factor per observation at ``x`` (1 for l2)."""
        if self.loss.kind == "l2":
            return torch.ones(self.n_obs, dtype=x.dtype, device=x.device)
        r = self.residual_vectors(self.full(x)[None])[0]
        return self.loss.scales((r * r).sum(-1))[1]

    def jacobian(self, x: Tensor) -> Tensor:
        J = self.data_jacobian(x)
        if self.loss.kind != "l2":
            J = J * self.observation_weights(x).repeat_interleave(3)[:, None]
        pos = {int(v): i for i, v in enumerate(self.params.free_index.tolist())}
        if self._prior is not None:
            idx, w = self._prior
            P = torch.zeros(idx.numel(), J.shape[1], dtype=J.dtype, device=J.device)
            P[torch.arange(idx.numel(), device=J.device), [pos[int(v)] for v in idx.tolist()]] = w
            J = torch.cat([J, P], 0)
        if self._gauge is not None:
            row = torch.zeros(1, J.shape[1], dtype=J.dtype, device=J.device)
            row[0, [pos[int(v)] for v in self._geo_free.tolist()]] = GAUGE_WEIGHT * self._gauge[0]
            J = torch.cat([J, row], 0)
        return J
