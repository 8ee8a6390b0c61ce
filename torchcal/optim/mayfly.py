"""Mayfly algorithm (Zervoudakis & Tsafarakis 2020) and seed 002's modified mayfly algorithm.

Both solvers are vectorised over the population: one Python loop over generations, every
per-mayfly operation is a tensor op on ``(n, k)`` positions / velocities (``n`` males, ``n``
females, ``k`` parameters). Random numbers come only from the solver's seeded generator
(:meth:`Solver.generator`), so a run is bit-reproducible for a given seed, dtype and device and
never touches global RNG state.

Shapes: males ``Xm, Vm, Pm`` (positions, velocities, personal bests) ``(n, k)`` with fitness
``fm, pf`` ``(n,)``; females ``Xf, Vf`` ``(n, k)`` with fitness ``ff`` ``(n,)``; offspring
``(n_off, k)``; the global best ``gx`` ``(k,)`` with fitness ``gf`` (0-d tensor).
"""
from __future__ import annotations

from dataclasses import astuple, dataclass
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import IterativeSolver, evaluate
from torchcal.optim.result import Result
from torchcal.optim.swarm_options import MayflyOptions
from torchcal.problems.base import Problem

__all__ = ["Mayfly", "MayflyState", "best_rows", "sorted_rows"]


@dataclass
class MayflyState:
    """Mutable state of a mayfly swarm (tensors on the problem's dtype/device).

    Attributes:
        Xm, Vm: ``(n, k)`` male positions and velocities; fm ``(n,)`` their fitness.
        Pm: ``(n, k)`` male personal bests; pf ``(n,)`` their fitness.
        Xf, Vf: ``(n, k)`` female positions and velocities; ff ``(n,)`` their fitness.
        gx: ``(k,)`` best point ever evaluated; gf: 0-d tensor, its fitness.
        n_evals: points evaluated so far (a host int: sizes are known, so no device sync).
    """

    Xm: Tensor
    Vm: Tensor
    fm: Tensor
    Pm: Tensor
    pf: Tensor
    Xf: Tensor
    Vf: Tensor
    ff: Tensor
    gx: Tensor
    gf: Tensor
    n_evals: int = 0

    @property
    def best(self) -> Tensor:
        """The best fitness so far (what the engine records)."""
        return self.gf

    def offer(self, X: Tensor, f: Tensor) -> None:
        """Update the global best from candidates ``X (N, k)``, ``f (N,)`` (no host sync).

        Strict ``<`` keeps the older point on ties."""
        if f.numel() == 0:
            return
        j = torch.argmin(f)
        better = f[j] < self.gf
        self.gx = torch.where(better, X[j], self.gx)
        self.gf = torch.where(better, f[j], self.gf)


