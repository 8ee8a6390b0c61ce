"""The modified mayfly algorithm (MMA, seed 002): the mayfly swarm with an improved tent-map
initial population and Cauchy mutation of the best mayflies."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import evaluate
from torchcal.optim.mayfly import Mayfly, MayflyState, best_rows
from torchcal.optim.result import Result
from torchcal.problems.base import Problem

__all__ = ["ModifiedMayfly", "improved_tent_map"]


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
        f = evaluate(problem, X)
        fm, Xm = best_rows(n, f[: 2 * n], X[: 2 * n])
        ff, Xf = best_rows(n, f[2 * n:], X[2 * n:])
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
        fy = evaluate(problem, Y)
        s.n_evals += m
        f2, X2, male2 = best_rows(n_off, torch.cat((f, fy)), torch.cat((X, Y)),
                              torch.cat((male, male[pick])))
        return X2, f2, male2
