#!/usr/bin/env python
"""Seed 001: SCARA dynamic-parameter identification with chaotic PSO, and excitation design.

Steps (all on the Adept Cobra s600 of ``torchcal.kinematics.robots``; its masses, COMs and inertias are
ILLUSTRATIVE, not published):

1. **Excitation design.** Fourier series, N = 3 harmonics per joint (7 coefficients), base
   frequency ω_f = 2π·0.2 rad/s (5 s period), limits: DH position limits less 10° per side, half
   the rated joint speed, accelerations 10 / 20 rad/s² (assumed). Objective: condition number of
   the stacked six-column regressor over one period (500 samples). Optimised with the shared GA
   (seed settings pc 0.5, pm 0.2; population 30, 200 generations) and with L-BFGS (autograd) from
   ``--starts`` random feasible starts; the better design is used. Baseline: the median over 100
   random feasible Fourier trajectories.
2. **Data.** Torques from the true ξ along two periods of the design (1000 samples at 100 Hz),
   Gaussian noise σ_τ on torques and σ_q, σ_q̇, σ_q̈ on the joint states used to build the
   regressor (defaults 0.1 N·m, 1e-4 rad, 1e-3 rad/s, 1e-2 rad/s²).
3. **Identification:** ordinary least squares, recursive least squares (λ = 1, P₀ = 1e6 I),
   PSO and chaotic PSO with the seed's settings (population 200, c1 1.3, c2 1.8, w 0.9 → 0.2,
   200 iterations; CPSO: logistic map with μ = 4 — the seed prints μ = 2, which is not chaotic).
   Swarm fitness: torque RMSE (N·m); bounds: the physical box of
   :func:`torchcal.problems.dynamics.physical_box`.
4. **Validation** on a fresh random feasible Fourier trajectory (different seed, 1000 samples):
   torque RMSE against the noisy measured torques (``*_torque_rmse``, what one can measure) and
   against the noise-free torques (``*_torque_rmse_true``, model error only).

Timing: one torch thread; the four methods are run ``--reps`` times interleaved (order rotated)
and the median is reported; the solvers are seeded, so every repetition gives the same estimate.

Outputs in ``--out`` (default ``out/seed001/``): ``fig2_excitation.png``, ``fig_design.png``,
``fig3_fitness.png``, ``fig4_torque.png``, ``fig5_torque_error.png``, ``results.json``; a table
on stdout and, last, one JSON line.

Usage: python scripts/seed001_scara_cpso.py [--out out/seed001] [--seed 0] [--reps 3]
       [--starts 3] [--friction] [--quick]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from torchcal.pipelines.dynamics import DynamicsSettings
from torchcal.studies.dynamics import study


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="out/seed001")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reps", type=int, default=3, help="timing repetitions (interleaved)")
    ap.add_argument("--starts", type=int, default=3, help="L-BFGS random starts")
    ap.add_argument("--noise-tau", type=float, default=0.1, help="torque noise σ, N·m")
    ap.add_argument("--noise-q", type=float, default=1e-4, help="position noise σ, rad")
    ap.add_argument("--noise-qd", type=float, default=1e-3, help="velocity noise σ, rad/s")
    ap.add_argument("--noise-qdd", type=float, default=1e-2, help="acceleration noise σ, rad/s²")
    ap.add_argument("--friction", action="store_true", help="add viscous + Coulomb friction")
    ap.add_argument("--quick", action="store_true", help="1 rep, 1 start, short GA (smoke test)")
    return ap.parse_args()


# -- figures ---------------------------------------------------------------------------------
def figures(out_dir, ex, x_opt, x_rand, ga, grads, results, val, xi_hat, ls_fit, info):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = ex.times(1000)
    qo, qdo, qddo = ex.evaluate(x_opt, t)
    qr, qdr, qddr = ex.evaluate(x_rand, t)
    fig, ax = plt.subplots(3, 2, figsize=(10, 8), sharex=True)
    lims = [(ex.q_lower, ex.q_upper), (-ex.qd_max, ex.qd_max), (-ex.qdd_max, ex.qdd_max)]
    labels = ["angle (rad)", "velocity (rad/s)", "acceleration (rad/s²)"]
    for r, (opt, rnd) in enumerate([(qo, qr), (qdo, qdr), (qddo, qddr)]):
        for j in range(2):
            a = ax[r, j]
            a.plot(t, opt[:, j], "C0", label=f"optimised (cond {info['cond_optimised']:.3f})")
            a.plot(t, rnd[:, j], "C1", lw=0.8, alpha=0.7,
                   label=f"random (cond {info['cond_random_start']:.2f})")
            for v in (lims[r][0][j], lims[r][1][j]):
                a.axhline(float(v), color="k", ls="--", lw=0.7)
            a.set_ylabel(labels[r])
            if r == 0:
                a.set_title(f"joint {j + 1}")
            if r == 2:
                a.set_xlabel("t (s)")
    ax[0, 0].legend(fontsize=8, loc="lower right")
    fig.suptitle("Fig. 2 — excitation trajectories (Fourier, N = 3, ω_f = 2π·0.2 rad/s); dashed: limits")
    fig.tight_layout()
    fig.savefig(out_dir / "fig2_excitation.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.semilogy(ga.history, label=f"GA pc 0.5 pm 0.2 ({info['ga_time_s']:.1f} s)")
    for i, r in enumerate(grads):
        ax.semilogy(r.history, lw=0.8, label=f"L-BFGS start {i + 1}" + (
            f" (total {info['gradient_time_s']:.1f} s)" if i == 0 else ""))
    ax.axhline(info["cond_random"], color="k", ls=":", label="random (median of 100)")
    ax.set_xlabel("generation / iteration")
    ax.set_ylabel("cond(W)")
    ax.legend(fontsize=8)
    ax.set_title("Excitation design: condition number")
    fig.tight_layout()
    fig.savefig(out_dir / "fig_design.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    styles = {"pso": ("PSO", "C0", "-"), "cpso": ("CPSO (μ = 4)", "C3", "-"),
              "cpso_mu2": ("CPSO, seed's μ = 2", "C2", ":")}
    for m, (lab, col, ls) in styles.items():
        h = torch.tensor(results[m][1].history, dtype=torch.float64)
        ax[0].semilogy(h, color=col, ls=ls, label=lab)
        ax[1].semilogy((h / ls_fit - 1).clamp_min(1e-16), color=col, ls=ls, label=lab)
    ax[0].axhline(ls_fit, color="k", ls="--", label=f"least squares ({ls_fit:.4f} N·m)")
    ax[0].set_ylabel("fitness: torque RMSE (N·m)")
    ax[1].axhline(0.01, color="k", ls="--", lw=0.8, label="1 % above least squares")
    ax[1].set_ylabel("fitness / least-squares fitness − 1")
    for a in ax:
        a.set_xlabel("iteration")
        a.legend(fontsize=8)
    fig.suptitle("Fig. 3 — best fitness per iteration (pop 200, c1 1.3, c2 1.8, w 0.9→0.2)")
    fig.tight_layout()
    fig.savefig(out_dir / "fig3_fitness.png", dpi=120)
    plt.close(fig)

    tv = val["t"]
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for j in range(2):
        ax[j].plot(tv, val["tau_meas"][:, j], ".", ms=2, color="0.6", label="measured")
        ax[j].plot(tv, val["tau"][:, j], "k", lw=1, label="actual model")
        ax[j].plot(tv, (val["W_true"] @ xi_hat["cpso"])[:, j], "C3--", lw=1, label="identified (CPSO)")
        ax[j].set_ylabel(f"τ{j + 1} (N·m)")
    ax[0].legend(fontsize=8)
    ax[1].set_xlabel("t (s)")
    fig.suptitle("Fig. 4 — validation torques: actual model vs CPSO-identified model")
    fig.tight_layout()
    fig.savefig(out_dir / "fig4_torque.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for j in range(2):
        for i, m in enumerate(("ls", "rls", "pso", "cpso", "ls3")):
            e = (val["W_true"] @ xi_hat[m] - val["tau"])[:, j]
            lab = "LS, ties imposed (3 base parameters)" if m == "ls3" else m.upper()
            ax[j].plot(tv, e, lw=1, ls=["-", "--", "-.", ":", "-"][i], label=lab)
        ax[j].set_ylabel(f"error τ{j + 1} (N·m)")
    ax[0].legend(fontsize=8, ncol=3)
    ax[1].set_xlabel("t (s)")
    fig.suptitle("Fig. 5 — torque error per joint on the validation trajectory (vs noise-free model)")
    fig.tight_layout()
    fig.savefig(out_dir / "fig5_torque_error.png", dpi=120)
    plt.close(fig)


def main() -> None:
    args = parse()
    torch.set_num_threads(1)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = DynamicsSettings(**{k: v for k, v in vars(args).items() if k != "out"})
    r = study(cfg)
    res, summary, ls3, xi, xi_hat, names, results, box = (r[k] for k in ("res", "summary", "ls3", "xi", "xi_hat",
                                                                          "names", "results", "box"))
    info, train, val, rows, x_opt = r["info"], r["train"], r["val"], r["rows"], r["x_opt"]
    xi_ls3 = xi_hat["ls3"]
    figures(out_dir, r["ex"], x_opt, r["x_rand"], r["ga"], r["grads"], results, val, xi_hat, r["ls_fit"], info)

    # -- report -----------------------------------------------------------------------------
    print(f"Excitation: cond random median {info['cond_random']:.3f} (best of 100 "
          f"{info['cond_random_min']:.3f}), GA {info['cond_ga']:.4f} in {info['ga_time_s']:.2f} s, "
          f"L-BFGS {info['cond_gradient']:.6f} in {info['gradient_time_s']:.2f} s "
          f"({info['gradient_starts']} starts); used: {info['design_method']}; "
          f"max limit violation on a 20x grid {info['design_violation']:.1e}")
    print(f"Noise: torque {args.noise_tau} N·m, q {args.noise_q} rad, qd {args.noise_qd} rad/s, "
          f"qdd {args.noise_qdd} rad/s²; training {train['t'].numel()} samples, validation "
          f"{val['t'].numel()}")
    print(f"{'':6s}" + "".join(f"{n:>9s}" for n in names) + f"{'fit':>9s}{'val':>9s}{'val*':>9s}{'time s':>8s}")
    print(f"{'true':6s}" + "".join(f"{float(v):9.4f}" for v in xi))
    for m in rows:
        s = summary[m]
        print(f"{m:6s}" + "".join(f"{float(v):9.4f}" for v in xi_hat[m])
              + f"{s['fit_rmse']:9.5f}{s['torque_rmse']:9.5f}{s['torque_rmse_true']:9.5f}{s['time_s']:8.3f}")
    print(f"{'ls3':6s}" + "".join(f"{float(v):9.4f}" for v in xi_ls3)
          + f"{'':9s}{ls3['torque_rmse']:9.5f}{ls3['torque_rmse_true']:9.5f}")
    print("fit: training torque RMSE (the swarm fitness); val: validation RMSE vs measured torques; "
          "val*: vs noise-free torques (N·m). ls3: LS on the 3 base parameters (ties imposed).")
    for m in rows:
        print(f"{m:6s} param error %: " + " ".join(f"{v:6.2f}" for v in summary[m]["param_err_pct"]))

    (out_dir / "results.json").write_text(json.dumps(
        {"summary": res, "per_method": summary, "ls3": ls3, "xi_true": xi.tolist(),
         "xi_hat": {m: v.tolist() for m, v in xi_hat.items()}, "names": names,
         "history": {m: results[m][1].history for m in ("pso", "cpso", "cpso_mu2")},
         "bounds": [box[0].tolist(), box[1].tolist()], "x_opt": x_opt.tolist()}, indent=1))
    print(json.dumps(res))


if __name__ == "__main__":
    main()
