"""Finite-Fourier excitation trajectories (seed 001) and the condition-number design objective.

Joint ``i`` follows a finite Fourier series with ``N`` harmonics of the base frequency ``ω_f``
(Swevers et al. 1997; seed 001 uses ``N = 3``), ``ω_l = l ω_f``::

    q_i(t)   = q0_i + Σ_l [ a_il / ω_l · sin(ω_l t) − b_il / ω_l · cos(ω_l t) ]
    q̇_i(t)  =        Σ_l [ a_il · cos(ω_l t) + b_il · sin(ω_l t) ]
    q̈_i(t)  =        Σ_l [ −a_il ω_l · sin(ω_l t) + b_il ω_l · cos(ω_l t) ]

so ``2N + 1`` coefficients per joint (``a_il``, ``b_il`` in rad/s, ``q0_i`` in rad), laid out per
joint as ``[a_1..a_N, b_1..b_N, q0]``; a population is ``(P, J (2N + 1))``. The trajectory is
periodic with period ``2π/ω_f`` and ``q0`` is its mean position.

**Limits.** ``q_lower ≤ q ≤ q_upper``, ``|q̇| ≤ q̇_max``, ``|q̈| ≤ q̈_max`` per joint, checked on
the sample grid with a margin that makes them hold in continuous time. By default they are
enforced by *scaling*: the oscillating part of joint ``i`` (its ``a``, ``b``) is multiplied by
the largest ``s_i ∈ [0, 1]`` that satisfies all three limits around the mean ``q0_i`` (velocity
and acceleration scale with ``s``; the position excursion above / below ``q0`` too). A feasible
vector is left unchanged (up to the grid margin), an infeasible one is pulled along the ray
towards its mean, so every decoded trajectory is feasible and the optimiser never sees a
penalty cliff (:meth:`FourierExcitation.project`). ``constraint="penalty"`` in
:class:`ExcitationProblem` instead adds ``penalty × (largest relative violation)``.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from torchcal.dynamics import scara
from torchcal.kinematics.robots import dh_table

__all__ = ["FourierExcitation", "condition_number", "stack_regressor"]


class FourierExcitation:
    """Fourier-series trajectories for ``J`` joints, evaluated for a whole population at once.

    Args:
        q_lower, q_upper: ``(J,)`` position limits (rad or m).
        qd_max, qdd_max: ``(J,)`` velocity and acceleration limits (per s, per s²).
        n_harmonics: ``N`` (seed 001: 3).
        omega_f: base frequency ``ω_f`` (rad/s); the period is ``2π/ω_f``.
        n_samples: samples per period of the grid on which limits and regressors are taken.
    """

    def __init__(self, q_lower: Sequence[float] | Tensor, q_upper: Sequence[float] | Tensor,
                 qd_max: Sequence[float] | Tensor, qdd_max: Sequence[float] | Tensor,
                 n_harmonics: int = 3, omega_f: float = 2 * math.pi * 0.2, n_samples: int = 500,
                 dtype: torch.dtype = torch.float64):
        as_t = lambda v: torch.as_tensor(v, dtype=dtype).flatten()  # noqa: E731
        self.q_lower, self.q_upper = as_t(q_lower), as_t(q_upper)
        self.qd_max, self.qdd_max = as_t(qd_max), as_t(qdd_max)
        J = self.q_lower.numel()
        if not all(v.numel() == J for v in (self.q_upper, self.qd_max, self.qdd_max)):
            raise ValueError("q_lower, q_upper, qd_max and qdd_max need one entry per joint")
        if bool((self.q_upper <= self.q_lower).any()) or bool((self.qd_max <= 0).any()) \
                or bool((self.qdd_max <= 0).any()):
            raise ValueError("need q_upper > q_lower and positive velocity / acceleration limits")
        self.n_joints, self.n_harmonics = J, int(n_harmonics)
        self.omega_f, self.n_samples, self.dtype = float(omega_f), int(n_samples), dtype

    @classmethod
    def from_robot(cls, name: str = "scara", joints: Sequence[int] = (0, 1), *,
                   margin: float = math.radians(10.0), velocity_fraction: float = 0.5,
                   qdd_max: Sequence[float] = (10.0, 20.0), **kw) -> "FourierExcitation":
        """Limits from the robot's DH table (:func:`torchcal.kinematics.robots.dh_table`): position limits
        shrunk by ``margin`` on each side, ``velocity_fraction`` of the rated joint speed, and
        ``qdd_max`` (rad/s²; not published for the Cobra s600 — the default is an assumption
        for a gentle identification run). ``kw`` goes to the constructor."""

        rows = [dh_table(name)[j] for j in joints]
        return cls([r["lower"] + margin for r in rows], [r["upper"] - margin for r in rows],
                   [velocity_fraction * r["velocity"] for r in rows], qdd_max, **kw)

    # -- layout ---------------------------------------------------------------------------------
    @property
    def n_coef(self) -> int:
        """Coefficients per joint, ``2N + 1``."""
        return 2 * self.n_harmonics + 1

    @property
    def dim(self) -> int:
        return self.n_joints * self.n_coef

    @property
    def period(self) -> float:
        return 2 * math.pi / self.omega_f

    def names(self) -> list[str]:
        N = self.n_harmonics
        per = [f"a{l}" for l in range(1, N + 1)] + [f"b{l}" for l in range(1, N + 1)] + ["q0"]
        return [f"j{j + 1}.{p}" for j in range(self.n_joints) for p in per]

    def bounds(self) -> tuple[Tensor, Tensor]:
        """``(dim,)`` search box: ``|a_il|, |b_il| ≤ q̇_max,i`` (rad/s) and ``q0_i`` within the
        position limits. Scaling makes any point of the box feasible."""
        N = self.n_harmonics
        hi = torch.cat([torch.cat([v.expand(2 * N), u[None]]) for v, u in
                        zip(self.qd_max, self.q_upper)])
        lo = torch.cat([torch.cat([-v.expand(2 * N), l[None]]) for v, l in
                        zip(self.qd_max, self.q_lower)])
        return lo, hi

    def split(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(P, dim)`` -> ``a``, ``b`` ``(P, J, N)`` and ``q0`` ``(P, J)``."""
        c = x.reshape(*x.shape[:-1], self.n_joints, self.n_coef)
        N = self.n_harmonics
        return c[..., :N], c[..., N:2 * N], c[..., 2 * N]

    def join(self, a: Tensor, b: Tensor, q0: Tensor) -> Tensor:
        return torch.cat([a, b, q0[..., None]], -1).flatten(-2)

    # -- evaluation -----------------------------------------------------------------------------
    def times(self, n: int | None = None, periods: float = 1.0) -> Tensor:
        """``(n,)`` equally spaced times over ``periods`` periods (s), end excluded."""
        n = self.n_samples if n is None else int(n)
        return torch.arange(n, dtype=self.dtype) * (periods * self.period / n)

    def evaluate(self, x: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Positions, velocities, accelerations ``(P, T, J)`` of coefficient vectors ``x``
        ``(P, dim)`` at times ``t`` ``(T,)`` (default: :meth:`times`). A 1-D ``x`` gives
        ``(T, J)``."""
        q, qd, qdd = self._parts(x, t)
        return q + self.split(x)[2][..., None, :], qd, qdd

    def _parts(self, x: Tensor, t: Tensor | None):
        """Oscillating parts ``(q − q0, q̇, q̈)``, each ``(..., T, J)``."""
        t = self.times() if t is None else t.to(self.dtype)
        a, b, _ = self.split(x)
        w = self.omega_f * torch.arange(1, self.n_harmonics + 1, dtype=self.dtype)  # (N,)
        S, C = torch.sin(t[:, None] * w), torch.cos(t[:, None] * w)  # (T, N)
        # a, b: (..., J, N); contract the harmonic axis against (T, N) -> (..., T, J)
        q = (a @ (S / w).T - b @ (C / w).T).transpose(-1, -2)
        qd = (a @ C.T + b @ S.T).transpose(-1, -2)
        qdd = (-a @ (S * w).T + b @ (C * w).T).transpose(-1, -2)
        return q, qd, qdd

    def scale(self, x: Tensor, t: Tensor | None = None) -> Tensor:
        """``(P, J)`` largest factor ``s ∈ [0, 1]`` of each joint's oscillation that keeps it
        within all limits around its mean ``q0`` (see the module docstring), in continuous time.

        The limits are sampled on the grid ``t`` (default :meth:`times`). Between samples ``h``
        apart a trigonometric polynomial ``f`` of degree ``N`` can exceed its sampled values by at
        most ``ε ||f||∞`` with ``ε = (N ω_f h / 2)² / 2`` (Bernstein's inequality bounds
        ``|f''| ≤ (N ω_f)² ||f||∞``); the sampled maxima are inflated by that bound before the
        ratios are taken (``ε ≈ 1.8e-4`` on the default grid), so the result holds between
        grid points too.
        """
        qo, qd, qdd = self._parts(x, t)
        q0 = self.split(x)[2]
        tiny = torch.finfo(self.dtype).tiny
        eps = self._grid_eps(t)
        up, down = qo.amax(-2), (-qo).amax(-2)  # sampled excursions above / below the mean
        q_inf = torch.maximum(up, down) / (1.0 - eps)
        up, down = up + eps * q_inf, down + eps * q_inf
        room_up = (self.q_upper - q0).clamp_min(0.0)
        room_down = (q0 - self.q_lower).clamp_min(0.0)
        s = torch.stack([room_up / up.clamp_min(tiny), room_down / down.clamp_min(tiny),
                         (1.0 - eps) * self.qd_max / qd.abs().amax(-2).clamp_min(tiny),
                         (1.0 - eps) * self.qdd_max / qdd.abs().amax(-2).clamp_min(tiny)], -1)
        return s.amin(-1).clamp(max=1.0)

    def _grid_eps(self, t: Tensor | None) -> float:
        """Relative between-sample excess bound ``(N ω_f h / 2)² / 2`` of the grid ``t``."""
        if t is None:
            h = self.period / self.n_samples
        else:
            h = float((t[1:] - t[:-1]).max()) if t.numel() > 1 else self.period
        eps = 0.5 * (self.n_harmonics * self.omega_f * h / 2) ** 2
        if eps >= 0.5:
            raise ValueError(f"sample grid too coarse for {self.n_harmonics} harmonics (h = {h} s)")
        return eps

    def project(self, x: Tensor, t: Tensor | None = None) -> Tensor:
        """Feasible coefficients: ``a``, ``b`` of each joint times :meth:`scale` (``q0`` is
        clipped to the position limits first). Differentiable almost everywhere."""
        a, b, q0 = self.split(x)
        q0 = torch.maximum(torch.minimum(q0, self.q_upper), self.q_lower)
        x = self.join(a, b, q0)
        s = self.scale(x, t)[..., None]
        return self.join(a * s, b * s, q0)

    def violation(self, x: Tensor, t: Tensor | None = None) -> Tensor:
        """``(P,)`` largest relative limit violation (0 when feasible): position excess over the
        range width, velocity / acceleration excess over their limits."""
        q, qd, qdd = self.evaluate(x, t)
        width = self.q_upper - self.q_lower
        v = torch.stack([((q - self.q_upper) / width).amax(-2), ((self.q_lower - q) / width).amax(-2),
                         (qd.abs() / self.qd_max - 1.0).amax(-2),
                         (qdd.abs() / self.qdd_max - 1.0).amax(-2)], -1)
        return v.clamp_min(0.0).amax(-1).amax(-1)

    def random(self, n: int, generator: torch.Generator | None = None, feasible: bool = True) -> Tensor:
        """``(n, dim)`` coefficient vectors uniform in :meth:`bounds`, projected onto the limits
        when ``feasible``."""
        lo, hi = self.bounds()
        x = lo + (hi - lo) * torch.rand((n, self.dim), generator=generator, dtype=self.dtype)
        return self.project(x) if feasible else x


def stack_regressor(W: Tensor) -> Tensor:
    """``(..., T, J, k)`` per-sample regressors -> ``(..., T J, k)`` stacked observation matrix."""
    return W.flatten(-3, -2)


def condition_number(W: Tensor) -> Tensor:
    """``(...)`` 2-norm condition number ``σ_max/σ_min`` of ``(..., m, k)`` matrices, from the
    eigenvalues of ``WᵀW`` (cheap for tall ``W`` and differentiable); ``inf`` when rank
    deficient. Reliable up to about 1e7 in float64 (the Gram matrix squares it)."""
    lam = torch.linalg.eigvalsh(W.transpose(-1, -2) @ W)
    lo, hi = lam[..., 0], lam[..., -1]
    ok = lo > hi * 1e-15
    c = torch.sqrt(hi / torch.where(ok, lo, torch.ones_like(lo)))
    return torch.where(ok, c, torch.full_like(c, math.inf))


