"""Tests of the swarm solvers (PSO, LDPSO-BT, chaotic PSO) and the swarm + LM hybrid."""
from __future__ import annotations

import math

import pytest
import torch

from torchcal.optim import (FunctionProblem, LeastSquaresProblem, Result, Solver, available,
                            get_solver, register)
from torchcal.optim.cpso import ChaoticPSO, avoid_fixed_points, logistic_sequence
from torchcal.optim.pso import LDPSO_BT, PSO, SwarmState, ldpso_pop_sizes

from conftest import Recorder

D = torch.float64
CENTRE = torch.tensor([0.3, -1.2, 2.1, 0.7, -0.4, 1.5], dtype=D)

# Small, seeded configurations that solve the test problems reliably and fast.
CONFIGS = {
    "pso": dict(pop_size=30, max_iter=200, w=0.729),
    "ldpso-bt": dict(n_max=40, n_min=10, max_iter=400),
    "cpso": dict(pop_size=30, max_iter=200),
}


def sphere_fn(X):
    return ((X - CENTRE) ** 2).sum(-1)


def sphere(fn=sphere_fn, x0=None):
    return FunctionProblem(fn, -5 * torch.ones(6, dtype=D), 5 * torch.ones(6, dtype=D), x0=x0)


def rastrigin_fn(X):
    return 10 * X.shape[-1] + (X ** 2 - 10 * torch.cos(2 * math.pi * X)).sum(-1)


def rastrigin():
    return FunctionProblem(rastrigin_fn, -5.12 * torch.ones(2, dtype=D), 5.12 * torch.ones(2, dtype=D))


# ---------------------------------------------------------------------------------------------
# Registry and convergence
# ---------------------------------------------------------------------------------------------
def test_registered_names_and_aliases():
    names = available()
    for n in ("pso", "ldpso-bt", "ldpso", "cpso", "chaotic-pso", "hybrid", "pso+lm"):
        assert n in names
    assert isinstance(get_solver("ldpso"), LDPSO_BT)
    assert isinstance(get_solver("chaotic-pso"), ChaoticPSO)
    assert type(get_solver("pso")) is PSO


def test_defaults_follow_the_seeds():
    p = get_solver("pso")
    assert (p.pop_size, p.max_iter, p.w, p.c1, p.c2, p.v_max) == (240, 500, 0.8, 1.49, 1.49, 0.2)
    ld = get_solver("ldpso-bt")
    assert (ld.n_max, ld.n_min, ld.max_iter, ld.w1, ld.w2, ld.k_switch, ld.c1, ld.c2) == \
        (240, 40, 500, 0.8, 0.4, 0.8, 1.49, 1.49)
    cp = get_solver("cpso")
    assert (cp.pop_size, cp.max_iter, cp.c1, cp.c2, cp.n_chaos, cp.mu, cp.chaos_radius) == \
        (200, 200, 1.3, 1.8, 10, 4.0, None)
    assert cp.inertia(1) == pytest.approx(0.9) and cp.inertia(200) == pytest.approx(0.2)
    assert cp.inertia(100) == pytest.approx(0.9 - 0.7 * 99 / 199)


@pytest.mark.parametrize("method", list(CONFIGS))
def test_shifted_sphere_to_1e6(method):
    res = get_solver(method, seed=1, **CONFIGS[method]).minimize(sphere())
    assert isinstance(res, Result) and res.method == method
    assert float((res.x - CENTRE).abs().max()) < 1e-6
    # the fitness of the point returned (the solver evaluated it in a population batch: the same
    # number up to the rounding of a 6-term sum)
    assert res.fun == pytest.approx(sphere_fn(res.x[None]).item(), rel=1e-12, abs=1e-300)
    assert res.x.dtype == D and res.x.shape == (6,)


@pytest.mark.parametrize("method", list(CONFIGS))
def test_rastrigin_2d_global_minimum(method):
    res = get_solver(method, seed=3, **CONFIGS[method]).minimize(rastrigin())
    assert res.fun < 1e-3
    assert float(res.x.abs().max()) < 1e-2  # the global, not a local, minimum


