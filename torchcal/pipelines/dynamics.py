"""SCARA dynamic identification (seed 001): excitation design (GA and L-BFGS on the regressor's
condition number) and identification of measured torques by least squares, recursive LS, PSO and
the seed's chaotic PSO. The study that simulates torques and compares the methods is
:func:`torchcal.studies.dynamics.study`. Torques in N m, angles in rad, lumped parameters in the
units of :mod:`torchcal.dynamics.scara`."""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import torch

from torchcal.dynamics import excitation as exc
from torchcal.dynamics import scara
from torchcal.optim import get_solver
from torchcal.optim.ga import GeneticAlgorithm
from torchcal.problems import dynamics as idf
from torchcal.problems.excitation import ExcitationProblem

__all__ = ["DynamicsSettings", "SEED_SWARM", "FRICTION_TRUE", "design", "identify_all"]


@dataclass
class DynamicsSettings:
    """What a study varies: the seed, timing repetitions, L-BFGS starts, measurement noise (σ of
    torque N m, position rad, velocity rad/s, acceleration rad/s²), friction, and ``quick`` (one
    repetition, one start, a short GA)."""

    seed: int = 0
    reps: int = 3
    starts: int = 3
    noise_tau: float = 0.1
    noise_q: float = 1e-4
    noise_qd: float = 1e-3
    noise_qdd: float = 1e-2
    friction: bool = False
    quick: bool = False


SEED_SWARM = dict(pop_size=200, max_iter=200, c1=1.3, c2=1.8, w=(0.9, 0.2))  # seed 001
FRICTION_TRUE = dict(fv=(0.8, 0.5), fc=(1.2, 0.7))  # illustrative, used with --friction


def timed(fn):
    """``(fn(), wall-clock seconds)``."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


# -- 1. excitation design ---------------------------------------------------------------------
def design(cfg: DynamicsSettings, friction: bool):
    """Seed 001's excitation design: the GA (seed preset) and L-BFGS from random starts on the
    condition number of the stacked regressor; returns the trajectory model, the problem, the
    optimised and a random design, both solvers' results and a summary ``info``."""
    ex = exc.FourierExcitation.from_robot("scara")
    reg = lambda q, qd, qdd: scara.regressor(q, qd, qdd, friction)  # noqa: E731
    prob = ExcitationProblem(ex, reg)
    g = torch.Generator().manual_seed(cfg.seed)
    X_rand = ex.random(100, g)
    c_rand = prob.fitness(X_rand)

    ga_opts = dict(GeneticAlgorithm.PRESETS["seed001"], max_iter=40 if cfg.quick else 200)
    ga, t_ga = timed(lambda: get_solver("ga", seed=cfg.seed, **ga_opts).minimize(prob))

    # L-BFGS from the first random designs (the first is also the "random start" reported)
    grads, t_grad = [], 0.0
    for i in range(1 if cfg.quick else cfg.starts):
        p_i = ExcitationProblem(ex, reg, x0=X_rand[i])
        r, dt = timed(lambda: get_solver("lbfgs", max_iter=100).minimize(p_i))
        grads.append(r)
        t_grad += dt
    grad = min(grads, key=lambda r: r.fun)

    best = ga if ga.fun <= grad.fun else grad
    x_opt = prob.decode(best.x[None])[0]
    x_rand = X_rand[0]
    fine = ex.times(20 * ex.n_samples)
    info = {
        "cond_random": float(c_rand.median()), "cond_random_min": float(c_rand.min()),
        "cond_random_start": float(c_rand[0]),
        "cond_ga": ga.fun, "cond_gradient": grad.fun, "cond_optimised": best.fun,
        "design_method": "ga" if best is ga else "lbfgs",
        "ga_time_s": t_ga, "gradient_time_s": t_grad, "gradient_starts": len(grads),
        "design_violation": float(ex.violation(x_opt[None], fine)[0]),
    }
    return ex, prob, x_opt, x_rand, ga, grads, info


# -- 3. identification -----------------------------------------------------------------------
def identify_all(train, box, cfg: DynamicsSettings):
    """LS, RLS, PSO and chaotic PSO on the torque fit of ``train``, interleaved ``cfg.reps`` times
    for the timings; returns the problem, each method's ``(ξ, Result or None)`` and median times (s)."""
    lo, hi = box
    problem = idf.TorqueFitProblem(train["W"], train["tau_meas"], lo, hi)
    methods = {
        "ls": lambda: (idf.ols(train["W"], train["tau_meas"]), None),
        "rls": lambda: (idf.rls(train["W"], train["tau_meas"])[0], None),
        "pso": lambda: (lambda r: (r.x, r))(get_solver("pso", seed=cfg.seed, **SEED_SWARM).minimize(problem)),
        "cpso": lambda: (lambda r: (r.x, r))(get_solver("cpso", seed=cfg.seed, mu=4.0,
                                                        **SEED_SWARM).minimize(problem)),
    }
    times = {m: [] for m in methods}
    out = {}
    names = list(methods)
    for rep in range(1 if cfg.quick else cfg.reps):
        for m in names[rep % len(names):] + names[:rep % len(names)]:
            (x, res), dt = timed(methods[m])
            times[m].append(dt)
            out.setdefault(m, (x, res))
    return problem, out, {m: statistics.median(v) for m, v in times.items()}
