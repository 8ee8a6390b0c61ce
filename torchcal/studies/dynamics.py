"""SCARA dynamic identification (seed 001) as a study: design an excitation, simulate torques along
the optimised and a random trajectory, identify them by LS, RLS, PSO and chaotic PSO
(:mod:`torchcal.pipelines.dynamics`), and validate on a fresh trajectory.
``scripts/seed001_scara_cpso.py`` prints and plots what :func:`study` returns. Torques in N m,
angles in rad, lumped parameters in the units of :mod:`torchcal.dynamics.scara`."""
from __future__ import annotations

import torch

from torchcal.dynamics import scara
from torchcal.optim import get_solver
from torchcal.pipelines.dynamics import FRICTION_TRUE, SEED_SWARM, DynamicsSettings, design, identify_all
from torchcal.problems import dynamics as idf
from torchcal.sim.scara import simulate

__all__ = ["study"]


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