@pytest.mark.parametrize("method", list(CONFIGS))
def test_history_evals_and_callback(method):
    rec = Recorder(sphere_fn)
    calls = []
    opts = dict(CONFIGS[method], max_iter=15)
    res = get_solver(method, seed=0, callback=lambda it, b: calls.append((it, b)), **opts).minimize(sphere(rec))
    assert len(res.history) == 16 and res.n_iter == 15
    assert all(isinstance(h, float) for h in res.history)
    assert all(b <= a for a, b in zip(res.history, res.history[1:]))  # best-so-far never rises
    assert res.history[-1] == res.fun
    # history[0] is the best of the initial population.
    assert res.history[0] == pytest.approx(float(sphere_fn(rec.batches[0]).min()), rel=1e-12)
    assert res.n_evals == rec.n_points
    assert calls == list(enumerate(res.history))


# ---------------------------------------------------------------------------------------------
# Reproducibility, bounds, x0
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", list(CONFIGS))
def test_same_seed_identical_different_seed_differs(method):
    opts = dict(CONFIGS[method], max_iter=30)
    a = get_solver(method, seed=7, **opts).minimize(rastrigin())
    b = get_solver(method, seed=7, **opts).minimize(rastrigin())
    c = get_solver(method, seed=8, **opts).minimize(rastrigin())
    assert torch.equal(a.x, b.x) and a.history == b.history
    assert a.history != c.history


def test_does_not_touch_global_rng():
    torch.manual_seed(123)
    before = torch.get_rng_state()
    for m in CONFIGS:
        get_solver(m, **dict(CONFIGS[m], max_iter=3)).minimize(sphere())
    assert torch.equal(torch.get_rng_state(), before)


@pytest.mark.parametrize("method,extra", [("pso", {}), ("ldpso-bt", {}), ("cpso", {}),
                                          ("cpso", {"chaos_radius": 0.05})])
def test_every_evaluated_point_inside_bounds(method, extra):
    lo = torch.tensor([-1.0, 0.0, 2.0, -3.0], dtype=D)
    hi = torch.tensor([1.0, 0.5, 2.5, 3.0], dtype=D)
    target = torch.tensor([1.3, -0.2, 2.5, 0.0], dtype=D)  # outside in 2 components: forces clipping
    rec = Recorder(lambda X: ((X - target) ** 2).sum(-1))
    opts = dict(CONFIGS[method], max_iter=40, **extra)
    res = get_solver(method, seed=2, **opts).minimize(FunctionProblem(rec, lo, hi))
    pts = torch.cat(rec.batches)
    assert pts.shape[0] == res.n_evals
    assert bool((pts >= lo).all() and (pts <= hi).all())
    # Particles press on the walls (clipping really happened) and the optimum is on them.
    assert bool((pts[:, 0] == hi[0]).any() and (pts[:, 1] == lo[1]).any())
    torch.testing.assert_close(res.x, target.clamp(lo, hi), atol=1e-3, rtol=0)


def test_velocity_zeroed_on_clipped_components():
    """w = -1, c1 = c2 = 0: a free particle flips its velocity every step and so leaves any wall
    it touched; a particle whose velocity was zeroed at the wall stays there for good."""
    rec = Recorder(lambda X: X.sum(-1))
    PSO(pop_size=20, max_iter=6, w=-1.0, c1=0.0, c2=0.0, v_max=0.3, seed=1).minimize(
        FunctionProblem(rec, torch.zeros(3, dtype=D), torch.ones(3, dtype=D)))
    b = rec.batches
    hits = 0
    for t in range(1, len(b) - 1):
        wall = (b[t] == 0) | (b[t] == 1)
        hits += int(wall.sum())
        assert torch.equal(b[t + 1][wall], b[t][wall])
    assert hits > 0


