"""Particle swarm optimisation: standard global-best PSO and LDPSO-BT (seed 000).

Both solvers are vectorised over the population: one Python loop over iterations, every
per-particle operation is a tensor op on ``(P, k)`` positions / velocities. Random numbers
come only from the solver's seeded generator (:meth:`Solver.generator`), so a run is
bit-reproducible for a given seed, dtype and device and never touches global RNG state.

Shapes: ``k`` parameters, ``P`` particles; positions ``X``, velocities ``V``, personal bests
``pbest`` are ``(P, k)``; fitness values ``f``, ``pbest_f`` are ``(P,)``; ``gbest`` is
``(k,)`` and ``gbest_f`` a 0-d tensor.
"""
from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from typing import Callable

import torch
from torch import Tensor

from .base import Solver, progress_bar, register
from .problem import Problem
from .result import Result

__all__ = ["PSO", "LDPSO_BT", "ldpso_pop_sizes", "SwarmState"]


@dataclass
class SwarmState:
    """Mutable state of a swarm during one run (all tensors on the problem's dtype/device).

    Attributes:
        X: ``(P, k)`` positions.   V: ``(P, k)`` velocities.
        pbest: ``(P, k)`` personal best positions.   pbest_f: ``(P,)`` their fitness.
        gbest: ``(k,)`` global best position.   gbest_f: 0-d tensor, its fitness.
        n_evals: points evaluated so far (Python int: the population size is known on the
            host, so counting never synchronises with the device).
    """

    X: Tensor
    V: Tensor
    pbest: Tensor
    pbest_f: Tensor
    gbest: Tensor
    gbest_f: Tensor
    n_evals: int = 0

    @property
    def size(self) -> int:
        return int(self.X.shape[0])


