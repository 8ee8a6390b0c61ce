"""Chaotic particle swarm optimisation (seed 001).

CPSO is :class:`~torchcal.optim.pso.PSO` with two additions driven by the logistic map
``s <- mu s (1 - s)``:

1. the initial positions and velocities are a logistic-map sequence mapped onto the bounds
   (instead of uniform random numbers);
2. after each iteration a chaotic sequence started at the global best is evaluated and its best
   point replaces a random particle.

Shapes as in :mod:`torchcal.optim.pso`: ``k`` parameters, ``P`` particles, ``n`` chaotic points.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.pso import PSO, SwarmState
from torchcal.optim.swarm_options import CPSOOptions, PSOOptions
from torchcal.problems.base import Problem

__all__ = ["ChaoticPSO", "logistic_sequence", "avoid_fixed_points"]

#: Points of ``[0, 1]`` on which the ``mu = 4`` logistic map is not chaotic: the fixed points
#: 0 and 3/4, and the points that reach a fixed point in one or two steps (1 -> 0, 1/2 -> 1 -> 0,
#: 1/4 -> 3/4). A sequence started on (or, in floating point, very near) one of them stalls.
_BAD_POINTS = (0.0, 0.25, 0.5, 0.75, 1.0)


def avoid_fixed_points(s: Tensor, eps: float = 1e-3) -> Tensor:
    """Move entries of ``s`` (any shape, values in ``[0, 1]``) that lie within ``eps`` of 0, 1/4,
    1/2, 3/4 or 1 by ``3 eps`` towards the middle of their half of the interval (``+3 eps`` below
    1/2, ``-3 eps`` from 1/2 up), which leaves them at least ``2 eps`` from every bad point.
    Deterministic, so it does not consume random numbers."""
    near = torch.zeros_like(s, dtype=torch.bool)
    for p in _BAD_POINTS:
        near |= (s - p).abs() < eps
    step = torch.where(s < 0.5, torch.full_like(s, 3 * eps), torch.full_like(s, -3 * eps))
    return torch.where(near, s + step, s)


def logistic_sequence(s0: Tensor, n: int, mu: float = 4.0) -> Tensor:
    """``(n, *s0.shape)``: the iterates ``s_1 .. s_n`` of ``s_{j+1} = mu s_j (1 - s_j)`` from
    ``s0`` (``s0`` itself is not included). Values are clamped to ``[0, 1]`` to absorb rounding.

    The loop is over the ``n`` iterates (inherently sequential); each step is vectorised over
    the components of ``s0``.
    """
    out = torch.empty((n, *s0.shape), dtype=s0.dtype, device=s0.device)
    s = s0
    for j in range(n):
        s = (mu * s * (1.0 - s)).clamp(0.0, 1.0)
        out[j] = s
    return out


@register
class ChaoticPSO(PSO):
    """Chaotic PSO (seed 001): logistic-map initialisation and a chaotic search around gbest.

    **Logistic map and mu.** The seed text prints ``mu = 2``; at ``mu = 2`` the logistic map is
    not chaotic (every start in ``(0, 1)`` converges to the fixed point 1/2), so the
    "chaotic" sequence would collapse. ``mu = 4`` is the fully chaotic value and is the default;
    ``mu`` is an option.

    **Initialisation.** A start vector ``s_0`` of ``k`` components is drawn uniform in ``(0, 1)``
    from the solver's generator (the first draw of the run), moved off the non-chaotic points by
    :func:`avoid_fixed_points`, and iterated ``2P`` times (:func:`logistic_sequence`). Iterates
    ``s_1 .. s_P`` give the positions ``x_i = lower + s_i (upper - lower)``; iterates
    ``s_{P+1} .. s_{2P}`` give the velocities ``v_i = (2 s_{P+i} - 1) v_max (upper - lower)``.
    When the problem has ``x0``, particle 0 is replaced by ``x0`` (clipped), as in :class:`PSO`.
    ``Result.extra["chaos_start"]`` is ``s_0`` after the adjustment.

    **Each iteration** runs the PSO update (inertia ``w`` linear ``0.9 -> 0.2`` by default),
    evaluates the swarm and updates the bests, then:

    1. maps ``gbest`` to ``z = (gbest - lower) / (upper - lower)`` in ``[0, 1]`` (adjusted by
       :func:`avoid_fixed_points`: a best at the centre or a bound would otherwise give a
       constant sequence), and iterates the logistic map ``n_chaos`` times from it;
    2. maps the iterates back onto the bounds and evaluates them in one batch;
    3. the best chaotic point replaces the position of a particle chosen uniformly at random
       (its velocity is kept; its personal best is updated if the point is better), and becomes
       the global best if it is better.

    So ``n_evals = P + max_iter (P + n_chaos)``.

    **Chaos radius.** The seed's sequence (``chaos_radius=None``, default) is the plain logistic
    sequence started at the mapped gbest: after a few iterates it wanders over the whole range,
    so it is a global chaotic probe that only starts at gbest, not a local search near it.
    ``chaos_radius=r`` (a fraction of the bound range) instead uses the iterates as offsets in a
    neighbourhood of gbest, ``x = gbest + r (2 s_j - 1)(upper - lower)``, clipped to the bounds,
    which turns the step into a local refinement around the best point.

    Args:
        pop_size, max_iter, c1, c2, v_max: as in :class:`PSO`; defaults are seed 001's settings
            (population 200, 200 iterations, c1 1.3, c2 1.8).
        w: inertia, default ``(0.9, 0.2)`` = linear decrease from 0.9 to 0.2 (seed 001).
        n_chaos: chaotic points evaluated per iteration (default 10; 0 disables the search).
        chaos_radius: ``None`` for the seed's full-range sequence, else the neighbourhood
            half-width as a fraction of the bound range.
        mu: logistic-map parameter (default 4, the chaotic value; see above).
        seed, progress, callback: see :class:`~torchcal.optim.Solver`.
    """

    name = "cpso"
    aliases = ("chaotic-pso",)
    batched = False  # the chaotic search follows one global best

    def __init__(self, settings: CPSOOptions | None = None, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None, **options):
        o = CPSOOptions.build(settings, **options)
        super().__init__(PSOOptions(pop_size=o.pop_size, max_iter=o.max_iter, w=o.w, c1=o.c1, c2=o.c2, v_max=o.v_max),
                         seed=seed, progress=progress, callback=callback)
        self.settings = o
        n_chaos, chaos_radius, mu = o.n_chaos, o.chaos_radius, o.mu
        if int(n_chaos) < 0:
            raise ValueError(f"n_chaos must be >= 0, got {n_chaos}")
        if chaos_radius is not None and not chaos_radius > 0:
            raise ValueError(f"chaos_radius must be positive or None, got {chaos_radius}")
        self.n_chaos = int(n_chaos)
        self.chaos_radius = None if chaos_radius is None else float(chaos_radius)
        self.mu = float(mu)
        self._chaos_start: Tensor | None = None

    def _init_positions(self, problem: Problem, g: torch.Generator, vlim: Tensor) -> tuple[Tensor, Tensor]:
        P, k = self.pop_size, problem.dim
        s0 = avoid_fixed_points(torch.rand(k, generator=g, dtype=problem.dtype, device=problem.device))
        self._chaos_start = s0
        seq = logistic_sequence(s0, 2 * P, self.mu)  # (2P, k)
        X = problem.lower + seq[:P] * (problem.upper - problem.lower)
        V = (2.0 * seq[P:] - 1.0) * vlim
        return X, V

    def _chaos_points(self, gbest: Tensor, problem: Problem) -> Tensor:
        """``(n_chaos, k)`` chaotic points from the mapped global best (see class docstring)."""
        lo, span = problem.lower, problem.upper - problem.lower
        # Degenerate (zero-width) parameters map to 0 rather than NaN.
        z = torch.where(span > 0, (gbest - lo) / torch.where(span > 0, span, torch.ones_like(span)),
                        torch.zeros_like(span))
        seq = logistic_sequence(avoid_fixed_points(z.clamp(0.0, 1.0)), self.n_chaos, self.mu)
        if self.chaos_radius is None:
            return lo + seq * span
        return problem.clip(gbest + self.chaos_radius * (2.0 * seq - 1.0) * span)

    def _after_step(self, t: int, s: SwarmState, problem: Problem, g: torch.Generator) -> None:
        if self.n_chaos == 0:
            return
        C = self._chaos_points(s.gbest, problem)
        fc = self._evaluate(problem, C)
        s.n_evals += self.n_chaos
        b = torch.argmin(fc)
        c, c_f = C[b], fc[b]
        # Random particle index as a 1-element tensor: no host sync, and index_copy_ uses it.
        # Every update is in place: the state's tensors are views of the swarm's buffers.
        j = torch.randint(s.size, (1,), generator=g, device=problem.device)
        s.X.index_copy_(0, j, c[None])
        better = c_f < s.pbest_f.index_select(0, j)  # (1,)
        s.pbest.index_copy_(0, j, torch.where(better[:, None], c[None], s.pbest.index_select(0, j)))
        s.pbest_f.index_copy_(0, j, torch.where(better, c_f[None], s.pbest_f.index_select(0, j)))
        gb = c_f < s.gbest_f
        torch.where(gb, c, s.gbest, out=s.gbest)
        torch.where(gb, c_f, s.gbest_f, out=s.gbest_f)

    def _extra(self, s: SwarmState) -> dict:
        return {"chaos_start": self._chaos_start, "n_chaos": self.n_chaos,
                "chaos_radius": self.chaos_radius, "mu": self.mu}
