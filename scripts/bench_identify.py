#!/usr/bin/env python
"""Identification speed: torchcal's Levenberg-Marquardt against scipy.optimize.least_squares
(method="lm", MINPACK) on the same KR5 arc calibration problem, in the same run.

The problem (seed 000's setting): the KUKA KR5 arc built from its classic DH table, 24 DH
errors (Δa, Δd, Δα, Δθ per row) drawn uniformly in ±0.25 mm (lengths) / ±0.05 rad (angles)
from a seeded generator, 30 random poses, position-only measurements of the flange origin in
the robot base frame (base frame and flange offsets fixed at their true value, zero). Only 19
of the 24 DH errors are identifiable from flange positions (Δd3 duplicates Δd2, Δα5/Δθ5 tie with
Δd5/Δa5 and Δα6/Δθ6 do not move the flange origin), so both solvers are given the identifiable
subset that :func:`torchcal.problems.identifiability.identifiability` picks: a full-rank problem. The
dropped errors keep their true non-zero values in the simulated robot and are absorbed by the
identified ones, so even the noise-free fit leaves a small residual. Variants: noise-free, and
0.02 mm Gaussian noise per axis.

Peers, with the *same* residual function ``problem.residuals`` and the same start (zero):

* ``scipy``: ``least_squares(fun, x0, method="lm")`` with its default finite-difference
  Jacobian, as a scipy user would call it;
* ``scipy_jac``: the same, given torchcal's analytic Jacobian ``problem.jacobian``.

The headline ``lm`` is LM as ``torchcal.calibrate()`` runs it (``tau=1e-6``). Two option settings
are timed alongside for the record: ``lm_tau3`` (the former generic default ``tau=1e-3``) and ``lm_tau6_2pt``
(also ``jac="2-point"``: forward differences as one batched residuals call of k+1 points).
Call counts are reported per solver: residual points, Jacobians, and ``problem.fitness`` calls.

Tolerances: xtol = ftol = gtol = 1e-10 on both sides (``--tol``). They are not the same tests
(scipy/MINPACK: gtol on the cosine between r and J's columns, xtol on the scaled step, ftol on
the relative reduction; torchcal: gtol on ``||Jᵀr||_inf`` in m², xtol on ``||h|| / ||x||``, ftol
on the relative reduction), so we check the outcome instead: the final sum of squares and the
"final error" (max per-axis position error, mm, of the identified vs the true robot on 200
fresh poses) must agree between the solvers (reported, and ``same_accuracy`` says whether they
agree to 1e-6 mm).

Timing: every run is timed on its own (``time.perf_counter``), the solvers are interleaved
(order rotated every repetition), one warm-up each, median of ``--reps`` runs; one torch thread
(the machine is shared; small problems only lose from a second thread). Scaling: LM time for
30 / 300 / 3000 poses, and for several parameter sets (DH 19, URDF joint-origin errors reduced
to their identifiable subset, and 3-marker variants of both).

Prints a small table, then one JSON line (the last line of stdout).

Usage: python scripts/bench_identify.py [--reps 15] [--tol 1e-10] [--seed 0] [--quick] [--profile]
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal import Robot  # noqa: E402
from torchcal.problems.identifiability import identifiability  # noqa: E402
from torchcal.measure.data import Measurements  # noqa: E402
from torchcal.optim import get_solver  # noqa: E402
from torchcal.problems.calibration import CalibrationProblem  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402
from torchcal.sim.serial import random_configs  # noqa: E402

D = torch.float64
LEN_ERR, ANG_ERR = 0.25e-3, 0.05  # uniform half-widths: m, rad
THREE_MARKERS = ["flange", "m2@flange=0.1,0,0", "m3@flange=0,0.1,0"]
# The headline "lm" is LM as torchcal.calibrate() runs it: tau = 1e-6 (torchcal.damping.TAU, the one
# default: mu0 = tau with Marquardt scaling, a value for a good start; calibrate() starts at the
# registered point). Timed alongside: the former generic default tau = 1e-3 ("lm_tau3", ~3 more
# iterations here) and the batched forward-difference Jacobian (k+1 points in one residuals()
# call), which is cheaper than the analytic one at this size.
CALIBRATE_LM = {"tau": 1e-6}
LM_EXTRA = {"lm_tau3": {"tau": 1e-3}, "lm_tau6_2pt": {"tau": 1e-6, "jac": "2-point"}}


# ----------------------------------------------------------------------------- problem setup
class Case:
    """A calibration problem with known truth, and what is needed to score a solution."""

    def __init__(self, robot: Robot, error_patterns: list[str], n_poses: int, noise_m: float, seed: int,
                 n_test: int = 200):
        self.robot = robot
        g = torch.Generator().manual_seed(seed)
        ps = robot.params().only(*error_patterns)  # base and marker offsets stay fixed at zero
        amp = torch.tensor([LEN_ERR if u == "m" else ANG_ERR for u in ps.units], dtype=D)
        u = torch.rand(len(ps), generator=g, dtype=D) * 2 - 1
        self.truth = torch.where(ps.free, u * amp, torch.zeros_like(u))
        self.n_errors = int(ps.free.sum())
        q = random_configs(robot, n_poses, g)
        self.q_test = random_configs(robot, n_test, g)
        p = robot.positions(q, self.truth)
        p = p + noise_m * torch.randn(p.shape, generator=g, dtype=D)
        data = Measurements(q, p, list(robot.marker_names), list(robot.joint_names))
        # identify only what the poses can identify (at the nominal parameters): full rank
        self.report = identifiability(robot, q, free=ps)
        ps.free[:] = False
        for n in self.report.identifiable:
            ps.free[ps.index(n)] = True
        self.params = ps
        self.problem = CalibrationProblem(robot, ps, data)
        self.k, self.m = self.problem.dim, self.problem.m
        self.p_true_test = robot.positions(self.q_test, self.truth)

    def max_err_mm(self, x) -> float:
        """Max per-axis position error (mm) on the fresh poses, identified vs true robot."""
        full = self.problem.full(torch.as_tensor(x, dtype=D))
        return 1e3 * float((self.robot.positions(self.q_test, full) - self.p_true_test).abs().max())


def kr5_dh(n_poses: int, noise_m: float, seed: int, markers=None) -> Case:
    return Case(shipped("kuka_kr5_arc", source="dh", markers=markers or ["flange"]),
                ["joint_*.da", "joint_*.dd", "joint_*.dalpha", "joint_*.dtheta"], n_poses, noise_m, seed)


def kr5_urdf(n_poses: int, noise_m: float, seed: int, markers=None) -> Case:
    robot = Robot.from_urdf(ROOT / "urdf" / "kuka_kr5_arc.urdf", markers=markers or ["flange"])
    # six origin errors per joint (joint_a1..a6) plus the zero offsets; base and flange fixed
    return Case(robot, ["joint_a*"], n_poses, noise_m, seed)


# ----------------------------------------------------------------------------- solvers
def make_runners(case: Case, tol: float, extra: bool = True) -> dict:
    prob = case.problem
    x0 = prob.start().numpy()
    calls = [0, 0]  # residual and Jacobian calls scipy makes (its nfev leaves out the FD calls)

    def fun(x):
        calls[0] += 1
        return prob.residuals(torch.as_tensor(x)[None])[0].numpy()

    def jac(x):
        calls[1] += 1
        return prob.jacobian(torch.as_tensor(x)).numpy()

    def lm_with(**opts):
        solver = get_solver("lm", gtol=tol, xtol=tol, ftol=tol, **opts)

        def run():
            res = solver.minimize(prob)
            return res.x.numpy(), 2 * res.extra["cost"], {"n_iter": res.n_iter, "n_res": res.n_evals,
                                                          "n_jac": res.extra["n_jac"], "message": res.message}
        return run

    def sp():
        calls[:] = [0, 0]
        s = least_squares(fun, x0, method="lm", xtol=tol, ftol=tol, gtol=tol)
        return s.x, 2 * s.cost, {"nfev": s.nfev, "status": s.status, "n_res": calls[0], "n_jac": 0}

    def sp_jac():
        calls[:] = [0, 0]
        s = least_squares(fun, x0, jac=jac, method="lm", xtol=tol, ftol=tol, gtol=tol)
        return s.x, 2 * s.cost, {"nfev": s.nfev, "njev": s.njev, "status": s.status, "n_res": calls[0],
                                 "n_jac": calls[1]}

    runners = {"lm": lm_with(**CALIBRATE_LM), "scipy": sp, "scipy_jac": sp_jac}
    if extra:  # option settings, not defaults: what the defaults leave on the table
        runners.update({name: lm_with(**opts) for name, opts in LM_EXTRA.items()})
    return runners


def time_interleaved(runners: dict, reps: int) -> dict[str, list[float]]:
    """Seconds per run for each runner, interleaved (order rotated every repetition)."""
    names = list(runners)
    for n in names:  # warm-up
        runners[n]()
    times = {n: [] for n in names}
    for i in range(reps):
        for n in names[i % len(names):] + names[: i % len(names)]:
            t = time.perf_counter()
            runners[n]()
            times[n].append(time.perf_counter() - t)
    return times


def med_ms(ts: list[float]) -> float:
    return 1e3 * statistics.median(ts)


def compare(case: Case, tol: float, reps: int) -> dict:
    runners = make_runners(case, tol)
    out = {"n_poses": case.problem.m // 3, "k": case.k, "m": case.m}
    xs = {}
    for n, f in runners.items():
        # count problem.fitness calls (LM calls it after each accepted step); untimed run
        nfit = [0]

        def fitness(X, _orig=case.problem.fitness):
            nfit[0] += 1
            return _orig(X)
        case.problem.fitness = fitness
        try:
            x, sse, info = f()
        finally:
            del case.problem.fitness
        info["n_fitness"] = nfit[0]
        xs[n] = x
        out[f"{n}_sse_m2"] = sse
        out[f"{n}_max_err_mm"] = case.max_err_mm(x)
        out[f"{n}_info"] = info
    times = time_interleaved(runners, reps)
    for n, ts in times.items():
        out[f"{n}_time_ms"] = med_ms(ts)
        out[f"{n}_time_ms_iqr"] = [1e3 * float(np.percentile(ts, 25)), 1e3 * float(np.percentile(ts, 75))]
    out["speedup"] = out["scipy_time_ms"] / out["lm_time_ms"]
    out["speedup_vs_scipy_jac"] = out["scipy_jac_time_ms"] / out["lm_time_ms"]
    for n in runners:
        if n.startswith("lm_"):
            out[f"speedup_{n}"] = out["scipy_time_ms"] / out[f"{n}_time_ms"]
            out[f"speedup_vs_scipy_jac_{n}"] = out["scipy_jac_time_ms"] / out[f"{n}_time_ms"]
    out["max_param_diff_vs_scipy"] = float(np.abs(xs["lm"] - xs["scipy"]).max())
    out["max_param_diff_vs_scipy_jac"] = float(np.abs(xs["lm"] - xs["scipy_jac"]).max())
    errs = [out[f"{n}_max_err_mm"] for n in ("lm", "scipy", "scipy_jac")]
    out["same_accuracy"] = bool(max(errs) - min(errs) < 1e-6)
    errs_all = [out[f"{n}_max_err_mm"] for n in runners]
    out["same_accuracy_incl_lm_options"] = bool(max(errs_all) - min(errs_all) < 1e-6)
    return out


def lm_interleaved(cases: dict[str, Case], tol: float, reps: int) -> dict[str, dict]:
    """LM (defaults) on several problems, timed interleaved: time, error and evaluation counts."""
    runners = {name: make_runners(c, tol, extra=False)["lm"] for name, c in cases.items()}
    rows = {}
    for name, r in runners.items():
        x, _, info = r()
        c = cases[name]
        rows[name] = {"k": c.k, "m": c.m, "n_errors": c.n_errors, "lm_max_err_mm": c.max_err_mm(x),
                      "lm_n_iter": info["n_iter"], "lm_n_jac": info["n_jac"]}
    for name, ts in time_interleaved(runners, reps).items():
        rows[name]["lm_time_ms"] = med_ms(ts)
    return rows


def profile_lm(case: Case, tol: float, n: int = 20) -> None:
    """cProfile of ``n`` LM solves, top entries by own time, to stderr."""
    import cProfile
    import io
    import pstats

    run = make_runners(case, tol, extra=False)["lm"]
    run()
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(n):
        run()
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(20)
    s2 = io.StringIO()
    pstats.Stats(pr, stream=s2).sort_stats("cumulative").print_stats(25)
    print(s.getvalue(), s2.getvalue(), file=sys.stderr)


# ----------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--tol", type=float, default=1e-10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, no 3000-pose scaling run")
    ap.add_argument("--profile", action="store_true", help="cProfile LM on the KR5 problem (stderr)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    reps = 5 if args.quick else args.reps
    tol = args.tol

    out = {"problem": "KR5 arc DH, 24 DH errors uniform +-0.25 mm / +-0.05 rad, 30 poses, flange position only, "
                      "base fixed; identifiable subset solved (full rank)",
           "tolerances": {"xtol": tol, "ftol": tol, "gtol": tol}, "reps": reps, "threads": args.threads,
           "torch": torch.__version__, "scipy": scipy.__version__, "numpy": np.__version__,
           "python": platform.python_version(), "machine": platform.machine()}

    base = kr5_dh(30, 0.0, args.seed)
    out["n_errors"] = base.n_errors
    out["rank"] = base.report.rank
    out["identified"] = base.report.identifiable
    out["dropped"] = base.report.dropped
    if args.profile:
        profile_lm(base, tol)

    variants = {"noise_free": base, "noisy_0.02mm": kr5_dh(30, 0.02e-3, args.seed)}
    out["variants"] = {name: compare(c, tol, reps) for name, c in variants.items()}
    main_v = out["variants"]["noise_free"]
    for key in ("lm_time_ms", "scipy_time_ms", "scipy_jac_time_ms", "speedup", "speedup_vs_scipy_jac",
                "lm_max_err_mm", "scipy_max_err_mm", "scipy_jac_max_err_mm", "same_accuracy"):
        out[key] = main_v[key]
    out["speedup_noisy"] = out["variants"]["noisy_0.02mm"]["speedup"]
    out["speedup_vs_scipy_jac_noisy"] = out["variants"]["noisy_0.02mm"]["speedup_vs_scipy_jac"]
    out["target_3x_vs_scipy"] = bool(min(out["speedup"], out["speedup_noisy"]) >= 3)
    out["target_3x_vs_scipy_jac"] = bool(min(out["speedup_vs_scipy_jac"], out["speedup_vs_scipy_jac_noisy"]) >= 3)
    for n in LM_EXTRA:  # option settings, for the record
        out[f"{n}_time_ms"] = main_v[f"{n}_time_ms"]
        out[f"speedup_{n}"] = main_v[f"speedup_{n}"]
        out[f"speedup_vs_scipy_jac_{n}"] = main_v[f"speedup_vs_scipy_jac_{n}"]

    # scaling with the number of poses (noise-free DH problem, 19 parameters): LM alone,
    # interleaved across pose counts; then each pose count against the scipy peers (own loop)
    counts = (30, 300) if args.quick else (30, 300, 3000)
    pose_cases = {str(n): base if n == 30 else kr5_dh(n, 0.0, args.seed) for n in counts}
    lm_rows = lm_interleaved(pose_cases, tol, reps)
    out["lm_time_ms_by_poses"] = {n: r["lm_time_ms"] for n, r in lm_rows.items()}
    scal_rows = {}
    for n, c in pose_cases.items():
        res = main_v if n == "30" else compare(c, tol, max(3, reps // 3) if int(n) >= 3000 else reps)
        scal_rows[n] = {k: res[k] for k in ("k", "m", "lm_time_ms", "lm_tau3_time_ms", "lm_tau6_2pt_time_ms",
                                            "scipy_time_ms", "scipy_jac_time_ms", "speedup", "speedup_vs_scipy_jac",
                                            "lm_max_err_mm", "scipy_max_err_mm", "same_accuracy")}
        scal_rows[n]["lm_n_jac"] = res["lm_info"]["n_jac"]
        scal_rows[n]["lm_time_ms_interleaved_across_counts"] = lm_rows[n]["lm_time_ms"]
    out["scaling_poses"] = scal_rows

    # scaling with the number of parameters (30 poses, noise-free), interleaved
    par_rows = lm_interleaved({"dh_1marker": base,
                               "dh_3markers": kr5_dh(30, 0.0, args.seed, THREE_MARKERS),
                               "urdf_1marker": kr5_urdf(30, 0.0, args.seed),
                               "urdf_3markers": kr5_urdf(30, 0.0, args.seed, THREE_MARKERS)}, tol, reps)
    out["lm_time_ms_by_params"] = {f"{name}_k{r['k']}": r["lm_time_ms"] for name, r in par_rows.items()}
    out["scaling_params"] = par_rows

    # ---- human table
    print(f"KR5 arc DH, {base.n_errors} DH errors, rank {base.report.rank} -> {base.k} identified, 30 poses, "
          f"tol {tol:g}, {reps} reps, median ms (torch {torch.__version__}, scipy {scipy.__version__}, "
          f"{args.threads} thread)")
    cols = ["lm", *LM_EXTRA, "scipy", "scipy_jac"]
    print(f"{'variant':<14}{'solver':<13}{'ms':>8}{'scipy/x':>9}{'scipy+J/x':>10}{'max err mm':>12}{'SSE m2':>12}"
          f"  calls (residuals: points evaluated)")
    for name, v in out["variants"].items():
        for n in cols:
            info = v[f"{n}_info"]
            ev = f"res {info['n_res']} jac {info['n_jac']} fitness {info['n_fitness']}"
            t = v[f"{n}_time_ms"]
            print(f"{name:<14}{n:<13}{t:>8.1f}{v['scipy_time_ms'] / t:>9.2f}{v['scipy_jac_time_ms'] / t:>10.2f}"
                  f"{v[f'{n}_max_err_mm']:>12.7f}{v[f'{n}_sse_m2']:>12.4e}  {ev}")
    print("(lm: as calibrate() runs it, tau=1e-6; lm_tau3: the former default tau=1e-3; lm_tau6_2pt: tau=1e-6, jac='2-point'; scipy: method='lm', "
          "finite differences; scipy_jac: method='lm' with torchcal's analytic Jacobian)")
    print("\nposes: 'LM ms' from one loop interleaving the pose counts; the rest from each count's own loop")
    print(f"{'poses':<8}{'m':>7}{'LM ms':>9}{'tau3':>8}{'tau6_2pt':>9}{'scipy':>9}{'scipy+J':>9}{'scipy/LM':>9}"
          f"{'sc+J/LM':>8}{'LM n_jac':>9}")
    for n, r in scal_rows.items():
        print(f"{n:<8}{r['m']:>7}{r['lm_time_ms_interleaved_across_counts']:>9.1f}{r['lm_tau3_time_ms']:>8.1f}"
              f"{r['lm_tau6_2pt_time_ms']:>9.1f}"
              f"{r['scipy_time_ms']:>9.1f}{r['scipy_jac_time_ms']:>9.1f}"
              f"{r['speedup']:>9.2f}{r['speedup_vs_scipy_jac']:>8.2f}{r['lm_n_jac']:>9}")
    print(f"\n{'parameter set (30 poses)':<26}{'errors':>7}{'k':>5}{'m':>6}{'LM ms':>9}{'n_jac':>7}{'LM err mm':>11}")
    for label, r in par_rows.items():
        print(f"{label:<26}{r['n_errors']:>7}{r['k']:>5}{r['m']:>6}{r['lm_time_ms']:>9.1f}{r['lm_n_jac']:>7}"
              f"{r['lm_max_err_mm']:>11.6f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
