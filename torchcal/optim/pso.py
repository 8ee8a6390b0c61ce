"""Particle swarm optimisation: standard global-best PSO and LDPSO-BT (seed 000).

Both solvers are vectorised over the population: one Python loop over iterations, every
per-particle operation is a tensor op on ``(P, k)`` positions / velocities. Random numbers
come only from the solver's seeded generator (:meth:`Solver.generator`), so a run is
bit-reproducible for a given seed, dtype and device and never touches global RNG state.

An iteration's cost should follow the live population, which LDPSO-BT shrinks: the swarm lives
in buffers allocated once for the initial population, the live particles are their first ``P``
rows, every update is written in place into them (``out=`` and in-place ops), and the views for
each population size are made once (:class:`SwarmState`). So apart from the fitness, an
iteration is a fixed, short list of tensor operations on ``P`` rows, with no allocation of swarm
state and no per-particle Python.

Shapes: ``k`` parameters, ``P`` particles; positions ``X``, velocities ``V``, personal bests
``pbest`` are ``(P, k)``; fitness values ``f``, ``pbest_f`` are ``(P,)``; ``gbest`` is
``(k,)`` and ``gbest_f`` a 0-d tensor. Several independent runs carry a leading run axis
``R`` on all of them (:mod:`torchcal.optim.swarm`).
"""
from __future__ import annotations

from dataclasses import astuple
from fractions import Fraction
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import IterativeSolver
from torchcal.optim.swarm import SwarmState, rand_runs, rows_of
from torchcal.optim.swarm_options import LDPSOOptions, PSOOptions
from torchcal.problems.base import Problem

__all__ = ["PSO", "LDPSO_BT", "ldpso_pop_sizes", "SwarmState"]