def sorted_rows(f: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """Sort ``f`` ascending (stable, so ties keep their order: deterministic) and reorder the
    other ``(n, ...)`` tensors the same way."""
    order = torch.argsort(f, stable=True)
    return (f[order], *(t[order] for t in tensors))


def best_rows(n: int, f: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """The ``n`` fittest rows, sorted best first."""
    out = sorted_rows(f, *tensors)
    return tuple(t[:n] for t in out)


@register
class Mayfly(IterativeSolver):
    """Mayfly algorithm (MA), Zervoudakis & Tsafarakis (2020), as described in seed 002.

    ``n = pop_size`` males and ``n`` females. Each generation (every mayfly of a sex at once):

    1. **Females** move towards the male of the same rank when that male is fitter,
       ``v = g v + a3 e^{-beta r_mf^2} (x_male - x_female)``, else fly at random,
       ``v = g v + fl r``, ``r ~ U(-1, 1)``; then they are evaluated.
    2. **Males** that are not the global best move towards their personal best and the global
       best, ``v = g v + a1 e^{-beta r_p^2}(pbest - x) + a2 e^{-beta r_g^2}(gbest - x)``; the best
       male (the one holding the global best, i.e. ``f(x) <= f(gbest)`` as in the authors' code)
       does the nuptial dance ``v = g v + d r``. Then they are evaluated and personal bests updated.
    3. Both sexes are ranked; the ``n_off / 2`` best pairs (male ``i`` with female ``i``) mate:
       per gene ``L ~ U(0, 1)``, ``off1 = L male + (1 - L) female`` (a male child),
       ``off2 = L female + (1 - L) male`` (a female child); offspring start with velocity 0 and
       are evaluated.
    4. **Replacement**: males pool with the male offspring and the ``n`` fittest stay, the same
       for females (the authors' code); new males' personal best is their position.
    5. ``g *= g_damp``, ``d *= d_damp``, ``fl *= fl_damp``.

    Velocities are clamped to ``v_max (upper - lower)`` and positions clipped to the bounds.
    Updates within a sex are synchronous (the authors' code moves mayflies one after another and
    updates the global best in between; here the global best is updated after each batch).

    **Units.** The distances in the attraction terms are per component (``r^2`` element-wise,
    as in the authors' code, not the Cartesian distance of the paper's text: in 300 dimensions
    ``e^{-beta |x - y|^2}`` underflows to 0 and the swarm would stop attracting) and measured in
    units of each parameter's range; ``d``, ``fl`` and ``v_max`` are fractions of each
    parameter's range. So one setting works for parameters in mm and rad alike (the seeds' problems
    mix them); on seed 002's ELM bounds ``[-1, 1]`` the range is 2.

    **Defaults** (the patent gives no values, so these are the usual ones): ``g = 0.8`` with
    ``g_damp = 1``, ``a1 = 1``, ``a2 = a3 = 1.5``, ``beta = 2``, ``d = fl = 0.1``,
    ``d_damp = fl_damp = 0.99``, ``v_max = 0.1``, ``pop_size = 20`` males and as many females
    (the authors' code), ``n_off = pop_size``. The authors' code also mutates
    ``round(0.05 n)`` offspring by a small uniform jump; the patent's description of MA does not,
    and seed 002's MMA replaces it by its Cauchy mutation, so :class:`Mayfly` has none.

    **Start point.** Male 0 starts at ``problem.x0`` (clipped) when the problem has one; every
    other mayfly is uniform in the bounds. The result is never worse than ``x0``.

    Args:
        pop_size: males ``n`` (= females).
        max_iter: generations (not given by the seeds; default 200).
        n_off: offspring per generation (even, at most ``2 n``); ``None`` = ``pop_size`` (rounded
            up to even).
        g, g_damp, a1, a2, a3, beta, d, d_damp, fl, fl_damp, v_max: see above.
        seed, progress, callback: see :class:`Solver`. ``callback(it, best)`` is called after
            initialisation (``it = 0``) and after each generation.

    Result: ``x`` the best point ever evaluated, ``history`` the best fitness after
    initialisation and each generation (``max_iter + 1`` floats), ``n_evals = 2 n +
    max_iter (2 n + n_off)``. NaN fitness counts as ``+inf``.
    """

    name = "ma"
    population = True
    aliases = ("mayfly",)

    def __init__(self, settings: MayflyOptions | None = None, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None, **options):
        self.settings = MayflyOptions.build(settings, **options)
        pop_size, max_iter, n_off, g, g_damp, a1, a2, a3, beta, d, d_damp, fl, fl_damp, v_max = astuple(self.settings)
        super().__init__(seed=seed, progress=progress, callback=callback)
        pop_size = int(pop_size)
        n_off = pop_size + pop_size % 2 if n_off is None else int(n_off)
        if pop_size < 1 or int(max_iter) < 0:
            raise ValueError(f"need pop_size >= 1 and max_iter >= 0, got {pop_size}, {max_iter}")
        if n_off < 0 or n_off % 2 or n_off > 2 * pop_size:
            raise ValueError(f"n_off must be even and in [0, 2 pop_size] (one pair gives two "
                             f"offspring), got {n_off}")
        if not v_max > 0:
            raise ValueError(f"v_max must be positive, got {v_max}")
        self.pop_size = pop_size
        self.max_iter = int(max_iter)
        self.n_off = n_off
        self.g, self.g_damp = float(g), float(g_damp)
        self.a1, self.a2, self.a3, self.beta = float(a1), float(a2), float(a3), float(beta)
        self.d, self.d_damp = float(d), float(d_damp)
        self.fl, self.fl_damp = float(fl), float(fl_damp)
        self.v_max = float(v_max)

    # -- counts ---------------------------------------------------------------------------------
    def evals_per_generation(self) -> int:
        """Points evaluated per generation: females, males and offspring."""
        return 2 * self.pop_size + self.n_off

    # -- hooks (ModifiedMayfly overrides these) ---------------------------------------------------
    def initial_population(self, problem: Problem, g: torch.Generator | None = None
                           ) -> MayflyState:
        """Evaluated initial swarm, both sexes sorted best first (pairs are by rank).

        Uniform in the bounds; male 0 is ``problem.x0`` when given. ``g`` defaults to a fresh
        :meth:`generator` (the run passes its own).
        """
        g = self.generator(problem) if g is None else g
        n, k = self.pop_size, problem.dim
        lo, span = problem.lower, problem.upper - problem.lower
        X = lo + torch.rand((2 * n, k), generator=g, dtype=problem.dtype, device=problem.device) * span
        if problem.x0 is not None:
            X[0] = problem.x0
        X = problem.clip(X)  # also catches lo + u*span overshooting hi by a rounding step
        f = evaluate(problem, X)
        return self._state(X[:n], f[:n], X[n:], f[n:], n_evals=2 * n)

    @staticmethod
    def _state(Xm: Tensor, fm: Tensor, Xf: Tensor, ff: Tensor, n_evals: int) -> MayflyState:
        fm, Xm = sorted_rows(fm, Xm)
        ff, Xf = sorted_rows(ff, Xf)
        s = MayflyState(Xm=Xm, Vm=torch.zeros_like(Xm), fm=fm, Pm=Xm.clone(), pf=fm.clone(),
                        Xf=Xf, Vf=torch.zeros_like(Xf), ff=ff, gx=Xm[0].clone(), gf=fm[0].clone(),
                        n_evals=n_evals)
        s.offer(Xf, ff)
        return s

    def offspring(self, problem: Problem, s: MayflyState, g: torch.Generator
                  ) -> tuple[Tensor, Tensor, Tensor]:
        """Mating of the ``n_off / 2`` best ranked pairs (both sexes sorted best first).

        Returns ``(X (n_off, k), f (n_off,), is_male (n_off,) bool)``: the first half are the
        male children ``L male + (1 - L) female``, the second half the female children. Adds the
        evaluations to ``s.n_evals``.
        """
        h = self.n_off // 2
        M, Fe = s.Xm[:h], s.Xf[:h]
        L = torch.rand(M.shape, generator=g, dtype=M.dtype, device=M.device)
        # Convex combinations stay in the box; clip only guards against rounding.
        X = problem.clip(torch.cat((L * M + (1.0 - L) * Fe, L * Fe + (1.0 - L) * M), 0))
        f = evaluate(problem, X)
        s.n_evals += 2 * h
        is_male = torch.arange(2 * h, device=X.device) < h
        return X, f, is_male

    # -- the run (steps of the engine) --------------------------------------------------------
    def init(self, problem: Problem, gen: torch.Generator) -> MayflyState:
        problem.require_finite_bounds(self.name)
        s = self.initial_population(problem, gen)
        span = problem.upper - problem.lower
        # Distances are measured in units of the range; a zero range (fixed parameter) gets
        # unit scale so nothing divides by zero (its distances are 0 anyway).
        s.span, s.inv_span = span, 1.0 / torch.where(span > 0, span, torch.ones_like(span))
        s.vlim = self.v_max * span
        s.g, s.d, s.fl = self.g, self.d, self.fl  # damped every generation
        return s

    @staticmethod
    def _move(problem: Problem, s: MayflyState, X: Tensor, V: Tensor) -> tuple[Tensor, Tensor]:
        V = torch.maximum(torch.minimum(V, s.vlim), -s.vlim)
        return problem.clip(X + V), V

    def step(self, problem: Problem, s: MayflyState, t: int, gen: torch.Generator) -> None:
        n, span, inv_span = self.pop_size, s.span, s.inv_span
        r = torch.rand((2, n, problem.dim), generator=gen, dtype=problem.dtype, device=problem.device) * 2.0 - 1.0

        # 1. Females: towards the same-rank male when he is fitter, else a random flight.
        diff = s.Xm - s.Xf
        attract = (s.ff > s.fm)[:, None]
        Vf = s.g * s.Vf + torch.where(
            attract, self.a3 * torch.exp(-self.beta * (diff * inv_span) ** 2) * diff,
            s.fl * span * r[0])
        s.Xf, s.Vf = self._move(problem, s, s.Xf, Vf)
        s.ff = evaluate(problem, s.Xf)
        s.offer(s.Xf, s.ff)

        # 2. Males: pbest/gbest attraction; the one at the global best dances.
        dp, dg = s.Pm - s.Xm, s.gx - s.Xm
        dance = (s.fm <= s.gf)[:, None]
        Vm = s.g * s.Vm + torch.where(
            dance, s.d * span * r[1],
            self.a1 * torch.exp(-self.beta * (dp * inv_span) ** 2) * dp
            + self.a2 * torch.exp(-self.beta * (dg * inv_span) ** 2) * dg)
        s.Xm, s.Vm = self._move(problem, s, s.Xm, Vm)
        s.fm = evaluate(problem, s.Xm)
        s.n_evals += 2 * n
        better = s.fm < s.pf
        s.Pm = torch.where(better[:, None], s.Xm, s.Pm)
        s.pf = torch.where(better, s.fm, s.pf)
        s.offer(s.Xm, s.fm)

        # 3. Rank both sexes, then mate the best pairs.
        s.fm, s.Xm, s.Vm, s.Pm, s.pf = sorted_rows(s.fm, s.Xm, s.Vm, s.Pm, s.pf)
        s.ff, s.Xf, s.Vf = sorted_rows(s.ff, s.Xf, s.Vf)
        Xo, fo, male = self.offspring(problem, s, gen)
        s.offer(Xo, fo)

        # 4. Each sex pools with its offspring (velocity 0, pbest = position); best n stay.
        Xom, fom = Xo[male], fo[male]
        Xof, fof = Xo[~male], fo[~male]
        s.fm, s.Xm, s.Vm, s.Pm, s.pf = best_rows(
            n, torch.cat((s.fm, fom)), torch.cat((s.Xm, Xom)),
            torch.cat((s.Vm, torch.zeros_like(Xom))), torch.cat((s.Pm, Xom)),
            torch.cat((s.pf, fom)))
        s.ff, s.Xf, s.Vf = best_rows(n, torch.cat((s.ff, fof)), torch.cat((s.Xf, Xof)),
                                 torch.cat((s.Vf, torch.zeros_like(Xof))))

        # 5. Damping.
        s.g *= self.g_damp
        s.d *= self.d_damp
        s.fl *= self.fl_damp
        return None

    def finish(self, problem: Problem, s: MayflyState) -> tuple[Tensor, float, dict]:
        return s.gx.clone(), float(s.gf), {"g": s.g, "d": s.d, "fl": s.fl}


