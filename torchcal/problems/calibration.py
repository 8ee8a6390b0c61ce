"""The calibration problem: what an instrument measured
(:class:`~torchcal.measure.observations.Observations`), a robot and a parameter set as an optimiser
:class:`~torchcal.optim.Problem` over the free parameters. With set-up unknowns and effect models:
:class:`~torchcal.problems.effect_calibration.EffectCalibrationProblem`."""
from __future__ import annotations


import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.kinematics.fk_compact import PositionKernel
from torchcal.measure.data import Measurements
from torchcal.measure.loss import Loss
from torchcal.measure.observations import Observations
from torchcal.measure.setup import Setup, needs_setup
from torchcal.params import ParamSet
from torchcal.problems.base import Problem

__all__ = ["CalibrationProblem"]

class CalibrationProblem(Problem):
    """Minimise the residuals of what ``data`` measured over the free entries of ``params``.

    The observations (:class:`~torchcal.measure.observations.Observations`): every marker position
    (partial ones included: an axis not measured gives a zero residual and zero Jacobian rows) and
    distances between markers of one row, 3 components per observation (m), row-major. With
    ``rot_weight`` (m/rad) the data are poses instead (:meth:`Observations.as_poses`): each marker
    seen in all three axes with a measured orientation, ``(p − p_meas, rot_weight · log(R R_measᵀ))``,
    6 components per observation (default weight in calibrate 0.1 m/rad: 1 mrad counts like 0.1 mm).

    Args:
        params: start values, free flags and bounds (lower/upper are used as given; swarm
            solvers need them finite).
        data: the measurements; plane contacts and distances to fixed points, whose set-up is
            unknown, are for :class:`~torchcal.problems.effect_calibration.EffectCalibrationProblem`.
        fitness: ``"sse"`` (sum of squared residuals, m²) or ``"sum_norm"`` (sum of Euclidean
            position errors per observation, m — seed 000's objective).
        compact: evaluate position-only fitness through the compact kinematics path
            (:class:`~torchcal.kinematics.fk_compact.PositionKernel`); ``False`` uses the general path.
        loss: a robust :class:`~torchcal.measure.loss.Loss` per observation (a whole pose under ``rot_weight``).
        weights: ``(n_obs,)`` per observation: its residual is scaled by ``sqrt(w)``.
    """

    def __init__(self, robot, params: ParamSet, data: Measurements, fitness: str = "sse", compact: bool = True, *,
                 rot_weight: float | None = None, loss: Loss | None = None, weights: Tensor | None = None):
        if fitness not in ("sse", "sum_norm"):
            raise ValueError(f"fitness must be 'sse' or 'sum_norm', got {fitness!r}")
        idx = params.free_index
        if idx.numel() == 0:
            raise ValueError("no free parameter: every parameter is fixed; choose some to identify ("
                             + advice("free=['pattern'] in calibrate, or ParamSet.unfix('pattern')",
                                      "--free PATTERN, e.g. --free '*.offset'") + ")")
        self.robot, self.params, self.q, self.fitness_kind = robot, params, data.q, fitness
        self.obs, self.obs_dim = _observations(robot, data, rot_weight), 3 if rot_weight is None else 6
        self.n_obs = self.obs.n * 3 // self.obs_dim
        self.loss, self.weights = loss or Loss("l2"), _weights(weights, self.n_obs, robot)
        self.compact = compact
        self.fitness_is_sse = fitness == "sse"  # lets LM reuse its own sum of squares
        super().__init__(params.lower[idx], params.upper[idx], params.values[idx], params.free_names)
        # residuals are counted against the free parameters where a fit starts, after the
        # identifiability reduction (pipelines.fitting), never here: the Jacobian of a problem with
        # more unknowns than residuals is what that reduction reads
        self.m = self.n_obs * self.obs_dim
        self._free_cols = tuple(idx.tolist())  # the Jacobian's columns, read on the host once
        robot.column_plan(self._free_cols)

    def full(self, X: Tensor) -> Tensor:
        """Free values ``(P, k)`` or ``(k,)`` -> full parameter vectors."""
        return self.params.expand(X)

    def residual_vectors(self, full: Tensor) -> Tensor:
        """``(P, K)`` full vectors -> ``(P, n_obs, 3 | 6)`` model − measured per observation (m),
        unweighted and without loss."""
        if self.obs_dim == 3:
            return self._vectors(self.robot.positions(self.q, full, check=False))
        R, t = self.robot.fk_rt(self.q, full, check=False)
        return self._vectors(t, R)

    def _vectors(self, p: Tensor, R: Tensor | None = None) -> Tensor:
        """Residual vectors from marker positions ``p (P, N, M, 3)`` and, for poses, rotations ``R``."""
        return self.obs.residuals(p) if R is None else _as_poses(self.obs.residuals(p, None, R), 1)

    def errors(self, full: Tensor) -> Tensor:
        """``(P, K) -> (P, n_obs)`` Euclidean position error per observation (m), unweighted and without loss."""
        return self.residual_vectors(full)[..., :3].norm(dim=-1)

    def residuals(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P, m)`` weighted, robustified residuals (m)."""
        r = self.residual_vectors(self.full(X))
        if self.weights is not None:
            r = r * self.weights.sqrt()[:, None]
        return self.loss.apply(r).reshape(r.shape[0], -1)

    def jacobian(self, x: Tensor) -> Tensor:
        """``(k,) -> (m, k)`` Jacobian of :meth:`residuals` (under a robust loss, the rows whose product with
        the residuals is the exact gradient: :meth:`~torchcal.measure.loss.Loss.jacobian`)."""
        return self.full_jacobian(self.full(x), self._free_cols)

    def full_jacobian(self, full: Tensor, columns=None) -> Tensor:
        """``(K,)`` full vector -> ``(m, K)`` Jacobian of :meth:`residuals` in every parameter, free or
        fixed (``(m, c)`` in the parameters ``columns`` alone, indices into K)."""
        if self.obs_dim == 3:
            J, p = self.robot.param_jacobian(self.q, full, kind="position", check=False, return_positions=True,
                                             columns=columns)
            J, p, R = self.obs.project(p, J), p[None], None
        else:
            J = self.robot.param_jacobian(self.q, full, kind="pose", check=False, columns=columns)
            R, p = self.robot.fk_rt(self.q, full[None], check=False)
            J = _as_poses(self.obs.project(p[0], J[..., :3, :], None, J[..., 3:, :], R[0]), 0)
        w = None if self.weights is None else self.weights.sqrt()
        if w is not None:
            J = J * w[:, None, None]
        if self.loss.kind != "l2":  # the loss's rows at each observation's weighted residual
            r = self._vectors(p, R)[0] * (1 if w is None else w[:, None])
            J = self.loss.jacobian(r, J)
        return J.reshape(-1, J.shape[-1])

    def fitness(self, X: Tensor) -> Tensor:
        """``(P, k) -> (P,)``: the sum of squares of :meth:`residuals`, or the sum of Euclidean
        errors (m). Full positions go through a :class:`~torchcal.kinematics.fk_compact.PositionKernel`
        (built on the first call, rebuilt when the parameter set changes), whose per-call cost
        follows ``P``; other observations, and populations that carry gradients, through the general
        residuals."""
        # The kernel writes into its own buffers: no autograd graph, no torch.func transform.
        plain = not X.requires_grad and not torch._C._functorch.is_functorch_wrapped_tensor(X)
        kernel = self._kernels() if self.compact and plain else None
        if kernel is None:
            if self.fitness_is_sse:
                r = self.residuals(X)
                return (r * r).sum(-1)
            return self.errors(self.full(X)).sum(-1)
        d = kernel(X) - self.obs.target  # (P, n_obs, 3)
        return (d * d).sum((1, 2)) if self.fitness_is_sse else torch.linalg.vector_norm(d, dim=-1).sum(-1)

    def _kernels(self) -> PositionKernel | None:
        """The :class:`PositionKernel` of the observations when every one is a position seen in
        all three axes, unweighted and without a robust loss under ``"sse"`` (the fitness is then a
        plain function of the positions), else ``None``. Keyed by the parameter set's tensors and
        their in-place version counters, so changing fixed values or free flags rebuilds it."""
        ps = self.params
        key = tuple((id(t), t._version) for t in (ps.values, ps.free))
        if getattr(self, "_kernel_key", None) == key:
            return self._kernel_cache
        # partial axes are masked in the general path only
        ok = self.obs_dim == 3 and bool(self.obs.full_positions.all()) and (
            not self.fitness_is_sse or (self.weights is None and self.loss.kind == "l2"))
        kern = PositionKernel(self.robot, self.q, ps.values, ps.free_index, self.obs.rows, self.obs.marker) if ok else None
        self._kernel_key, self._kernel_cache = key, kern
        return kern


def _observations(robot, data: Measurements, rot_weight: float | None) -> Observations:
    """What :class:`CalibrationProblem` fits: the data's observations, as poses with ``rot_weight``."""
    if needs_setup(data):
        raise ValueError("these rows touch planes or measure distances to fixed points, whose poses are unknowns a "
                         "CalibrationProblem does not hold: use EffectCalibrationProblem (torchcal.run_loop)")
    if rot_weight is None:
        return Observations(robot, data)
    if data.quaternions is None:
        raise ValueError("a pose residual needs orientation columns <marker>.qw/.qx/.qy/.qz in the data; "
                         "use a position residual otherwise")
    return Observations(robot, data, rot_weight=rot_weight).as_poses()


def _as_poses(r: Tensor, axis: int) -> Tensor:
    """Position and orientation halves of pose observations (:meth:`Observations.as_poses`) along
    ``axis`` side by side: ``(…, 2h, 3, …)`` -> ``(…, h, 6, …)``."""
    h = r.shape[axis] // 2
    return torch.cat([r.narrow(axis, 0, h), r.narrow(axis, h, h)], axis + 1)


def _weights(weights, n_obs: int, robot) -> Tensor | None:
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=robot.dtype, device=robot.device)
    if w.shape != (n_obs,):
        raise ValueError(f"weights must have one entry per observation ({n_obs}), got shape {tuple(w.shape)}")
    return w
