"""SCARA dynamic identification (seed 001) as a pipeline: excitation design (GA and L-BFGS on the
regressor's condition number), simulated torques along the optimised and a random trajectory,
identification by least squares, recursive LS, PSO and the seed's chaotic PSO, and validation on
a fresh trajectory. ``scripts/seed001_scara_cpso.py`` prints and plots what :func:`study` returns.
Torques in N m, angles in rad, lumped parameters in the units of :mod:`torchcal.dynamics.scara`."""
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
from torchcal.sim.scara import simulate

__all__ = ["DynamicsSettings", "SEED_SWARM", "FRICTION_TRUE", "design", "identify_all", "study"]


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


def study(cfg: DynamicsSettings) -> dict:
    """The whole seed-001 study for ``cfg``: design, data, identification, validation, extras.
    Returns the per-method ``summary``, the headline ``res`` (what the script prints as JSON) and
    everything the figures need."""
    friction = cfg.friction
    truth = scara.PlanarParams.from_robot("scara", **(FRICTION_TRUE if friction else {}))
    xi = scara.lumped(truth, friction)
    names = list(scara.SEED_NAMES) + (list(scara.FRICTION_NAMES) if friction else [])
    box = idf.physical_box(friction_max=(5.0, 5.0) if friction else None)

    ex, _, x_opt, x_rand, ga, grads, info = design(cfg, friction)

    g = torch.Generator().manual_seed(cfg.seed + 1000)
    train = simulate(ex, x_opt, xi, friction, cfg, g)
    x_val = ex.random(1, torch.Generator().manual_seed(cfg.seed + 2000))[0]
    val = simulate(ex, x_val, xi, friction, cfg, g)

    problem, results, times = identify_all(train, box, cfg)
    xi_hat = {m: results[m][0] for m in results}
    ls_fit = float(problem.fitness(xi_hat["ls"][None])[0])
    # ties imposed: the three base parameters (linear too, so LS is again exact)
    Wb = lambda d: d["W"][..., :6] @ scara.BASE_TO_SEED  # noqa: E731
    wb_train = torch.cat([Wb(train), train["W"][..., 6:]], -1)
    beta = idf.ols(wb_train, train["tau_meas"])
    xi_ls3 = torch.cat([scara.BASE_TO_SEED @ beta[:3], beta[3:]])

    # Extras (not timed): the seed's printed mu = 2 (its logistic map collapses onto 1/2, so the
    # "chaotic" initial swarm degenerates), and both swarms on the random, worse-conditioned design.
    mu2 = get_solver("cpso", seed=cfg.seed, mu=2.0, **SEED_SWARM).minimize(problem)
    rnd = simulate(ex, x_rand, xi, friction, cfg, g)
    p_rnd = idf.TorqueFitProblem(rnd["W"], rnd["tau_meas"], *box)
    f_rnd_ls = float(p_rnd.fitness(idf.ols(rnd["W"], rnd["tau_meas"])[None])[0])
    extras = {"cpso_mu2_vs_ls_fit_pct": 100 * (mu2.fun / ls_fit - 1),
              "random_design_cond": info["cond_random_start"]}
    for m, opts in (("pso", {}), ("cpso", {"mu": 4.0})):
        r = get_solver(m, seed=cfg.seed, **opts, **SEED_SWARM).minimize(p_rnd)
        extras[f"random_design_{m}_vs_ls_fit_pct"] = 100 * (r.fun / f_rnd_ls - 1)
    results["cpso_mu2"] = (mu2.x, mu2)

    summary = {}
    rows = []
    for m in ("ls", "rls", "pso", "cpso"):
        x = xi_hat[m]
        rel = (x - xi).abs() / xi.abs() * 100
        summary[m] = {
            "fit_rmse": float(problem.fitness(x[None])[0]),
            "torque_rmse": float(idf.torque_rmse(val["W"], val["tau_meas"], x)),
            "torque_rmse_true": float(idf.torque_rmse(val["W_true"], val["tau"], x)),
            "torque_rmse_joint": idf.torque_rmse(val["W"], val["tau_meas"], x, per_joint=True).tolist(),
            "param_err_pct": rel.tolist(),
            "time_s": times[m],
            "dist_to_ls": float((x - xi_hat["ls"]).norm() / xi_hat["ls"].norm()),
        }
        rows.append(m)
    ls3 = {"torque_rmse": float(idf.torque_rmse(val["W"], val["tau_meas"], xi_ls3)),
           "torque_rmse_true": float(idf.torque_rmse(val["W_true"], val["tau"], xi_ls3)),
           "param_err_pct": ((xi_ls3 - xi).abs() / xi.abs() * 100).tolist()}

    xi_hat["ls3"] = xi_ls3
    res = {
        **{f"{m}_torque_rmse": summary[m]["torque_rmse"] for m in rows},
        **{f"{m}_torque_rmse_true": summary[m]["torque_rmse_true"] for m in rows},
        **{f"{m}_fit_rmse": summary[m]["fit_rmse"] for m in rows},
        **{f"{m}_time_s": summary[m]["time_s"] for m in rows},
        **{f"{m}_param_err_max_pct": max(summary[m]["param_err_pct"]) for m in rows},
        "ls3_torque_rmse": ls3["torque_rmse"], "ls3_torque_rmse_true": ls3["torque_rmse_true"],
        **extras,
        "cpso_vs_ls_fit_pct": 100 * (summary["cpso"]["fit_rmse"] / summary["ls"]["fit_rmse"] - 1),
        "pso_vs_ls_fit_pct": 100 * (summary["pso"]["fit_rmse"] / summary["ls"]["fit_rmse"] - 1),
        "cpso_vs_ls_val_pct": 100 * (summary["cpso"]["torque_rmse"] / summary["ls"]["torque_rmse"] - 1),
        **info,
        "noise": {"tau": cfg.noise_tau, "q": cfg.noise_q, "qd": cfg.noise_qd, "qdd": cfg.noise_qdd},
        "friction": friction, "seed": cfg.seed, "mu": 4.0,
    }
    return dict(res=res, summary=summary, ls3=ls3, xi=xi, xi_hat=xi_hat, names=names, results=results, box=box,
                x_opt=x_opt, x_rand=x_rand, ex=ex, ga=ga, grads=grads, info=info, val=val, train=train, ls_fit=ls_fit,
                rows=rows)