@pytest.mark.parametrize("v_max", [0.05, None])
def test_velocity_limit(v_max):
    lo, hi = torch.tensor([-1.0, 0.0], dtype=D), torch.tensor([1.0, 10.0], dtype=D)
    rec = Recorder(rastrigin_fn)
    PSO(pop_size=20, max_iter=10, c1=3.0, c2=3.0, v_max=v_max, seed=2).minimize(FunctionProblem(rec, lo, hi))
    steps = torch.stack([(b - a).abs() for a, b in zip(rec.batches, rec.batches[1:])])
    ratio = (steps / (hi - lo)).amax(dim=(0, 1))  # largest step per component / range
    if v_max is None:
        assert bool((ratio > 0.1).all())  # unclamped strong attraction: big jumps
    else:
        assert bool((ratio <= v_max + 1e-12).all()) and bool((ratio > 0.9 * v_max).all())


@pytest.mark.parametrize("method", list(CONFIGS))
def test_x0_is_a_particle_and_infinite_bounds_rejected(method):
    x0 = torch.tensor([4.0, -4.0, 1.0, 1.0, 1.0, 9.0], dtype=D)  # last component outside: clipped
    rec = Recorder(sphere_fn)
    get_solver(method, **dict(CONFIGS[method], max_iter=2)).minimize(sphere(rec, x0=x0))
    torch.testing.assert_close(rec.batches[0][0], x0.clamp(-5, 5), atol=0, rtol=0)
    inf = FunctionProblem(sphere_fn, torch.full((6,), -math.inf, dtype=D), torch.ones(6, dtype=D))
    with pytest.raises(ValueError, match="finite"):
        get_solver(method).minimize(inf)


def test_float32_problem_stays_float32():
    p = FunctionProblem(sphere_fn, -5 * torch.ones(6), 5 * torch.ones(6))
    for m in CONFIGS:
        res = get_solver(m, **dict(CONFIGS[m], max_iter=5)).minimize(p)
        assert res.x.dtype == torch.float32


def test_progress_bar_runs(capsys):
    pytest.importorskip("tqdm")
    res = get_solver("pso", pop_size=5, max_iter=4, progress=True).minimize(sphere())
    assert len(res.history) == 5
    assert "pso" in capsys.readouterr().err


def test_nan_fitness_is_never_best():
    def fn(X):
        f = sphere_fn(X)
        return torch.where(X[:, 0] > 0, torch.full_like(f, math.nan), f)
    res = get_solver("pso", pop_size=20, max_iter=20).minimize(sphere(fn))
    assert math.isfinite(res.fun) and float(res.x[0]) <= 0


# ---------------------------------------------------------------------------------------------
# LDPSO-BT
# ---------------------------------------------------------------------------------------------
def _expected_sizes(n_max, n_min, max_it):
    # round() half away from zero (MATLAB), as documented in ldpso_pop_sizes.
    return [math.floor(n_max - (t - 1) * (n_max - n_min) / (max_it - 1) + 0.5) for t in range(1, max_it + 1)]


def test_ldpso_pop_size_formula():
    # Defaults: no ties, so any rounding convention agrees with the formula.
    sizes = ldpso_pop_sizes(240, 40, 500)
    assert sizes == [round(240 - (t - 1) * 200 / 499) for t in range(1, 501)]
    assert sizes[0] == 240 and sizes[-1] == 40 and len(sizes) == 500
    # 24/16 = 1.5 per step: every other value is a tie, rounded up (28.5 -> 29).
    assert ldpso_pop_sizes(30, 6, 17) == _expected_sizes(30, 6, 17)
    assert ldpso_pop_sizes(30, 6, 17)[1] == 29


def test_ldpso_population_really_shrinks_and_saves_evaluations():
    n_max, n_min, max_it = 30, 6, 17
    rec = Recorder(sphere_fn)
    res = LDPSO_BT(n_max=n_max, n_min=n_min, max_iter=max_it, seed=4).minimize(sphere(rec))
    expected = _expected_sizes(n_max, n_min, max_it)
    assert res.extra["pop_sizes"] == expected
    # The fitness really sees the smaller populations (index-selected tensors).
    assert [b.shape[0] for b in rec.batches] == [n_max] + expected
    assert res.n_evals == n_max + sum(expected) == rec.n_points
    pso = PSO(pop_size=n_max, max_iter=max_it, seed=4).minimize(sphere())
    assert pso.n_evals == n_max * (max_it + 1)
    assert res.n_evals < pso.n_evals


