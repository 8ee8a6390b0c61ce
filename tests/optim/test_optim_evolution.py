"""Tests of the evolutionary solvers: real-coded GA, mayfly algorithm (MA) and seed 002's MMA."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.optim import FunctionProblem, get_solver, minimize
from torchcal.optim.ga import GeneticAlgorithm
from torchcal.optim.mayfly import Mayfly
from torchcal.optim.mma import ModifiedMayfly, improved_tent_map

from conftest import Recorder

D = torch.float64
SHIFT = torch.tensor([1.5, -2.0, 0.7, 3.1, -0.4], dtype=D)


def sphere(X):
    return (X * X).sum(-1)


def shifted_sphere(X):
    return ((X - SHIFT) ** 2).sum(-1)


def rastrigin(X):
    return 10.0 * X.shape[-1] + (X * X - 10.0 * torch.cos(2.0 * math.pi * X)).sum(-1)


def box(fn, k, half, x0=None):
    return FunctionProblem(fn, -half * torch.ones(k, dtype=D), half * torch.ones(k, dtype=D), x0=x0)


# Small, fast configurations (the defaults are the seeds' sizes).
def make(name, seed=0, **kw):
    base = {"ga": dict(pop_size=20, max_iter=200),
            "ma": dict(pop_size=10, max_iter=60),
            "mma": dict(pop_size=10, max_iter=60)}[name]
    return get_solver(name, seed=seed, **{**base, **kw})


ALL = ["ga", "ma", "mma"]


# -- convergence ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ALL)
def test_shifted_sphere_converges(name):
    res = make(name).minimize(box(shifted_sphere, 5, 5.0))
    assert res.fun < 1e-4
    assert torch.allclose(res.x, SHIFT, atol=1e-2)
    # the fitness of the point returned, which the solver evaluated in a population batch: equal up
    # to the rounding of a short sum
    assert res.fun == pytest.approx(float(shifted_sphere(res.x[None])[0]), rel=1e-12, abs=1e-300)
    assert res.method == name


@pytest.mark.parametrize("name", ALL)
def test_rastrigin_2d_global_basin(name):
    kw = {"ga": dict(max_iter=100), "ma": dict(pop_size=20), "mma": dict(pop_size=20)}[name]
    res = make(name, **kw).minimize(box(rastrigin, 2, 5.12))
    assert res.fun < 1e-2
    assert float(res.x.abs().max()) < 0.05  # the global basin, not a neighbouring one


def random_search(problem, n, seed):
    """Best of ``n`` uniform samples in the bounds (its own seeded generator)."""
    g = torch.Generator().manual_seed(10_000 + seed)
    U = torch.rand((n, problem.dim), generator=g, dtype=problem.dtype)
    return float(problem.fitness(problem.lower + U * (problem.upper - problem.lower)).min())


@pytest.mark.parametrize("name", ["ma", "mma"])
@pytest.mark.parametrize("fn,k,half,factor", [(sphere, 10, 5.0, 1e-2), (rastrigin, 5, 5.12, 0.5)])
def test_beats_random_search(name, fn, k, half, factor):
    prob = box(fn, k, half)
    alg, rs = [], []
    for seed in range(5):
        res = make(name, seed=seed, max_iter=40).minimize(prob)
        alg.append(res.fun)
        rs.append(random_search(prob, res.n_evals, seed))  # equal number of evaluations
    assert sum(alg) / 5 < factor * sum(rs) / 5


# -- reproducibility ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ALL)
def test_reproducible(name):
    prob = box(rastrigin, 4, 5.12)
    a = make(name, seed=3, max_iter=15).minimize(prob)
    b = make(name, seed=3, max_iter=15).minimize(prob)
    c = make(name, seed=4, max_iter=15).minimize(prob)
    # the same run twice (same shapes, same kernels, same machine): exact
    assert torch.equal(a.x, b.x) and a.history == b.history and a.n_evals == b.n_evals
    assert not torch.equal(a.x, c.x)
    assert a.history != c.history


def test_no_global_rng_use():
    torch.manual_seed(123)
    before = torch.get_rng_state()
    for name in ALL:
        make(name, max_iter=3).minimize(box(sphere, 3, 1.0))
    assert torch.equal(torch.get_rng_state(), before)


# -- bounds, evaluation counts, history, start point -------------------------------------------
LO = torch.tensor([-0.1, 2.0, -3.0, 1e-3], dtype=D)
HI = torch.tensor([0.3, 2.5, -1.0, 2e-3], dtype=D)


@pytest.mark.parametrize("name", ALL)
def test_evaluated_points_stay_in_bounds(name):
    # Optimum outside the box on every axis, so the swarms press against the walls.
    rec = Recorder(lambda X: ((X - torch.tensor([5.0, -5.0, 5.0, -5.0], dtype=D)) ** 2).sum(-1))
    prob = FunctionProblem(rec, LO, HI, x0=torch.tensor([0.0, 2.2, -2.0, 1.5e-3], dtype=D))
    res = make(name, max_iter=30).minimize(prob)
    P = rec.points
    assert bool((P >= LO).all()) and bool((P <= HI).all())
    assert bool((res.x >= LO).all()) and bool((res.x <= HI).all())
    # The corner nearest the optimum is reached.
    assert torch.allclose(res.x, torch.tensor([0.3, 2.0, -1.0, 1e-3], dtype=D), atol=1e-3)


def expected_evals(name, solver, T):
    if name == "ga":
        I = solver.n_islands
        S = solver.pop_size // I
        E = math.ceil(0.05 * S)
        return I * S + T * I * (S - E)
    n, n_off = solver.pop_size, solver.n_off
    if name == "ma":
        return 2 * n + T * (2 * n + n_off)
    n_mut = int(math.floor(solver.cauchy_share * n_off + 0.5))
    return 4 * n + T * (2 * n + n_off + n_mut)


@pytest.mark.parametrize("name,kw", [("ga", {}), ("ga", dict(pop_size=21, n_islands=3)),
                                     ("ma", {}), ("ma", dict(n_off=6)),
                                     ("mma", {}), ("mma", dict(n_off=8, cauchy_share=0.3))])
def test_n_evals_and_history(name, kw):
    rec = Recorder(sphere)
    T = 7
    calls = []
    solver = make(name, max_iter=T, callback=lambda it, best: calls.append((it, best)), **kw)
    res = solver.minimize(FunctionProblem(rec, -torch.ones(3, dtype=D), torch.ones(3, dtype=D)))
    assert res.n_evals == rec.points.shape[0] == expected_evals(name, solver, T)
    assert res.n_iter == T and len(res.history) == T + 1
    assert all(b <= a for a, b in zip(res.history, res.history[1:]))  # best so far never rises
    assert res.history[-1] == res.fun  # one stored number
    assert res.fun == pytest.approx(float(sphere(rec.points).min()), rel=1e-12)  # recomputed on another batch
    assert [it for it, _ in calls] == list(range(T + 1))
    assert [b for _, b in calls] == res.history


def test_history_zero_is_best_of_initial_population():
    rec = Recorder(rastrigin)
    n = 6
    res = make("ma", pop_size=n, max_iter=2).minimize(FunctionProblem(
        rec, -5.12 * torch.ones(3, dtype=D), 5.12 * torch.ones(3, dtype=D)))
    assert res.history[0] == pytest.approx(float(rastrigin(rec.batches[0]).min()), rel=1e-12)
    assert rec.batches[0].shape[0] == 2 * n


@pytest.mark.parametrize("name", ALL)
def test_x0_is_in_initial_population(name):
    x0 = SHIFT.clone()  # the optimum itself: history[0] must be exactly 0
    rec = Recorder(shifted_sphere)
    res = make(name, max_iter=2).minimize(box(rec, 5, 5.0, x0=x0))
    assert res.history[0] == 0.0 and res.fun == 0.0
    assert bool((rec.batches[0] == x0).all(1).any())


def test_mma_keeps_a_poor_x0():
    x0 = torch.full((5,), 5.0, dtype=D)  # a bad corner: not among the fittest half
    solver = make("mma")
    s = solver.initial_population(box(shifted_sphere, 5, 5.0, x0=x0))
    assert bool((s.Xm == x0).all(1).any())


def test_float32_and_registry():
    prob = FunctionProblem(sphere, -torch.ones(3), torch.ones(3))
    for name, alias, cls in [("ga", "rcga", GeneticAlgorithm), ("ma", "mayfly", Mayfly),
                             ("mma", "modified-mayfly", ModifiedMayfly)]:
        assert type(get_solver(name)) is cls and type(get_solver(alias)) is cls
        res = minimize(prob, alias, max_iter=5, pop_size=10)
        assert res.x.dtype == torch.float32 and res.fun < 1.0


def test_progress_bar_runs(capsys):
    res = make("mma", max_iter=3, progress=True).minimize(box(sphere, 2, 1.0))
    assert len(res.history) == 4
    assert "mma" in capsys.readouterr().err


def test_infinite_bounds_rejected():
    prob = FunctionProblem(sphere, torch.tensor([-1.0, -math.inf], dtype=D), torch.ones(2, dtype=D))
    for name in ALL:
        with pytest.raises(ValueError, match="finite"):
            make(name).minimize(prob)


def test_nan_fitness_is_never_best():
    def fn(X):
        f = sphere(X - 0.5)
        return torch.where(X[:, 0] < 0, torch.full_like(f, math.nan), f)
    for name in ALL:
        res = make(name, max_iter=20).minimize(box(fn, 2, 1.0))
        assert math.isfinite(res.fun) and float(res.x[0]) >= 0


# -- GA operators ---------------------------------------------------------------------------------
def test_ga_presets_and_defaults():
    ga = GeneticAlgorithm()
    assert (ga.pop_size, ga.p_crossover, ga.migration) == (30, 0.8, 0.7)  # seed 004
    p = GeneticAlgorithm.PRESETS
    assert p["seed004"]["pop_size"] == 30 and p["seed004"]["p_crossover"] == 0.8
    assert p["seed004"]["migration"] == 0.7
    assert p["seed001"]["p_crossover"] == 0.5 and p["seed001"]["p_mutation"] == 0.2
    ga1 = GeneticAlgorithm(**p["seed001"])
    assert (ga1.p_crossover, ga1.p_mutation) == (0.5, 0.2)
    assert ga.n_migrants == math.floor(0.7 * 15)


def test_ga_migration_moves_best_to_next_island():
    ga = GeneticAlgorithm(pop_size=15, n_islands=3, migration=0.4)  # 2 migrants of 5
    X = torch.arange(15, dtype=D).reshape(3, 5, 1)
    F = torch.tensor([[5., 1., 4., 2., 3.], [9., 8., 7., 6., 10.], [11., 15., 12., 14., 13.]], dtype=D)
    Xn, Fn = ga._migrate(X, F)
    # Island 1 keeps its best 3 and receives island 0's best 2 (fitness 1, 2), and so on round
    # the ring; migrants keep their fitness and position together.
    assert Fn[1].tolist() == [6., 7., 8., 1., 2.]
    assert Fn[2].tolist() == [11., 12., 13., 6., 7.]
    assert Fn[0].tolist() == [1., 2., 3., 11., 12.]
    assert Xn[1, 3:, 0].tolist() == [1., 3.]
    res = make("ga", max_iter=45, migration_interval=20).minimize(box(sphere, 2, 1.0))
    assert res.extra["n_migrations"] == 2


def test_ga_single_island_has_no_migration():
    res = make("ga", max_iter=45, n_islands=1).minimize(box(sphere, 2, 1.0))
    assert res.extra["n_migrations"] == 0 and res.extra["n_migrants"] == 0


def test_ga_without_crossover_or_mutation_only_copies():
    # pc = pm = 0: children are copies of parents, so no new point is ever evaluated and the
    # best stays the initial one. Guards that both operators are actually gated by their rates.
    rec = Recorder(sphere)
    res = make("ga", max_iter=10, p_crossover=0.0, p_mutation=0.0).minimize(
        FunctionProblem(rec, -torch.ones(3, dtype=D), torch.ones(3, dtype=D)))
    init = rec.batches[0]
    later = torch.cat(rec.batches[1:])
    assert bool((later[:, None, :] == init[None]).all(-1).any(1).all())
    assert res.history[0] == res.history[-1]


@pytest.mark.parametrize("selection", ["sus", "tournament"])
def test_ga_selection_prefers_fit(selection):
    ga = GeneticAlgorithm(pop_size=40, n_islands=2, selection=selection)
    F = torch.arange(20, dtype=D).repeat(2, 1)  # index = rank
    idx = ga._select(F, 2000, torch.Generator().manual_seed(0))
    assert idx.shape == (2, 2000)
    counts = torch.bincount(idx.reshape(-1), minlength=20).to(D)
    assert counts[:5].sum() > 2.0 * counts[-5:].sum()


# -- MMA specifics --------------------------------------------------------------------------------
def _tent(z, a):
    return z / a if z < a else (1.0 - z) / (1.0 - a)


def test_improved_tent_map_matches_scalar_recurrence():
    g = torch.Generator().manual_seed(5)
    z0 = torch.rand(3, generator=g, dtype=D)
    noise = torch.rand((12, 3), generator=g, dtype=D) / 12
    Z = improved_tent_map(z0, noise, 0.4)
    for j in range(3):
        z = float(z0[j])
        for i in range(12):
            z = (_tent(z, 0.4) + float(noise[i, j])) % 1.0
            assert float(Z[i, j]) == pytest.approx(z, abs=1e-12)
    assert bool(((Z >= 0) & (Z < 1)).all())


def test_mma_initialisation_is_fittest_half_of_tent_and_opposites():
    lo = torch.tensor([-2.0, 0.0, 10.0], dtype=D)
    hi = torch.tensor([1.0, 4.0, 11.0], dtype=D)
    fn = lambda X: rastrigin(X - torch.tensor([0.0, 2.0, 10.5], dtype=D))  # noqa: E731
    rec = Recorder(fn)
    prob = FunctionProblem(rec, lo, hi)
    n = 7
    solver = ModifiedMayfly(pop_size=n, seed=11)
    s = solver.initial_population(prob)
    assert len(rec.batches) == 1 and s.n_evals == 4 * n
    B = rec.batches[0]
    Cm, Om, Cf, Of = B[:n], B[n:2 * n], B[2 * n:3 * n], B[3 * n:]
    # Opposition: x_opp = x_min + x_max - x.
    assert torch.allclose(Om, lo + hi - Cm, atol=1e-12, rtol=0)
    assert torch.allclose(Of, lo + hi - Cf, atol=1e-12, rtol=0)
    # Candidates are one improved-tent chain (a = 0.5, noise in [0, 1/(2n))) mapped onto the
    # bounds: z_{i+1} - T(z_i) mod 1 lies in [0, 1/(2n)).
    Z = ((torch.cat((Cm, Cf)) - lo) / (hi - lo)).tolist()
    for i in range(2 * n - 1):
        for j in range(3):
            r = (Z[i + 1][j] - _tent(Z[i][j], 0.5)) % 1.0
            assert r < 1.0 / (2 * n) + 1e-9 or r > 1.0 - 1e-9
    # Selection, recomputed independently: each sex keeps the fittest n of its 2n.
    # The kept rows are copies (exact); their fitness is recomputed here on another batch shape, so
    # it compares to rounding. Seeded random points: no two fitnesses lie within rounding of each
    # other, so the kept set is the recomputed n fittest.
    for cand, X, f in ((B[:2 * n], s.Xm, s.fm), (B[2 * n:], s.Xf, s.ff)):
        fc = fn(cand)
        order = torch.argsort(fc, stable=True)[:n]
        gaps = fc.sort().values.diff()
        assert float(gaps.min()) > 1e-9 * float(fc.abs().max())  # the premise: no near-tie
        assert torch.equal(X, cand[order])
        torch.testing.assert_close(f, fc[order], rtol=1e-12, atol=0)
    assert float(s.gf) == pytest.approx(float(fn(B).min()), rel=1e-12)
    # The run starts from exactly this population.
    rec2 = Recorder(fn)
    res = ModifiedMayfly(pop_size=n, seed=11, max_iter=1).minimize(FunctionProblem(rec2, lo, hi))
    assert torch.equal(rec2.batches[0], B) and res.history[0] == float(s.gf)


def test_mma_cauchy_mutation_keeps_n_off():
    k, n_off = 10, 8
    solver = ModifiedMayfly(pop_size=8, n_off=n_off, cauchy_share=0.5, seed=2)
    assert solver.n_mut == 4
    rec = Recorder(sphere)
    prob = FunctionProblem(rec, -100 * torch.ones(k, dtype=D), 100 * torch.ones(k, dtype=D))
    # Offspring row i has a 0 in component i only: x + x C keeps that 0, which identifies the
    # parent of each mutant.
    X = 1.0 + torch.rand((n_off, k), generator=torch.Generator().manual_seed(0), dtype=D)
    X[torch.arange(n_off), torch.arange(n_off)] = 0.0
    f = sphere(X)
    male = torch.arange(n_off) % 2 == 0
    s = solver.initial_population(FunctionProblem(sphere, prob.lower, prob.upper))
    n0 = s.n_evals
    X2, f2, male2 = solver.cauchy_mutation(prob, s, X, f, male, torch.Generator().manual_seed(1))
    assert X2.shape == (n_off, k) and f2.shape == (n_off,) and male2.shape == (n_off,)
    assert s.n_evals == n0 + 4 and len(rec.batches) == 1
    Y = rec.batches[0]
    assert Y.shape == (4, k)
    parents = [int(torch.nonzero(y == 0)[0]) for y in Y]
    assert all(int((y == 0).sum()) == 1 for y in Y)
    assert len(set(parents)) == 4  # chosen without replacement
    assert not bool((Y[:, None] == X[None]).all(-1).any())  # each mutant moved
    # The fittest n_off of offspring + mutants, with the parent's sex.
    pool_f = torch.cat((f, sphere(Y)))
    pool_X = torch.cat((X, Y))
    pool_m = torch.cat((male, male[parents]))
    order = torch.argsort(pool_f, stable=True)[:n_off]
    torch.testing.assert_close(f2, pool_f[order], rtol=1e-12, atol=0)  # recomputed here: to rounding
    assert torch.equal(X2, pool_X[order])  # copies of the pool's rows
    assert torch.equal(male2, pool_m[order])


def test_mma_mutation_is_cauchy():
    # Every offspring at x = 1, so each mutant is 1 + C. The median of |C| is 1 for a standard
    # Cauchy (0.674 for a standard normal, 0.5 for U(-1, 1)) and P(|C| > 10) = 0.063.
    n_off, k = 400, 10
    solver = ModifiedMayfly(pop_size=n_off, n_off=n_off, cauchy_share=1.0, seed=0)
    lo, hi = -1e9 * torch.ones(k, dtype=D), 1e9 * torch.ones(k, dtype=D)
    X = torch.ones((n_off, k), dtype=D)
    rec = Recorder(sphere)
    s = solver.initial_population(FunctionProblem(sphere, lo, hi))
    solver.cauchy_mutation(FunctionProblem(rec, lo, hi), s, X, sphere(X),
                           torch.ones(n_off, dtype=torch.bool), torch.Generator().manual_seed(3))
    C = rec.batches[0] - 1.0
    assert C.shape == (n_off, k)
    assert 0.9 < float(C.abs().median()) < 1.1
    assert 0.04 < float((C.abs() > 10).double().mean()) < 0.09


def test_mayfly_mating_and_damping():
    k, n = 4, 6
    solver = Mayfly(pop_size=n, n_off=8, seed=0)
    prob = box(sphere, k, 2.0)
    s = solver.initial_population(prob)
    n0 = s.n_evals
    X, f, male = solver.offspring(prob, s, torch.Generator().manual_seed(0))
    assert X.shape == (8, k) and s.n_evals == n0 + 8
    assert male.tolist() == [True] * 4 + [False] * 4
    M, Fe = s.Xm[:4], s.Xf[:4]  # the 4 best ranked pairs
    # off1 = L m + (1-L) f and off2 = L f + (1-L) m: per gene between the parents, and the two
    # children of a pair sum to the parents' sum.
    assert torch.allclose(X[:4] + X[4:], M + Fe, atol=1e-12, rtol=0)
    assert bool((X[:4] >= torch.minimum(M, Fe) - 1e-12).all() & (X[:4] <= torch.maximum(M, Fe) + 1e-12).all())
    assert not torch.allclose(X[:4], X[4:])
    torch.testing.assert_close(f, sphere(X), rtol=1e-12, atol=0)
    T = 5
    res = Mayfly(pop_size=n, max_iter=T, g_damp=0.9, d_damp=0.8, fl_damp=0.7).minimize(prob)
    assert res.extra["g"] == pytest.approx(0.8 * 0.9 ** T)
    assert res.extra["d"] == pytest.approx(0.1 * 0.8 ** T)
    assert res.extra["fl"] == pytest.approx(0.1 * 0.7 ** T)
