"""Real-coded genetic algorithm (seed 004's calibration GA; seed 001's excitation-design GA).

Everything is vectorised over the population: the only Python loop is over generations, and
every per-individual operation is a tensor op on a ``(I, S, k)`` population (``I`` islands of
``S`` individuals, ``k`` parameters). Random numbers come only from the solver's seeded
generator (:meth:`Solver.generator`), so a run is bit-reproducible for a given seed, dtype and
device and never touches global RNG state.

Both seeds ran MATLAB's Global Optimization Toolbox ``ga``; the operators below follow that
toolbox where the seeds name one of its options (stochastic-uniform selection, linear fitness
scaling, island migration) and the usual real-coded GA operators where they do not.
"""
from __future__ import annotations

import math
from dataclasses import astuple
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from torchcal.optim.base import register
from torchcal.optim.engine import IterativeSolver, evaluate
from torchcal.optim.result import Result
from torchcal.optim.swarm_options import GAOptions
from torchcal.problems.base import Problem

__all__ = ["GeneticAlgorithm"]


@register
class GeneticAlgorithm(IterativeSolver):
    """Real-coded genetic algorithm with elitism and island migration.

    One generation, on every island at once (shapes ``(I, S, k)``; ``I = n_islands``,
    ``S = pop_size / n_islands``):

    1. **Elitism**: the ``n_elite`` best of each island pass unchanged.
    2. **Selection** of ``S - n_elite`` parents (rounded up to an even number) per island:

       * ``"sus"`` (default, seed 004): stochastic universal sampling ("随机均匀分布" = MATLAB's
         *stochastic uniform* selection) on linearly scaled fitness ("线性转换" = MATLAB's *shift
         linear* scaling): expectation ``e_i = 1 + (rate - 1)(mean f - f_i)/(mean f - min f)``,
         clipped at 0, so the best gets ``rate = 2`` expected copies and the mean 1. SUS has the
         lowest sampling noise of the fitness-proportional schemes. The parents are shuffled
         before pairing (as MATLAB does), since SUS returns them in index order.
       * ``"tournament"``: binary tournaments. Invariant to any monotone change of the fitness,
         so one huge outlier (e.g. a diverged ELM) cannot flatten the selection pressure as it
         can with linear scaling; use it when fitness values span many orders of magnitude.

    3. **Crossover**: each consecutive parent pair crosses with probability ``p_crossover``
       (otherwise the children are copies of the parents) by blend crossover BLX-``alpha``:
       per gene ``a ~ U(-alpha, 1 + alpha)``, ``c1 = a p1 + (1 - a) p2``,
       ``c2 = a p2 + (1 - a) p1``. ``alpha = 0`` is plain arithmetic (intermediate) crossover;
       the default ``0.3`` lets children leave the parents' box a little, which offsets the
       variance loss of averaging.
    4. **Mutation**: each gene of each child mutates with probability ``p_mutation`` by a
       Gaussian step ``N(0, sigma_t^2)``, ``sigma_t = mutation_scale (upper - lower)
       (1 - shrink (t - 1)/max_iter)`` (MATLAB's ``mutationgaussian`` schedule: wide steps first,
       fine steps to finish). Children are clipped to the bounds and evaluated.
    5. **Migration** (every ``migration_interval`` generations, when ``n_islands > 1``): the
       ``floor(migration S)`` best individuals of island ``i`` replace the as many worst of island
       ``i + 1`` (a ring; MATLAB's ``'forward'`` direction). Migrants carry their fitness, so
       migration costs no evaluations.

    **How "migration" is read.** Seed 004 tunes a "迁移概率" (migration probability) ``P_m = 0.7``
    next to the crossover probability 0.8 in MATLAB's GA toolbox; there, ``MigrationFraction`` is
    the share of a subpopulation that moves to the next subpopulation every
    ``MigrationInterval`` (default 20) generations. It only acts when the population is split
    into subpopulations; with one population of 30 (as the paper reports) it does nothing, which
    fits the paper's sweep (Table 4: the fitness moves only between 0.5112 and 0.5115 over
    ``P_m = 0.1 ... 1``). We therefore implement the toolbox's island migration and, so that the
    operator acts, split the default 30 into ``n_islands = 2`` islands of 15; ``n_islands = 1``
    is the literal single-population reading (migration inert).

    **Presets.** :attr:`PRESETS` holds the seeds' settings: ``GeneticAlgorithm(**GeneticAlgorithm.
    PRESETS["seed001"])``. Seed 004 (the defaults): population 30, crossover 0.8, migration 0.7,
    SUS + linear scaling; it gives no mutation rate (MATLAB's ``ga`` makes the remaining
    ``1 - 0.8 = 0.2`` of its children by mutation), so ``p_mutation = 0.2``. Seed 001: crossover
    0.5, mutation 0.2 (its population is not given; the default 30 is kept).

    **Start point.** Individual 0 of island 0 is ``problem.x0`` (clipped) when the problem has
    one; the rest are uniform in the bounds. With elitism the result is never worse than ``x0``.

    Args:
        pop_size: total population ``P`` (seed 004: 30); must be divisible by ``n_islands``.
        max_iter: generations (not given by the seeds; default 200).
        p_crossover: probability that a parent pair crosses (seed 004: 0.8; seed 001: 0.5).
        p_mutation: per-gene mutation probability (seed 001: 0.2).
        migration: share of an island that migrates (seed 004: 0.7).
        n_islands: number of islands ``I`` (default 2, see above).
        migration_interval: generations between migrations (MATLAB default 20).
        n_elite: elites per island; ``None`` = MATLAB's ``ceil(0.05 S)`` (1 for ``S = 15``).
        selection: ``"sus"`` or ``"tournament"``.
        scaling_rate: expected copies of the best under ``"sus"`` (MATLAB's default 2).
        alpha: BLX blend parameter.
        mutation_scale: initial Gaussian step as a fraction of each parameter's range.
        shrink: how far the step shrinks by the last generation (1 = to ``mutation_scale/max_iter``).
        seed, progress, callback: see :class:`Solver`. ``callback(it, best)`` is called after
            initialisation (``it = 0``) and after each generation with the best fitness so far.

    Result: ``x`` the best point ever evaluated, ``history`` the best fitness after
    initialisation and after each generation (``max_iter + 1`` floats), ``n_evals =
    P + max_iter I (S - n_elite)``. NaN fitness counts as ``+inf``.
    """

    name = "ga"
    population = True
    aliases = ("rcga",)

    #: Settings from the seed documents (pass as keyword arguments).
    PRESETS: dict[str, dict] = {
        "seed004": {"pop_size": 30, "p_crossover": 0.8, "migration": 0.7, "p_mutation": 0.2,
                    "selection": "sus"},
        "seed001": {"p_crossover": 0.5, "p_mutation": 0.2},
    }

    def __init__(self, settings: GAOptions | None = None, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None, **options):
        self.settings = GAOptions.build(settings, **options)
        (pop_size, max_iter, p_crossover, p_mutation, migration, n_islands, migration_interval, n_elite, selection,
         scaling_rate, alpha, mutation_scale, shrink) = astuple(self.settings)
        super().__init__(seed=seed, progress=progress, callback=callback)
        pop_size, n_islands = int(pop_size), int(n_islands)
        if n_islands < 1 or pop_size < 2 * n_islands or pop_size % n_islands:
            raise ValueError(f"pop_size={pop_size} must be a multiple of n_islands={n_islands} "
                             "with at least 2 individuals per island")
        S = pop_size // n_islands
        n_elite = math.ceil(0.05 * S) if n_elite is None else int(n_elite)
        if not 0 <= n_elite < S:
            raise ValueError(f"n_elite must be in [0, {S - 1}] (island size {S}), got {n_elite}")
        for nm, v in (("p_crossover", p_crossover), ("p_mutation", p_mutation),
                      ("migration", migration), ("shrink", shrink)):
            if not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"{nm} must be in [0, 1], got {v}")
        if selection not in ("sus", "tournament"):
            raise ValueError(f"selection must be 'sus' or 'tournament', got {selection!r}")
        if int(max_iter) < 0 or int(migration_interval) < 1:
            raise ValueError("need max_iter >= 0 and migration_interval >= 1")
        if not float(scaling_rate) >= 1.0 or not float(alpha) >= 0.0 or not float(mutation_scale) >= 0.0:
            raise ValueError("need scaling_rate >= 1, alpha >= 0, mutation_scale >= 0")
        self.pop_size = pop_size
        self.max_iter = int(max_iter)
        self.p_crossover = float(p_crossover)
        self.p_mutation = float(p_mutation)
        self.migration = float(migration)
        self.n_islands = n_islands
        self.island_size = S
        self.migration_interval = int(migration_interval)
        self.n_elite = n_elite
        self.selection = selection
        self.scaling_rate = float(scaling_rate)
        self.alpha = float(alpha)
        self.mutation_scale = float(mutation_scale)
        self.shrink = float(shrink)

    @property
    def n_migrants(self) -> int:
        """Individuals moved per island at each migration: ``floor(migration S)``."""
        return int(math.floor(self.migration * self.island_size + 1e-9)) if self.n_islands > 1 else 0

    # -- operators (all batched over islands) ---------------------------------------------------
    def _select(self, F: Tensor, n: int, g: torch.Generator) -> Tensor:
        """``(I, S)`` fitness -> ``(I, n)`` parent indices into each island."""
        I, S = F.shape
        dev = F.device
        if self.selection == "tournament":
            cand = torch.randint(0, S, (I, n, 2), generator=g, device=dev)
            fc = torch.gather(F, 1, cand.reshape(I, -1)).reshape(I, n, 2)
            # Ties go to the first contestant (argmin's first index): deterministic.
            return torch.gather(cand, 2, fc.argmin(-1, keepdim=True)).squeeze(-1)
        # Linear (shift) scaling. Infinite fitness (failed evaluations) is replaced by the worst
        # finite value so that mean/min stay finite; those individuals then get the lowest
        # expectation (clipped to 0 when below the line).
        finite = torch.isfinite(F)
        worst = torch.where(finite, F, torch.full_like(F, -float("inf"))).amax(1, keepdim=True)
        worst = torch.where(torch.isfinite(worst), worst, torch.zeros_like(worst))
        Ff = torch.where(finite, F, worst)
        mean, best = Ff.mean(1, keepdim=True), Ff.amin(1, keepdim=True)
        gap = mean - best
        flat = gap <= 0  # all equal: uniform expectations
        e = 1.0 + (self.scaling_rate - 1.0) * (mean - Ff) / torch.where(flat, torch.ones_like(gap), gap)
        e = torch.where(flat, torch.ones_like(e), e).clamp_min(0.0)
        # Stochastic universal sampling: n equally spaced pointers with one random offset.
        c = torch.cumsum(e, 1)
        c = c / c[:, -1:]
        start = torch.rand((I, 1), generator=g, dtype=F.dtype, device=dev)
        ptr = (start + torch.arange(n, dtype=F.dtype, device=dev)) / n
        idx = torch.searchsorted(c.contiguous(), ptr.contiguous(), right=True).clamp_max(S - 1)
        # SUS returns parents in index order; shuffle so that pairs are random.
        perm = torch.argsort(torch.rand((I, n), generator=g, dtype=F.dtype, device=dev), dim=1)
        return torch.gather(idx, 1, perm)

    def _crossover(self, parents: Tensor, g: torch.Generator) -> Tensor:
        """``(I, 2m, k)`` parents (consecutive pairs) -> ``(I, 2m, k)`` children (BLX-alpha)."""
        I, n, k = parents.shape
        p1, p2 = parents[:, 0::2], parents[:, 1::2]
        a = torch.rand((I, n // 2, k), generator=g, dtype=parents.dtype, device=parents.device)
        a = -self.alpha + (1.0 + 2.0 * self.alpha) * a
        cross = torch.rand((I, n // 2, 1), generator=g, dtype=parents.dtype,
                           device=parents.device) < self.p_crossover
        # A pair that does not cross passes on copies (a = 1 gives c1 = p1, c2 = p2).
        a = torch.where(cross, a, torch.ones_like(a))
        c1 = a * p1 + (1.0 - a) * p2
        c2 = a * p2 + (1.0 - a) * p1
        return torch.stack((c1, c2), 2).reshape(I, n, k)

    def _mutate(self, C: Tensor, t: int, span: Tensor, g: torch.Generator) -> Tensor:
        """Gaussian mutation of each gene with probability ``p_mutation`` at generation ``t``."""
        sigma = self.mutation_scale * (1.0 - self.shrink * (t - 1) / max(self.max_iter, 1)) * span
        u = torch.rand(C.shape, generator=g, dtype=C.dtype, device=C.device)
        z = torch.randn(C.shape, generator=g, dtype=C.dtype, device=C.device)
        return torch.where(u < self.p_mutation, C + z * sigma, C)

    def _migrate(self, X: Tensor, F: Tensor) -> tuple[Tensor, Tensor]:
        """Best ``n_migrants`` of island ``i`` replace the worst of island ``i + 1`` (ring)."""
        m = self.n_migrants
        order = torch.argsort(F, dim=1, stable=True)
        Xs = torch.gather(X, 1, order[..., None].expand_as(X))
        Fs = torch.gather(F, 1, order)
        # roll by +1 along islands: island i receives island i-1's best (i.e. i -> i+1).
        Xn = torch.cat((Xs[:, : self.island_size - m], torch.roll(Xs[:, :m], 1, 0)), 1)
        Fn = torch.cat((Fs[:, : self.island_size - m], torch.roll(Fs[:, :m], 1, 0)), 1)
        return Xn, Fn

    # -- the run --------------------------------------------------------------------------------
    def init(self, problem: Problem, g: torch.Generator) -> SimpleNamespace:
        problem.require_finite_bounds(self.name)
        dt, dev = problem.dtype, problem.device
        lo, hi = problem.lower, problem.upper
        I, S, k, E = self.n_islands, self.island_size, problem.dim, self.n_elite
        n_child = S - E
        s = SimpleNamespace(span=hi - lo, k=k, n_child=n_child,
                            n_par=n_child + (n_child % 2),  # pairs need an even number; the spare child is dropped
                            n_migrations=0)
        X = lo + torch.rand((I * S, k), generator=g, dtype=dt, device=dev) * s.span
        if problem.x0 is not None:
            # Seed the population with the user's start; elitism keeps it until beaten.
            X[0] = problem.clip(problem.x0)
        X = problem.clip(X)  # lo + u*span can overshoot hi by one rounding step
        s.F = evaluate(problem, X).reshape(I, S)
        s.X = X.reshape(I, S, k)
        s.n_evals = I * S
        i = int(torch.argmin(s.F.reshape(-1)))
        s.best_x, s.best = s.X.reshape(-1, k)[i].clone(), s.F.reshape(-1)[i].clone()
        return s

    def step(self, problem: Problem, s: SimpleNamespace, t: int, g: torch.Generator) -> None:
        I, k, E, n_child = self.n_islands, s.k, self.n_elite, s.n_child
        X, F = s.X, s.F
        order = torch.argsort(F, dim=1, stable=True)
        elite = order[:, :E]
        par = self._select(F, s.n_par, g)
        parents = torch.gather(X, 1, par[..., None].expand(I, s.n_par, k))
        C = self._crossover(parents, g)[:, :n_child]
        C = problem.clip(self._mutate(C, t, s.span, g))
        Fc = evaluate(problem, C.reshape(-1, k)).reshape(I, n_child)
        s.n_evals += I * n_child
        X = torch.cat((torch.gather(X, 1, elite[..., None].expand(I, E, k)), C), 1)
        F = torch.cat((torch.gather(F, 1, elite), Fc), 1)
        if self.n_migrants > 0 and t % self.migration_interval == 0:
            X, F = self._migrate(X, F)
            s.n_migrations += 1
        s.X, s.F = X, F
        # Best ever: children are the only new points (elites and migrants were seen).
        j = torch.argmin(Fc.reshape(-1))
        cf = Fc.reshape(-1)[j]
        better = cf < s.best
        s.best_x = torch.where(better, C.reshape(-1, k)[j], s.best_x)
        s.best = torch.where(better, cf, s.best)
        return None

    def finish(self, problem: Problem, s: SimpleNamespace) -> tuple[Tensor, float, dict]:
        return s.best_x, float(s.best), {"n_islands": self.n_islands, "island_size": self.island_size,
                                         "n_elite": self.n_elite, "n_migrants": self.n_migrants,
                                         "n_migrations": s.n_migrations}