def test_ldpso_drops_the_worst_by_pbest():
    s = SwarmState(X=torch.arange(5.0)[:, None].repeat(1, 2), V=torch.zeros(5, 2),
                   pbest=torch.arange(5.0)[:, None].repeat(1, 2) + 10,
                   pbest_f=torch.tensor([5.0, 1.0, 4.0, 2.0, 3.0]),
                   gbest=torch.zeros(2), gbest_f=torch.tensor(1.0))
    solver = LDPSO_BT(n_max=5, n_min=3, max_iter=3)
    solver._sizes = [5, 4, 3]
    p = sphere()
    solver._before_step(1, s, p, solver.generator(p))
    assert s.size == 5
    solver._before_step(3, s, p, solver.generator(p))
    assert s.pbest_f.tolist() == [1.0, 2.0, 3.0]
    assert s.X[:, 0].tolist() == [1.0, 3.0, 4.0] and s.pbest[:, 0].tolist() == [11.0, 13.0, 14.0]


@pytest.mark.parametrize("k_switch", [0.5, 1.0])
def test_ldpso_best_tracking_drops_pbest_term(k_switch):
    """Constant fitness keeps pbest at the start points, so (pbest - x) != 0 once particles moved.
    With c2 = 0 and w2 = 0, stage 2 (t > K MaxIt) has v = 0: particles freeze. With K = 1 there
    is no stage 2 and the pbest term keeps them moving."""
    rec = Recorder(lambda X: torch.zeros(X.shape[0], dtype=X.dtype))
    LDPSO_BT(n_max=8, n_min=8, max_iter=10, k_switch=k_switch, w1=0.7, w2=0.0, c1=1.49, c2=0.0,
             v_max=0.05, seed=5).minimize(sphere(rec))
    b = rec.batches  # b[t] = positions evaluated at iteration t (b[0]: initial)
    assert len(b) == 11
    for t in range(1, 6):  # stage 1 in both cases: particles move
        assert not torch.equal(b[t], b[t - 1])
    for t in range(6, 11):
        if k_switch == 0.5:  # t > 5: frozen
            assert torch.equal(b[t], b[t - 1])
        else:
            assert not torch.equal(b[t], b[t - 1])


# ---------------------------------------------------------------------------------------------
# Chaotic PSO
# ---------------------------------------------------------------------------------------------
def _logistic(s, n):
    out = []
    for _ in range(n):
        s = 4.0 * s * (1.0 - s)
        out.append(s)
    return torch.stack(out)


def test_cpso_initial_population_is_logistic_sequence():
    P, seed = 12, 11
    lo = torch.tensor([-1.0, 0.0, 10.0], dtype=D)
    hi = torch.tensor([1.0, 2.0, 30.0], dtype=D)
    rec = Recorder(lambda X: (X ** 2).sum(-1))
    # c1 = c2 = 0, w = 1: the first step is x1 = clip(x0 + v0), exposing the initial velocities.
    res = ChaoticPSO(pop_size=P, max_iter=1, w=1.0, c1=0.0, c2=0.0, v_max=0.1, seed=seed) \
        .minimize(FunctionProblem(rec, lo, hi))
    g = torch.Generator()
    g.manual_seed(seed)
    s0 = torch.rand(3, generator=g, dtype=D)
    bad = torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=D)
    assert float((s0[:, None] - bad).abs().min()) > 1e-3  # so no fixed-point nudge applies
    assert torch.equal(res.extra["chaos_start"], s0)
    seq = _logistic(s0, 2 * P)
    torch.testing.assert_close(rec.batches[0], lo + seq[:P] * (hi - lo), atol=1e-12, rtol=0)
    v0 = (2 * seq[P:] - 1) * 0.1 * (hi - lo)
    torch.testing.assert_close(rec.batches[1], (rec.batches[0] + v0).clamp(lo, hi), atol=1e-12, rtol=0)