@register
class PSO(Solver):
    """Standard global-best particle swarm optimisation.

    Per iteration ``t = 1..max_iter`` and particle (all particles at once)::

        v = w(t) v + c1 r1 (pbest - x) + c2 r2 (gbest - x),   r1, r2 ~ U(0, 1) per component
        v = clamp(v, -v_max (upper - lower), v_max (upper - lower))
        x = clip(x + v, lower, upper)      # velocity zeroed on the clipped components

    then personal and global bests are updated. Defaults are seed 000's settings for its
    PSO baseline (population 240, 500 iterations, w 0.8, c1 = c2 = 1.49).

    Initialisation: positions uniform in the bounds, velocities uniform in
    ``[-v_max (upper - lower), v_max (upper - lower)]``. When the problem has ``x0``, particle 0
    starts at ``x0`` (clipped to the bounds), so the result is never worse than the start.

    Args:
        pop_size: number of particles ``P``.
        max_iter: number of iterations (each evaluates the whole population).
        w: inertia weight; a float for a constant weight, or ``(w_start, w_end)`` for a weight
            decreasing linearly from ``w_start`` at iteration 1 to ``w_end`` at ``max_iter``.
        c1, c2: cognitive (personal best) and social (global best) coefficients.
        v_max: velocity limit as a fraction of each parameter's bound range; ``None`` = no limit
            (the initial velocities then span the full range).
        seed, progress, callback: see :class:`Solver`. ``callback(it, best)`` is called after
            initialisation (``it = 0``) and after each iteration with the best fitness so far.

    Result: ``x`` the global best, ``history`` the best fitness after initialisation and after
    each iteration (``max_iter + 1`` floats), ``n_evals`` every point evaluated. NaN fitness
    values count as ``+inf`` (never a best).
    """

    name = "pso"

    def __init__(self, *, pop_size: int = 240, max_iter: int = 500,
                 w: float | tuple[float, float] = 0.8, c1: float = 1.49, c2: float = 1.49,
                 v_max: float | None = 0.2, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None):
        super().__init__(seed=seed, progress=progress, callback=callback)
        if int(pop_size) < 1:
            raise ValueError(f"pop_size must be >= 1, got {pop_size}")
        if int(max_iter) < 0:
            raise ValueError(f"max_iter must be >= 0, got {max_iter}")
        if v_max is not None and not v_max > 0:
            raise ValueError(f"v_max must be positive or None, got {v_max}")
        self.pop_size = int(pop_size)
        self.max_iter = int(max_iter)
        self.w = w
        self.c1 = float(c1)
        self.c2 = float(c2)
        self.v_max = None if v_max is None else float(v_max)

    # -- schedule ----------------------------------------------------------------------------
    def inertia(self, t: int) -> float:
        """Inertia weight at iteration ``t`` (1-based): constant, or linear ``w_start -> w_end``."""
        if isinstance(self.w, (tuple, list)):
            w0, w1 = (float(v) for v in self.w)
            if self.max_iter <= 1:
                return w0
            return w0 + (w1 - w0) * (t - 1) / (self.max_iter - 1)
        return float(self.w)

    # -- hooks subclasses override -------------------------------------------------------------
    def _init_positions(self, problem: Problem, g: torch.Generator, vlim: Tensor) -> tuple[Tensor, Tensor]:
        """``(X, V)``, both ``(P, k)``: uniform positions in the bounds, uniform velocities in
        ``[-vlim, vlim]``."""
        P, k = self.pop_size, problem.dim
        u = torch.rand((2, P, k), generator=g, dtype=problem.dtype, device=problem.device)
        X = problem.lower + u[0] * (problem.upper - problem.lower)
        V = (2.0 * u[1] - 1.0) * vlim
        return X, V

    def _before_step(self, t: int, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        """Called at the start of iteration ``t`` (LDPSO-BT shrinks the population here)."""

    def _velocity(self, t: int, s: SwarmState, r1: Tensor, r2: Tensor) -> Tensor:
        """New ``(P, k)`` velocity before clamping: the standard PSO rule."""
        w = self.inertia(t)
        return w * s.V + self.c1 * r1 * (s.pbest - s.X) + self.c2 * r2 * (s.gbest - s.X)

    def _after_step(self, t: int, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        """Called after iteration ``t``'s bests are updated (chaotic PSO searches here)."""

    def _extra(self, s: SwarmState) -> dict:
        """Solver-specific entries for :attr:`Result.extra`."""
        return {}

    # -- shared helpers --------------------------------------------------------------------------
    @staticmethod
    def _evaluate(problem: Problem, X: Tensor) -> Tensor:
        """Batched fitness ``(P, k) -> (P,)`` in the problem's dtype, NaN mapped to ``+inf`` so a
        failed evaluation can never become a best (``argmin`` would otherwise pick NaN)."""
        f = problem.fitness(X).to(dtype=problem.dtype).reshape(X.shape[0])
        return torch.where(torch.isnan(f), torch.full_like(f, float("inf")), f)

    @staticmethod
    def _update_bests(s: SwarmState, X: Tensor, f: Tensor) -> None:
        """Update personal bests of every particle from ``(X, f)`` and the global best from them.

        Strict ``<`` keeps the older point on ties, so equal values never churn the bests. All
        ops stay on the device (no ``.item()``): the global best is chosen with ``torch.where``.
        """
        better = f < s.pbest_f
        s.pbest = torch.where(better[:, None], X, s.pbest)
        s.pbest_f = torch.where(better, f, s.pbest_f)
        i = torch.argmin(s.pbest_f)
        cand_f = s.pbest_f[i]
        gb = cand_f < s.gbest_f
        s.gbest = torch.where(gb, s.pbest[i], s.gbest)
        s.gbest_f = torch.where(gb, cand_f, s.gbest_f)

    # -- the run -------------------------------------------------------------------------------
    def _run(self, problem: Problem) -> Result:
        problem.require_finite_bounds(self.name)
        g = self.generator(problem)
        lo, hi = problem.lower, problem.upper
        span = hi - lo
        # Velocity limit per component; without v_max the full range is the natural scale.
        vlim = span * (self.v_max if self.v_max is not None else 1.0)

        X, V = self._init_positions(problem, g, vlim)
        if problem.x0 is not None:
            # Seed the swarm with the user's start so the result is never worse than it.
            X[0] = problem.clip(problem.x0)
        f = self._evaluate(problem, X)
        i = torch.argmin(f)
        s = SwarmState(X=X, V=V, pbest=X.clone(), pbest_f=f.clone(), gbest=X[i].clone(),
                       gbest_f=f[i].clone(), n_evals=int(X.shape[0]))
        self._after_init(s, problem, g)

        # History kept as a device tensor and converted once at the end: a per-iteration
        # .item() would force a host sync every iteration.
        hist = torch.empty(self.max_iter + 1, dtype=problem.dtype, device=problem.device)
        hist[0] = s.gbest_f
        bar = progress_bar(self.progress, self.max_iter, self.name)
        if self.callback is not None:
            self.callback(0, float(s.gbest_f))

        for t in range(1, self.max_iter + 1):
            self._before_step(t, s, problem, g)
            P, k = s.X.shape
            # One draw for r1 and r2 (fewer generator calls; the stream stays deterministic).
            r = torch.rand((2, P, k), generator=g, dtype=problem.dtype, device=problem.device)
            V = self._velocity(t, s, r[0], r[1])
            if self.v_max is not None:
                V = torch.maximum(torch.minimum(V, vlim), -vlim)
            Xn = s.X + V
            Xc = torch.maximum(torch.minimum(Xn, hi), lo)
            # A particle that hit a wall stops in that component instead of pushing into it.
            s.V = torch.where(Xc != Xn, torch.zeros_like(V), V)
            s.X = Xc
            f = self._evaluate(problem, Xc)
            s.n_evals += P
            self._update_bests(s, Xc, f)
            self._after_step(t, s, problem, g)
            hist[t] = s.gbest_f
            if bar is not None or self.callback is not None:
                best = float(s.gbest_f)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(best=f"{best:.4g}", refresh=False)
                if self.callback is not None:
                    self.callback(t, best)
        if bar is not None:
            bar.close()

        return Result(x=s.gbest.clone(), fun=float(s.gbest_f), history=hist.tolist(),
                      n_evals=s.n_evals, n_iter=self.max_iter, converged=False,
                      message=f"reached max_iter={self.max_iter}", extra=self._extra(s))

    def _after_init(self, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        """Called once after the initial population is evaluated."""


def ldpso_pop_sizes(n_max: int, n_min: int, max_iter: int) -> list[int]:
    """Seed 000's population schedule ``N(t) = round(Nmax - (t-1)(Nmax-Nmin)/(MaxIt-1))`` for
    ``t = 1..MaxIt``.

    Computed in exact rational arithmetic and rounded half away from zero (MATLAB's ``round``,
    which the paper used; Python's ``round`` would round halves to even). With one iteration the
    population is ``Nmax``.
    """
    if max_iter <= 1:
        return [int(n_max)] * max(int(max_iter), 0)
    out = []
    for t in range(1, max_iter + 1):
        q = Fraction(n_max) - Fraction((t - 1) * (n_max - n_min), max_iter - 1)
        out.append(int((q + Fraction(1, 2)).__floor__()))  # q > 0: half away from zero
    return out


@register
class LDPSO_BT(PSO):
    """LDPSO-BT (seed 000): PSO with a linearly decreasing population and a best-tracking stage.

    Two changes to standard PSO, exactly as in seed 000:

    1. **Linearly decreasing population.** At the start of iteration ``t = 1..MaxIt`` the swarm
       is cut to ``N(t) = round(Nmax - (t-1)(Nmax-Nmin)/(MaxIt-1))`` particles (see
       :func:`ldpso_pop_sizes`). The paper does not say which particles go; following the digest,
       the worst by personal-best fitness are dropped (the global best's owner is therefore always
       kept). Kept particles are index-selected, so every later tensor op and fitness evaluation
       is really on ``N(t)`` rows: fewer evaluations is the point (the paper reports 41.85 % less
       time than PSO).
    2. **Best tracking.** While ``t <= K MaxIt`` the velocity is standard PSO with inertia
       ``w1``; once ``t > K MaxIt`` the personal-best term is dropped and
       ``v = w2 v + c2 r2 (gbest - x)``.

    Initialisation, velocity clamping (``v_max``), clipping to bounds and the use of ``x0`` are
    those of :class:`PSO`. The initial population (``Nmax`` points) is evaluated once, so
    ``n_evals = Nmax + sum_t N(t)``. ``Result.extra["pop_sizes"]`` lists ``N(t)`` for each
    iteration.

    Args:
        n_max, n_min: ``Nmax`` (initial) and ``Nmin`` (final) population.
        max_iter: ``MaxIt``.
        w1, w2: inertia before / after the switch.
        k_switch: ``K``; the best-tracking stage is ``t > K MaxIt``.
        c1, c2, v_max, seed, progress, callback: as in :class:`PSO`.
    """

    name = "ldpso-bt"
    aliases = ("ldpso",)

    def __init__(self, *, n_max: int = 240, n_min: int = 40, max_iter: int = 500, w1: float = 0.8,
                 w2: float = 0.4, k_switch: float = 0.8, c1: float = 1.49, c2: float = 1.49,
                 v_max: float | None = 0.2, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None):
        if not 1 <= int(n_min) <= int(n_max):
            raise ValueError(f"need 1 <= n_min <= n_max, got n_min={n_min}, n_max={n_max}")
        super().__init__(pop_size=n_max, max_iter=max_iter, w=w1, c1=c1, c2=c2, v_max=v_max,
                         seed=seed, progress=progress, callback=callback)
        self.n_max = int(n_max)
        self.n_min = int(n_min)
        self.w1 = float(w1)
        self.w2 = float(w2)
        self.k_switch = float(k_switch)
        self._sizes: list[int] = []

    def _after_init(self, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        self._sizes = ldpso_pop_sizes(self.n_max, self.n_min, self.max_iter)

    def _before_step(self, t: int, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        n = self._sizes[t - 1]
        if n < s.size:
            # Keep the n best by personal-best fitness (stable sort: deterministic on ties), in
            # their original order so particle identity is easy to follow.
            keep = torch.argsort(s.pbest_f, stable=True)[:n].sort().values
            s.X = s.X.index_select(0, keep)
            s.V = s.V.index_select(0, keep)
            s.pbest = s.pbest.index_select(0, keep)
            s.pbest_f = s.pbest_f.index_select(0, keep)

    def _velocity(self, t: int, s: SwarmState, r1: Tensor, r2: Tensor) -> Tensor:
        if t > self.k_switch * self.max_iter:
            # Best-tracking stage: only the global best attracts.
            return self.w2 * s.V + self.c2 * r2 * (s.gbest - s.X)
        return self.w1 * s.V + self.c1 * r1 * (s.pbest - s.X) + self.c2 * r2 * (s.gbest - s.X)

    def _extra(self, s: SwarmState) -> dict:
        return {"pop_sizes": list(self._sizes)}
