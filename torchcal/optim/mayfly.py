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

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import Solver, register
from torchcal.optim.ga import _evaluate, _Reporter
from torchcal.problems.base import Problem
from torchcal.optim.result import Result

__all__ = ["Mayfly", "ModifiedMayfly", "MayflyState", "improved_tent_map"]


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

    def offer(self, X: Tensor, f: Tensor) -> None:
        """Update the global best from candidates ``X (N, k)``, ``f (N,)`` (no host sync).

        Strict ``<`` keeps the older point on ties."""
        if f.numel() == 0:
            return
        j = torch.argmin(f)
        better = f[j] < self.gf
        self.gx = torch.where(better, X[j], self.gx)
        self.gf = torch.where(better, f[j], self.gf)


def _sorted(f: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """Sort ``f`` ascending (stable, so ties keep their order: deterministic) and reorder the
    other ``(n, ...)`` tensors the same way."""
    order = torch.argsort(f, stable=True)
    return (f[order], *(t[order] for t in tensors))


def _best(n: int, f: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
    """The ``n`` fittest rows, sorted best first."""
    out = _sorted(f, *tensors)
    return tuple(t[:n] for t in out)


def improved_tent_map(z0: Tensor, noise: Tensor, a: float = 0.5) -> Tensor:
    """Iterate the improved tent map from ``z0``: ``(k,)``, ``noise (n, k)`` -> ``(n, k)``.

    ::

        z_{i+1} = ( z_i / a            + noise_i )  mod 1    if z_i <  a
        z_{i+1} = ( (1 - z_i)/(1 - a)  + noise_i )  mod 1    if z_i >= a

    Row ``i`` of the result is ``z_{i+1}``. Each of the ``k`` components is an independent chain.
    ``noise`` is the small random term that breaks the plain tent map's short and unstable
    cycles (with ``a = 0.5`` in binary floating point, ``2 z`` shifts one mantissa bit out per
    step and every orbit collapses to 0 within ~53 steps); the usual choice, used by
    :class:`ModifiedMayfly`, is ``noise ~ U(0, 1) / N`` with ``N`` the length of the sequence.

    The recurrence is inherently sequential, so this loops over the ``n`` steps (vectorised over
    the ``k`` chains); it runs once per optimisation, at initialisation.
    """
    if not 0.0 < a < 1.0:
        raise ValueError(f"tent parameter a must be in (0, 1), got {a}")
    out = torch.empty_like(noise)
    z = z0
    for i in range(noise.shape[0]):
        z = torch.where(z < a, z / a, (1.0 - z) / (1.0 - a)) + noise[i]
        z = torch.remainder(z, 1.0)
        out[i] = z
    return out


@register
class Mayfly(Solver):
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
    aliases = ("mayfly",)

    def __init__(self, *, pop_size: int = 20, max_iter: int = 200, n_off: int | None = None,
                 g: float = 0.8, g_damp: float = 1.0, a1: float = 1.0, a2: float = 1.5,
                 a3: float = 1.5, beta: float = 2.0, d: float = 0.1, d_damp: float = 0.99,
                 fl: float = 0.1, fl_damp: float = 0.99, v_max: float = 0.1,
                 seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None):
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
        f = _evaluate(problem, X)
        return self._state(X[:n], f[:n], X[n:], f[n:], n_evals=2 * n)

    @staticmethod
    def _state(Xm: Tensor, fm: Tensor, Xf: Tensor, ff: Tensor, n_evals: int) -> MayflyState:
        fm, Xm = _sorted(fm, Xm)
        ff, Xf = _sorted(ff, Xf)
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
        f = _evaluate(problem, X)
        s.n_evals += 2 * h
        is_male = torch.arange(2 * h, device=X.device) < h
        return X, f, is_male

    # -- the run --------------------------------------------------------------------------------
    def _run(self, problem: Problem) -> Result:
        problem.require_finite_bounds(self.name)
        gen = self.generator(problem)
        dt, dev = problem.dtype, problem.device
        lo, hi = problem.lower, problem.upper
        span = hi - lo
        # Distances are measured in units of the range; a zero range (fixed parameter) gets
        # unit scale so nothing divides by zero (its distances are 0 anyway).
        inv_span = 1.0 / torch.where(span > 0, span, torch.ones_like(span))
        vlim = self.v_max * span
        n = self.pop_size
        g, d, fl = self.g, self.d, self.fl

        s = self.initial_population(problem, gen)
        rep = _Reporter(self, self.max_iter, problem)
        rep(0, s.gf)

        def move(X: Tensor, V: Tensor) -> tuple[Tensor, Tensor]:
            V = torch.maximum(torch.minimum(V, vlim), -vlim)
            return problem.clip(X + V), V

        for t in range(1, self.max_iter + 1):
            r = torch.rand((2, n, problem.dim), generator=gen, dtype=dt, device=dev) * 2.0 - 1.0

            # 1. Females: towards the same-rank male when he is fitter, else a random flight.
            diff = s.Xm - s.Xf
            attract = (s.ff > s.fm)[:, None]
            Vf = g * s.Vf + torch.where(
                attract, self.a3 * torch.exp(-self.beta * (diff * inv_span) ** 2) * diff,
                fl * span * r[0])
            s.Xf, s.Vf = move(s.Xf, Vf)
            s.ff = _evaluate(problem, s.Xf)
            s.offer(s.Xf, s.ff)

            # 2. Males: pbest/gbest attraction; the one at the global best dances.
            dp, dg = s.Pm - s.Xm, s.gx - s.Xm
            dance = (s.fm <= s.gf)[:, None]
            Vm = g * s.Vm + torch.where(
                dance, d * span * r[1],
                self.a1 * torch.exp(-self.beta * (dp * inv_span) ** 2) * dp
                + self.a2 * torch.exp(-self.beta * (dg * inv_span) ** 2) * dg)
            s.Xm, s.Vm = move(s.Xm, Vm)
            s.fm = _evaluate(problem, s.Xm)
            s.n_evals += 2 * n
            better = s.fm < s.pf
            s.Pm = torch.where(better[:, None], s.Xm, s.Pm)
            s.pf = torch.where(better, s.fm, s.pf)
            s.offer(s.Xm, s.fm)

            # 3. Rank both sexes, then mate the best pairs.
            s.fm, s.Xm, s.Vm, s.Pm, s.pf = _sorted(s.fm, s.Xm, s.Vm, s.Pm, s.pf)
            s.ff, s.Xf, s.Vf = _sorted(s.ff, s.Xf, s.Vf)
            Xo, fo, male = self.offspring(problem, s, gen)
            s.offer(Xo, fo)

            # 4. Each sex pools with its offspring (velocity 0, pbest = position); best n stay.
            Xom, fom = Xo[male], fo[male]
            Xof, fof = Xo[~male], fo[~male]
            s.fm, s.Xm, s.Vm, s.Pm, s.pf = _best(
                n, torch.cat((s.fm, fom)), torch.cat((s.Xm, Xom)),
                torch.cat((s.Vm, torch.zeros_like(Xom))), torch.cat((s.Pm, Xom)),
                torch.cat((s.pf, fom)))
            s.ff, s.Xf, s.Vf = _best(n, torch.cat((s.ff, fof)), torch.cat((s.Xf, Xof)),
                                     torch.cat((s.Vf, torch.zeros_like(Xof))))

            # 5. Damping.
            g *= self.g_damp
            d *= self.d_damp
            fl *= self.fl_damp
            rep(t, s.gf)

        hist = rep.close()
        return Result(x=s.gx.clone(), fun=float(s.gf), history=hist, n_evals=s.n_evals,
                      n_iter=self.max_iter, converged=False,
                      message=f"reached max_iter={self.max_iter}",
                      extra={"g": g, "d": d, "fl": fl})


@register
class ModifiedMayfly(Mayfly):
    """Modified mayfly algorithm (MMA) of seed 002: the :class:`Mayfly` loop with two changes.

    1. **Initialisation by an improved tent map and opposition-based learning.** One chaotic
       sequence of ``2 n`` points (:func:`improved_tent_map`, ``a = tent_a = 0.5`` as the patent
       suggests, random term ``U(0, 1) / (2 n)``, each of the ``k`` components its own chain
       started at ``U(0, 1)``) is mapped onto the bounds, ``x = x_min + (x_max - x_min) z``
       (patent eq. 15): the first ``n`` points are male candidates, the next ``n`` female ones.
       Each candidate's opposite ``x_min + x_max - x`` (eq. 16) is evaluated too, and each sex
       keeps the fittest ``n`` of its ``2 n`` candidates and opposites. The exact form of the
       patent's eq. 14 was lost in extraction; the random term ``rand(0,1)/N`` is the usual
       "improved tent map" (Zhang et al.), and ``N`` = the sequence length.
    2. **Cauchy mutation of the offspring.** After mating, ``n_mut = round(cauchy_share n_off)``
       offspring chosen at random (without replacement) are copied and mutated,
       ``x' = x + x * C``, ``C ~ Cauchy(0, 1)`` per component (patent eq. 18), clipped to the
       bounds and evaluated; the mutants (of the parent's sex) join the offspring and the fittest
       ``n_off`` of the ``n_off + n_mut`` go on to the replacement step. Note that the jump is
       relative to ``x``: a component at 0 does not move. The patent gives no share; the default
       0.2 mutates a few offspring per generation (4 of 20).

    **Start point.** When the problem has ``x0`` it replaces the first male candidate (its
    opposite is evaluated too) and stays in the initial male population even if it is not
    among the fittest ``n`` (it then replaces the worst kept male).

    Args: those of :class:`Mayfly`, plus
        tent_a: the tent map's ``a4`` (patent: 0.5).
        cauchy_share: share of the offspring that is Cauchy-mutated.

    Result: as :class:`Mayfly`, with ``n_evals = 4 n + max_iter (2 n + n_off + n_mut)``.
    """

    name = "mma"
    aliases = ("modified-mayfly",)

    def __init__(self, *, tent_a: float = 0.5, cauchy_share: float = 0.2, **kwargs):
        super().__init__(**kwargs)
        if not 0.0 < float(tent_a) < 1.0:
            raise ValueError(f"tent_a must be in (0, 1), got {tent_a}")
        if not 0.0 <= float(cauchy_share) <= 1.0:
            raise ValueError(f"cauchy_share must be in [0, 1], got {cauchy_share}")
        self.tent_a = float(tent_a)
        self.cauchy_share = float(cauchy_share)

    @property
    def n_mut(self) -> int:
        """Offspring Cauchy-mutated per generation: ``round(cauchy_share n_off)`` (half up)."""
        return int(math.floor(self.cauchy_share * self.n_off + 0.5))

    def evals_per_generation(self) -> int:
        return super().evals_per_generation() + self.n_mut

    def initial_population(self, problem: Problem, g: torch.Generator | None = None
                           ) -> MayflyState:
        """Tent-map candidates plus their opposites; each sex keeps its fittest ``n``.

        Evaluates ``4 n`` points in one batch: rows ``[male candidates, male opposites, female
        candidates, female opposites]``, ``n`` each.
        """
        g = self.generator(problem) if g is None else g
        n, k = self.pop_size, problem.dim
        dt, dev = problem.dtype, problem.device
        lo, hi = problem.lower, problem.upper
        z0 = torch.rand(k, generator=g, dtype=dt, device=dev)
        noise = torch.rand((2 * n, k), generator=g, dtype=dt, device=dev) / (2 * n)
        Z = improved_tent_map(z0, noise, self.tent_a)
        C = lo + (hi - lo) * Z
        if problem.x0 is not None:
            C[0] = problem.x0
        C = problem.clip(C)
        Cm, Cf = C[:n], C[n:]
        # Opposites lo + hi - x are inside the box by symmetry; clip guards rounding.
        X = problem.clip(torch.cat((Cm, lo + hi - Cm, Cf, lo + hi - Cf), 0))
        f = _evaluate(problem, X)
        fm, Xm = _best(n, f[: 2 * n], X[: 2 * n])
        ff, Xf = _best(n, f[2 * n:], X[2 * n:])
        if problem.x0 is not None:
            # Keep the user's start: if it did not make the cut, it replaces the worst male.
            kept = (Xm == X[0]).all(1).any()
            Xm[-1] = torch.where(kept, Xm[-1], X[0])
            fm[-1] = torch.where(kept, fm[-1], f[0])
        return self._state(Xm, fm, Xf, ff, n_evals=4 * n)

    def offspring(self, problem: Problem, s: MayflyState, g: torch.Generator
                  ) -> tuple[Tensor, Tensor, Tensor]:
        X, f, male = super().offspring(problem, s, g)
        return self.cauchy_mutation(problem, s, X, f, male, g)

    def cauchy_mutation(self, problem: Problem, s: MayflyState, X: Tensor, f: Tensor,
                        male: Tensor, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """Mutate ``n_mut`` random offspring by ``x + x C`` and keep the fittest ``n_off``.

        ``X (n_off, k)``, ``f (n_off,)``, ``male (n_off,)`` -> the same shapes, sorted best
        first. Adds ``n_mut`` to ``s.n_evals``.
        """
        m, n_off = self.n_mut, X.shape[0]
        if m == 0 or n_off == 0:
            return X, f, male
        pick = torch.argsort(torch.rand(n_off, generator=g, dtype=X.dtype, device=X.device))[:m]
        u = torch.rand((m, X.shape[1]), generator=g, dtype=X.dtype, device=X.device)
        # Standard Cauchy by inversion; u = 0 would give tan(-pi/2) = -huge, clipped anyway.
        cauchy = torch.tan(math.pi * (u - 0.5))
        Y = problem.clip(X[pick] + X[pick] * cauchy)
        fy = _evaluate(problem, Y)
        s.n_evals += m
        f2, X2, male2 = _best(n_off, torch.cat((f, fy)), torch.cat((X, Y)),
                              torch.cat((male, male[pick])))
        return X2, f2, male2