def test_logistic_helpers():
    s = torch.tensor([0.0, 0.2501, 0.5, 0.7499, 1.0, 0.3], dtype=D)
    a = avoid_fixed_points(s)
    assert float((a[:5, None] - torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=D)).abs().min()) >= 2e-3 - 1e-15
    assert a[5] == s[5]
    seq = logistic_sequence(a, 50)
    assert seq.shape == (50, 6)
    # Started off the fixed points, no component collapses to a constant.
    assert bool((seq.std(0) > 0.1).all())
    torch.testing.assert_close(logistic_sequence(s[5:], 3), _logistic(s[5:], 3))
    # mu = 2 (the seed's printed value) is not chaotic: the sequence settles at 1/2.
    assert float((logistic_sequence(torch.tensor([0.3], dtype=D), 60, mu=2.0)[-1] - 0.5).abs()) < 1e-12


@pytest.mark.parametrize("radius", [None, 0.02])
def test_cpso_chaotic_replacement_each_iteration(radius):
    P, n_chaos, iters = 10, 7, 6
    rec = Recorder(sphere_fn)
    # w = c1 = c2 = 0: the swarm cannot move, so the only change between iterations is the
    # particle replaced by the best chaotic point.
    res = ChaoticPSO(pop_size=P, max_iter=iters, w=0.0, c1=0.0, c2=0.0, n_chaos=n_chaos,
                     chaos_radius=radius, seed=3).minimize(sphere(rec))
    assert res.n_evals == P + iters * (P + n_chaos) == rec.n_points
    b = rec.batches
    assert [x.shape[0] for x in b] == [P] + [P, n_chaos] * iters
    lo, span = -5.0, 10.0
    seen = b[0]
    for t in range(1, iters + 1):
        swarm, chaos = b[2 * t - 1], b[2 * t]
        seen = torch.cat([seen, swarm])
        gbest = seen[sphere_fn(seen).argmin()]
        z = (gbest - lo) / span
        if radius is None:  # the seed's sequence: logistic iterates from the mapped gbest
            assert float((z[:, None] - torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0], dtype=D)).abs().min()) > 1e-3
            torch.testing.assert_close(chaos, lo + _logistic(z, n_chaos) * span, atol=1e-12, rtol=0)
        else:  # a neighbourhood of gbest
            assert float((chaos - gbest).abs().max()) <= radius * span + 1e-12
        seen = torch.cat([seen, chaos])
        nxt = b[2 * t + 1] if t < iters else None
        if nxt is not None:
            # one particle replaced by a copy (exact: no arithmetic) of the best chaotic point; which one
            # is best is read on fitness values the solver computed in its own batch, so it is
            # checked to rounding, not by index
            changed = (nxt != swarm).any(1)
            assert int(changed.sum()) == 1
            new = nxt[changed][0]
            assert (chaos == new).all(1).any()
            assert float(sphere_fn(new[None])) == pytest.approx(float(sphere_fn(chaos).min()), rel=1e-12)
    assert res.fun == pytest.approx(float(sphere_fn(torch.cat(b)).min()), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# Hybrid
# ---------------------------------------------------------------------------------------------
T = torch.linspace(0, 3, 40, dtype=D)
TRUE = torch.tensor([2.0, 1.3, 0.5], dtype=D)


def curve_residuals(X):
    a, b, c = X[:, 0:1], X[:, 1:2], X[:, 2:3]
    return a * torch.exp(-b * T) + c - (TRUE[0] * torch.exp(-TRUE[1] * T) + TRUE[2])


def curve_problem():
    return LeastSquaresProblem(curve_residuals, torch.tensor([0.0, 0.1, -2.0], dtype=D),
                               torch.tensor([5.0, 5.0, 2.0], dtype=D))


class _StubPolish(Solver):
    """Records where it was started and returns that point: tests the plumbing without LM."""

    name = "_test-stub-polish"
    started_at: list = []

    def __init__(self, *, shift: float = 0.0, **kw):
        super().__init__(**kw)
        self.shift = shift

    def _run(self, problem):
        x = problem.start() + self.shift
        type(self).started_at.append(problem.x0.clone())
        return Result(x=x, fun=float(problem.fitness(x[None])[0]), history=[1.0, 0.5], n_evals=3,
                      n_iter=1, converged=True, message="stub")


@pytest.fixture
def stub_polish():
    """The stub, registered for one test and taken out after: a solver left in the registry would
    be listed by every later test of this process (the command line's --method among them)."""
    from torchcal.optim.base import _REGISTRY

    register(_StubPolish)
    yield _StubPolish
    _REGISTRY.pop(_StubPolish.name.lower(), None)


@pytest.mark.parametrize("shift", [0.0, 1.0])
def test_hybrid_plumbing_with_stub(shift, stub_polish):
    _StubPolish.started_at.clear()
    prob = curve_problem()
    swarm_opts = dict(pop_size=10, max_iter=5)
    res = get_solver("pso+lm", polish="_test-stub-polish", swarm_options=swarm_opts,
                     polish_options={"shift": shift}, seed=4).minimize(prob)
    alone = get_solver("pso", seed=4, **swarm_opts).minimize(prob)
    sw, pol = res.extra["swarm"], res.extra["polish"]
    assert torch.equal(sw.x, alone.x) and sw.history == alone.history  # seed passed through
    torch.testing.assert_close(_StubPolish.started_at[0], alone.x, atol=0, rtol=0)
    assert prob.x0 is None  # the caller's problem is not modified
    assert res.history == alone.history + [1.0, 0.5]
    assert res.n_evals == alone.n_evals + 3 + 1 and res.n_iter == 6
    # shift 0: polish returns the swarm best (ties go to the polish); shift 1: worse, swarm kept.
    assert res.extra["chosen"] == ("polish" if shift == 0.0 else "swarm")
    torch.testing.assert_close(res.x, alone.x, atol=0, rtol=0)
    assert res.fun == alone.fun and pol.message == "stub"


def test_hybrid_reaches_exact_optimum_with_lm():
    try:
        import torchcal.optim.lm  # noqa: F401
    except ImportError:
        pytest.skip("torchcal.optim.lm (LevenbergMarquardt) is not available yet; "
                    "hybrid swarm + LM test skipped")
    prob = curve_problem()
    swarm_opts = dict(pop_size=20, max_iter=30)
    alone = get_solver("pso", seed=0, **swarm_opts).minimize(prob)
    # The swarm alone is only roughly there (fitness ~4e-3, parameters ~4e-2 off).
    assert alone.fun > 1e-5 and float((alone.x - TRUE).abs().max()) > 1e-5
    res = get_solver("hybrid", swarm_options=swarm_opts, seed=0).minimize(prob)
    assert res.extra["chosen"] == "polish"
    assert float((res.x - TRUE).abs().max()) < 1e-9
    assert res.fun < 1e-18
    assert len(res.history) == len(alone.history) + len(res.extra["polish"].history)


# ---------------------------------------------------------------------------------------------
# The in-place iteration against the allocation-based loop it replaced
# ---------------------------------------------------------------------------------------------
def _reference_swarm(problem, *, P, iters, w_of_t, c1, c2, v_max, seed, sizes=None, w2=None, k_switch=None):
    """The PSO / LDPSO-BT loop as it was written before the in-place refactor: every update makes
    new tensors. ``sizes``: LDPSO-BT's population schedule (None: plain PSO)."""
    g = torch.Generator()
    g.manual_seed(seed)
    lo, hi = problem.lower, problem.upper
    vlim = (hi - lo) * (v_max if v_max is not None else 1.0)
    u = torch.rand((2, P, problem.dim), generator=g, dtype=lo.dtype)
    X, V = lo + u[0] * (hi - lo), (2.0 * u[1] - 1.0) * vlim
    if problem.x0 is not None:
        X[0] = problem.clip(problem.x0)

    def ev(Z):
        f = problem.fitness(Z)
        return torch.where(torch.isnan(f), torch.full_like(f, float("inf")), f)

    f = ev(X)
    i = torch.argmin(f)
    pb, pbf, gb, gbf = X.clone(), f.clone(), X[i].clone(), f[i].clone()
    hist = [float(gbf)]
    for t in range(1, iters + 1):
        if sizes is not None and sizes[t - 1] < X.shape[0]:
            keep = torch.argsort(pbf, stable=True)[: sizes[t - 1]].sort().values
            X, V, pb, pbf = X[keep], V[keep], pb[keep], pbf[keep]
        r = torch.rand((2, *X.shape), generator=g, dtype=lo.dtype)
        if k_switch is not None and t > k_switch * iters:
            V = w2 * V + c2 * r[1] * (gb - X)
        else:
            V = w_of_t(t) * V + c1 * r[0] * (pb - X) + c2 * r[1] * (gb - X)
        if v_max is not None:
            V = torch.maximum(torch.minimum(V, vlim), -vlim)
        Xn = X + V
        Xc = torch.maximum(torch.minimum(Xn, hi), lo)
        V = torch.where(Xc != Xn, torch.zeros_like(V), V)
        X = Xc
        f = ev(X)
        better = f < pbf
        pb = torch.where(better[:, None], X, pb)
        pbf = torch.where(better, f, pbf)
        i = torch.argmin(pbf)
        b = pbf[i] < gbf
        gb, gbf = torch.where(b, pb[i], gb), torch.where(b, pbf[i], gbf)
        hist.append(float(gbf))
    return gb, hist


@pytest.mark.parametrize("case", ["pso", "pso-linear-w-no-vmax", "ldpso-bt", "ldpso-bt-x0"])
def test_in_place_iteration_follows_the_allocating_loop(case):
    prob = rastrigin() if "x0" not in case else sphere(x0=torch.full((6,), 0.5, dtype=D))
    if case.startswith("pso"):
        w = (0.9, 0.3) if "linear" in case else 0.8
        vm = None if "no-vmax" in case else 0.2
        solver = PSO(pop_size=17, max_iter=60, w=w, c1=1.4, c2=1.6, v_max=vm, seed=5)
        ref = _reference_swarm(prob, P=17, iters=60, w_of_t=solver.inertia, c1=1.4, c2=1.6, v_max=vm, seed=5)
    else:
        solver = LDPSO_BT(n_max=30, n_min=6, max_iter=70, seed=9)
        ref = _reference_swarm(prob, P=30, iters=70, w_of_t=lambda t: 0.8, c1=1.49, c2=1.49, v_max=0.2, seed=9,
                               sizes=ldpso_pop_sizes(30, 6, 70), w2=0.4, k_switch=0.8)
    res = solver.minimize(prob)
    # the same iteration: in-place kernels on buffer rows and allocating ones on fresh tensors may
    # round the last bit differently (vector body against scalar tail), so the point and the best
    # fitness per iteration agree to 1e-9, far below the swarm's moves (the runs stop at max_iter)
    torch.testing.assert_close(res.x, ref[0], rtol=1e-9, atol=1e-9)
    assert res.history == pytest.approx(ref[1], rel=1e-9, abs=1e-12)


def test_swarm_state_is_never_reallocated():
    """The fitness sees the live rows of the swarm's buffers: one buffer for PSO, two (the live
    one and the spare that a shrink gathers into) for LDPSO-BT, whatever the population size."""
    seen, alive = {}, []

    def fn(X):
        alive.append(X)  # kept alive, so an allocating loop could not reuse freed memory
        seen.setdefault(fn.solver, set()).add(X.data_ptr())
        return sphere_fn(X)

    for solver in (PSO(pop_size=20, max_iter=30), LDPSO_BT(n_max=30, n_min=5, max_iter=40)):
        fn.solver = solver.name
        solver.minimize(FunctionProblem(fn, -5 * torch.ones(6, dtype=D), 5 * torch.ones(6, dtype=D)))
    # + 1: the initial population is evaluated before the buffers exist
    assert len(seen["pso"]) == 1 + 1
    assert len(seen["ldpso-bt"]) == 2 + 1