@register
class PSO(IterativeSolver):
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
        stall_iter, stall_tol: stop a run once its best fitness has improved by at most
            ``stall_tol`` (relative) over the last ``stall_iter`` iterations (``None``: run all
            ``max_iter``). The test reads the best on the host: one synchronisation per iteration.
        seed, progress, callback: see :class:`Solver`. ``callback(it, best)`` is called after
            initialisation (``it = 0``) and after each iteration with the best fitness so far.

    Result: ``x`` the global best, ``history`` the best fitness after initialisation and after
    each iteration (``max_iter + 1`` floats), ``n_evals`` every point evaluated. NaN fitness
    values count as ``+inf`` (never a best).

    Several independent runs (restarts with their own seeds) go as one population tensor through
    :func:`~torchcal.optim.engine.minimize_runs`, each with its own random stream, bests and
    stopping: the same results as the runs one by one.
    """

    name = "pso"
    population = True
    batched = True

    def __init__(self, settings: PSOOptions | None = None, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None, **options):
        self.settings = PSOOptions.build(settings, **options)
        pop_size, max_iter, w, c1, c2, v_max, stall_iter, stall_tol = astuple(self.settings)
        super().__init__(seed=seed, progress=progress, callback=callback)
        if int(pop_size) < 1:
            raise ValueError(f"pop_size must be >= 1, got {pop_size}")
        if int(max_iter) < 0:
            raise ValueError(f"max_iter must be >= 0, got {max_iter}")
        if v_max is not None and not v_max > 0:
            raise ValueError(f"v_max must be positive or None, got {v_max}")
        if stall_iter is not None and int(stall_iter) < 1:
            raise ValueError(f"stall_iter must be >= 1 or None, got {stall_iter}")
        if not stall_tol >= 0:
            raise ValueError(f"stall_tol must be >= 0 (a relative improvement), got {stall_tol}")
        self.stall_iter = None if stall_iter is None else int(stall_iter)
        self.stall_tol = float(stall_tol)
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

    def _velocity(self, t: int, s: SwarmState, w: dict) -> None:
        """Update ``s.V`` in place to the new velocity before clamping: the standard PSO rule
        ``w v + c1 r1 (pbest - x) + c2 r2 (gbest - x)``, with the random numbers in ``w["r"]``
        (scratch of :meth:`SwarmState.scratch`). Each product and sum is the same floating-point
        operation, in the same order, as that expression written out."""
        torch.mul(w["r"], self._c12, out=w["t"])
        torch.sub(s.pbest, s.X, out=w["d1"])
        torch.sub(s.gbest.unsqueeze(-2), s.X, out=w["d2"])
        w["t"].mul_(w["d"])
        s.V.mul_(self.inertia(t)).add_(w["t1"]).add_(w["t2"])

    def _after_step(self, t: int, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        """Called after iteration ``t``'s bests are updated (chaotic PSO searches here)."""

    def _extra(self, s: SwarmState) -> dict:
        """Solver-specific entries for :attr:`Result.extra`."""
        return {}

    # -- shared helpers --------------------------------------------------------------------------
    @staticmethod
    def _evaluate(problem: Problem, X: Tensor, out: Tensor | None = None) -> Tensor:
        """Batched fitness ``(..., P, k) -> (..., P)`` (one call on all points) in the problem's
        dtype, NaN mapped to ``+inf`` so a failed evaluation can never become a best (``argmin``
        would otherwise pick NaN); written into ``out`` when given."""
        f = problem.fitness(X.reshape(-1, X.shape[-1])).to(dtype=problem.dtype).reshape(X.shape[:-1])
        inf = float("inf")
        return torch.nan_to_num(f, nan=inf, posinf=inf, neginf=-inf, out=out)

    @staticmethod
    def _update_bests(s: SwarmState, X: Tensor, f: Tensor, w: dict | None = None) -> None:
        """Update personal bests of every particle from ``(X, f)`` and the global best from them,
        in place (``w``: scratch of :meth:`SwarmState.scratch`, else temporaries are allocated).

        Strict ``<`` keeps the older point on ties, so equal values never churn the bests. All
        ops stay on the device (no ``.item()``): the global best is chosen with ``torch.where``.
        """
        better = torch.lt(f, s.pbest_f, out=None if w is None else w["better"])
        col = better[..., None] if w is None else w["better_col"]
        torch.where(col, X, s.pbest, out=s.pbest)
        torch.where(better, f, s.pbest_f, out=s.pbest_f)
        cand_f, i = torch.min(s.pbest_f, -1)
        gb = cand_f < s.gbest_f
        torch.where(gb[..., None], rows_of(s.pbest, i[..., None])[..., 0, :], s.gbest, out=s.gbest)
        torch.where(gb, cand_f, s.gbest_f, out=s.gbest_f)

    # -- the run -------------------------------------------------------------------------------
    def init(self, problem: Problem, g: torch.Generator | list[torch.Generator]) -> SwarmState:
        """The start of one run (``g`` a generator) or of several (``g`` a list: one per run, each
        drawing what its run would draw alone)."""
        problem.require_finite_bounds(self.name)
        span = problem.upper - problem.lower
        # Velocity limit per component; without v_max the full range is the natural scale.
        vlim = span * (self.v_max if self.v_max is not None else 1.0)
        self._c12 = torch.tensor([self.c1, self.c2], dtype=problem.dtype, device=problem.device)[:, None, None]

        if isinstance(g, torch.Generator):
            X, V = self._init_positions(problem, g, vlim)
        else:
            X, V = (torch.stack(t) for t in zip(*(self._init_positions(problem, gi, vlim) for gi in g)))
        if problem.x0 is not None:
            # Seed the swarm with the user's start so the result is never worse than it.
            X[..., 0, :] = problem.clip(problem.x0)
        s = SwarmState.allocate(X, V, self._evaluate(problem, X), ring=0 if self.stall_iter is None else
                                self.stall_iter + 1)
        s.vlim, s.nvlim = vlim, -vlim
        self._after_init(s, problem, g)
        return s

    def step(self, problem: Problem, s: SwarmState, t: int, g: torch.Generator) -> None:
        self._before_step(t, s, problem, g)
        w = s.scratch()
        rand_runs(g, w["r"])  # r1 = r[..., 0, :, :], r2 = r[..., 1, :, :]: one draw per run
        self._velocity(t, s, w)
        if self.v_max is not None:
            s.V.clamp_(s.nvlim, s.vlim)
        torch.add(s.X, s.V, out=w["xn"])
        torch.clamp(w["xn"], problem.lower, problem.upper, out=s.X)
        # A particle that hit a wall stops in that component instead of pushing into it.
        s.V.masked_fill_(torch.ne(s.X, w["xn"], out=w["wall"]), 0.0)
        f = self._evaluate(problem, s.X, out=w["f"])
        s.n_evals += s.size
        self._update_bests(s, s.X, f, w)
        self._after_step(t, s, problem, g)
        s.t = t
        if s.ring is not None:
            s.ring[t % s.ring.shape[0]] = s.gbest_f
        return None

    def _stalled(self, s: SwarmState) -> Tensor | None:
        """``(...)`` bool: whether each run's best improved by at most ``stall_tol`` (relative)
        over the last ``stall_iter`` iterations; ``None`` before that many or without the test."""
        if s.ring is None or s.t < self.stall_iter:
            return None
        L = s.ring.shape[0]
        old, new = s.ring[(s.t - self.stall_iter) % L], s.ring[s.t % L]
        return (old - new) <= self.stall_tol * old.abs()

    def _stall_message(self) -> str:
        return (f"the best fitness improved by at most {self.stall_tol:g} (relative) over the last "
                f"{self.stall_iter} iterations")

    def check(self, problem: Problem, s: SwarmState) -> tuple[bool, str] | None:
        stalled = self._stalled(s)
        if stalled is not None and bool(stalled):
            return True, self._stall_message()
        return None

    def check_runs(self, problem: Problem, s: SwarmState) -> tuple[Tensor, str] | None:
        """For several runs: ``((R,) bool, why)``, the runs that stop now, or ``None``."""
        stalled = self._stalled(s)
        return None if stalled is None else (stalled, self._stall_message())

    def finish(self, problem: Problem, s: SwarmState) -> tuple[Tensor, float, dict]:
        return s.gbest.clone(), float(s.gbest_f), self._extra(s)

    def finish_runs(self, problem: Problem, s: SwarmState) -> list[tuple[Tensor, float, dict]]:
        """For several runs: ``(x, fun, extra)`` per run of the state."""
        return [(x.clone(), f, self._extra(s)) for x, f in zip(s.gbest, s.gbest_f.tolist())]

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
        c1, c2, v_max, stall_iter, stall_tol, seed, progress, callback: as in :class:`PSO`.
    """

    name = "ldpso-bt"
    aliases = ("ldpso",)

    def __init__(self, settings: LDPSOOptions | None = None, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None, **options):
        o = LDPSOOptions.build(settings, **options)
        n_max, n_min, max_iter, w1, w2, k_switch = o.n_max, o.n_min, o.max_iter, o.w1, o.w2, o.k_switch
        if not 1 <= int(n_min) <= int(n_max):
            raise ValueError(f"need 1 <= n_min <= n_max, got n_min={n_min}, n_max={n_max}")
        super().__init__(PSOOptions(pop_size=n_max, max_iter=max_iter, w=w1, c1=o.c1, c2=o.c2, v_max=o.v_max,
                                    stall_iter=o.stall_iter, stall_tol=o.stall_tol),
                         seed=seed, progress=progress, callback=callback)
        self.settings = o
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
            s.keep_rows(torch.argsort(s.pbest_f, dim=-1, stable=True)[..., :n].sort(-1).values)

    def _velocity(self, t: int, s: SwarmState, w: dict) -> None:
        if t > self.k_switch * self.max_iter:
            # Best-tracking stage: only the global best attracts, v = w2 v + c2 r2 (gbest - x).
            torch.mul(w["r2"], self.c2, out=w["t2"])
            w["t2"].mul_(torch.sub(s.gbest.unsqueeze(-2), s.X, out=w["d2"]))
            s.V.mul_(self.w2).add_(w["t2"])
            return
        super()._velocity(t, s, w)

    def _extra(self, s: SwarmState) -> dict:
        return {"pop_sizes": list(self._sizes)}
