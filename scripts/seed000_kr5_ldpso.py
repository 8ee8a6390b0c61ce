"""Seed 000 reproduction: LDPSO-BT vs PSO geometric calibration of a KUKA KR5 arc (DH model).

What the seed (journal article, 2022; digest in ``shared/docs/seeds.md`` section 000) did, and
what this script does the same way:

* Model: classic DH ``A_i = Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i)``, the KR5 arc data-sheet table
  (``torchcal.kinematics.robots.shipped("kuka_kr5_arc", source="dh")``), marker = flange.  Unknowns: the 24
  DH errors ``joint_a{1..6}.da/.dd/.dalpha/.dtheta``.  Measurements are flange positions in the
  robot base frame (ΔP = P_real − P_nominal), so the base frame (``base.*``) and the flange
  marker offsets (``flange.*``) are fixed at 0: ``ParamSet.only(<the 24 DH names>)``.
* True errors uniform in ±0.25 mm (Δa, Δd) and ±0.05 rad (Δα, Δθ) (seeded); 30 random joint
  configurations inside the joint limits; noise-free unless ``--noise-mm``.
* Objective ``f = Σ_i ‖ΔP_i‖`` (``CalibrationProblem(fitness="sum_norm")``); the search box is
  the error range itself (ParamSet lower/upper = ±0.25 mm / ±0.05 rad).
* PSO (240 particles, 500 iterations, w 0.8, c1 = c2 = 1.49) and LDPSO-BT (Nmax 240 → Nmin 40
  linearly, worst particles dropped, best tracking after K·MaxIt = 400 iterations with w2 0.4),
  i.e. the library defaults of ``get_solver("pso")`` / ``get_solver("ldpso-bt")``; 10 runs
  each (solver seeds 0..9).  Library choices the paper does not state: a velocity clamp of 0.2×
  the box width (``v_max``), and particle 0 starts at the problem's x0 = nominal (zero errors).

Not in the seed, added for comparison on the same data: Levenberg-Marquardt from zero errors
(library defaults, and the same with ``scaling="marquardt"``, labelled), and the hybrid
(``get_solver("hybrid")``: PSO with 240 particles but only ``--hybrid-iters`` (default 100)
iterations, then LM polish; both LM variants).  LM minimises the sum of squares, not Σ‖ΔP‖; its
row in the table is still Σ‖ΔP‖ at its solution.  PSO and LDPSO-BT also run on the general
kinematics path (``CalibrationProblem(compact=False)``, labelled), so that both paths' time ratios
come from the same rounds.

Method runs are interleaved round by round (each round: every method once, the order rotated
from round to round) so that machine-load noise on this shared 2-core box falls on all methods
alike; ``torch.set_num_threads(1)``.

Outputs (under ``--out``, default ``out/seed000/``, never committed): ``results.json`` (all
numbers), ``convergence.png`` (best fitness vs iteration and vs evaluations, log y, mean over
runs with min/max band, PSO vs LDPSO-BT, like the seed's figure).  Stdout: the seed's Table 3
(mean/best final fitness, mean time, mean evaluations), max per-axis |error| X/Y/Z before and
after each method on the 30 calibration poses and on ``--fresh`` (200) new random poses, the
identifiability analysis and parameter errors, the targets (met or not), and as the LAST line a
JSON object with the headline figures.

Digest notes, and what the identifiability analysis here shows:

* At the nominal parameters, position-only data identify 19 of the 24 DH errors:
  ``δα6`` and ``δθ6`` do not move the flange origin (a6 = 0: it lies on both axes); axes 2 and 3
  are parallel so only ``δd2 + δd3`` is seen; ``δα5`` acts like ``d6·δα5`` on ``δd5`` and ``δθ5``
  like ``−d6·δθ5`` on ``δa5`` (d6 = 115 mm).  The individual values of these five are therefore
  arbitrary for any method; only the combinations are determined, and an error in the
  unidentifiable directions leaves (to first order) no error at the flange point.
* Two caveats found while reproducing, both reported in the output: (1) these errors are large
  (±0.05 rad ≈ ±2.9°), so at the *true* parameters the Jacobian has rank 23 (only ``δα6`` exactly
  invisible) with three singular values ~1e-4 of the largest: second-order effects make the
  "unidentifiable" ones weakly visible, which noise-free LM exploits and noise destroys.
  (2) The combinations leave the box: ``δd5 + d6·δα5`` spans ±6 mm while the box allows ±0.25 mm
  for ``δd5``, so fixing the five dropped parameters at 0 *and* keeping the box makes the truth
  unreachable; all 24 must stay free inside the box.

Timing: the LDPSO-BT / PSO ratio is taken per round (the two runs of one round are neighbours in
time, so they see the same machine load), from thread CPU time, and reported as the median and
spread over the rounds (solver seeds 0..9).  The paper's −41.85 % equals its evaluation saving
(70 240 vs 120 240 evaluations, ratio 0.584): time ∝ evaluations, as with a per-particle loop.
A vectorised iteration costs ``t(P) = a + b·P``: the ratio is
``(501 a + 70 240 b) / (501 a + 120 240 b)``, 0.584 only when the fixed part ``a`` vanishes; 0.6
needs ``a`` below about 9.5 particles' worth (``b``).  The cost model measures ``a`` and ``b`` of a
whole PSO iteration (swarm update + fitness) and of the fitness alone, for the compact
position-only kinematics path (``torchcal.kinematics.fk_compact``, the default) and the general one
(``CalibrationProblem(compact=False)``), and predicts the ratio from the schedules.

The restarts as one batch: the 10 runs of each swarm are also run as one population tensor
(``torchcal.optim.minimize_runs``: runs × particles, each run with its own generator seeded as
alone, its own bests and its own stopping), ``--batch-reps`` times, PSO and LDPSO-BT alternately.
The batch gives each run bit for bit the result of its run alone (checked against the rounds
above: ``batched_identical_to_one_by_one``), and pays an iteration's fixed cost once for all ten,
so LDPSO-BT's shrinking population saves time in proportion to its evaluations:
``batched_time_ratio`` (wall, median over the repeats) and ``batched_time_ratio_cpu`` (thread CPU).
``--batched-only`` runs just that comparison (and two runs one by one to check the results).

Usage::

    .venv/bin/python scripts/seed000_kr5_ldpso.py                 # full run, noise-free data
    .venv/bin/python scripts/seed000_kr5_ldpso.py --batched-only  # the restarts as one batch only
    .venv/bin/python scripts/seed000_kr5_ldpso.py --noise-mm 0.02  # same with 0.02 mm noise
    .venv/bin/python scripts/seed000_kr5_ldpso.py --quick         # smoke test

The LM noise-free and 0.02 mm noise-floor figures are computed in every run (a side study on the
same truth and poses, ``--lm-noise-mm``, ``--lm-noise-draws``), so the final JSON always carries
both.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import torch

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from torchcal.problems.identifiability import identifiability  # noqa: E402
from torchcal.measure.data import Measurements  # noqa: E402
from torchcal.optim import get_solver, minimize_runs  # noqa: E402
from torchcal.problems.calibration import CalibrationProblem  # noqa: E402
from torchcal.kinematics.robots import shipped  # noqa: E402
from torchcal.sim.serial import random_configs  # noqa: E402

LEN_RANGE = 0.25e-3  # m
ANG_RANGE = 0.05  # rad
SEED_REPORTED = {  # seed 000, max |error| X/Y/Z (mm)
    "before": (47.1, 51.8, 52.8), "pso": (0.14, 0.13, 0.10), "ldpso-bt": (0.18, 0.18, 0.15),
    "time_saving": 0.4185,
}


# ---------------------------------------------------------------------------- setup
def build(args):
    robot = shipped("kuka_kr5_arc", source="dh")
    dh = [n for n in robot.param_names if n.startswith("joint_a") and n.rsplit(".", 1)[1] in
          ("da", "dd", "dalpha", "dtheta")]
    assert len(dh) == 24, dh
    ps = robot.params()
    ps.only(*dh)  # base.* and flange.* fixed at 0: base-frame measurements, flange = marker
    rng = torch.tensor([LEN_RANGE if u == "m" else ANG_RANGE for u in ps.units], dtype=torch.float64)
    ps.lower = torch.where(ps.free, -rng, torch.zeros_like(rng))
    ps.upper = torch.where(ps.free, rng, torch.zeros_like(rng))
    g = torch.Generator().manual_seed(args.seed)
    u = torch.rand(len(ps), generator=g, dtype=torch.float64)
    truth = torch.where(ps.free, (2 * u - 1) * rng, torch.zeros_like(rng))
    q = random_configs(robot, args.poses, g, margin=0.0)
    gf = torch.Generator().manual_seed(args.seed + 1_000_003)
    q_fresh = random_configs(robot, args.fresh, gf, margin=0.0)
    return robot, dh, ps, truth, q, q_fresh


def make_problem(robot, ps, q, positions, compact=True):
    data = Measurements(q.clone(), positions, list(robot.marker_names), list(robot.joint_names))
    return CalibrationProblem(robot, ps, data, fitness="sum_norm", compact=compact)


def noisy(robot, q, truth, noise_m, seed):
    p = robot.positions(q, truth)
    if noise_m <= 0:
        return p
    g = torch.Generator().manual_seed(seed)
    return p + noise_m * torch.randn(p.shape, generator=g, dtype=p.dtype)


def axis_err(robot, qs, full, truth):
    """(3,) max over poses of |P_identified − P_true| per axis (mm), base frame."""
    d = (robot.positions(qs, full) - robot.positions(qs, truth)).abs()  # (N, 1, 3)
    return (d.reshape(-1, 3).amax(0) * 1e3).tolist()


def rms_err(robot, qs, full, truth):
    d = robot.positions(qs, full) - robot.positions(qs, truth)
    return float(d.norm(dim=-1).pow(2).mean().sqrt() * 1e3)


# ---------------------------------------------------------------------------- methods
def method_specs(args):
    it = args.iters
    hyb = args.hybrid_iters
    lm_m = {"scaling": "marquardt"}
    return {
        "pso": lambda s: get_solver("pso", seed=s, max_iter=it),
        "ldpso-bt": lambda s: get_solver("ldpso-bt", seed=s, max_iter=it),
        "lm": lambda s: get_solver("lm", seed=s),
        "lm-marquardt": lambda s: get_solver("lm", seed=s, **lm_m),
        "hybrid": lambda s: get_solver("hybrid", seed=s, swarm="pso", swarm_options={"max_iter": hyb}),
        "hybrid-marquardt": lambda s: get_solver("hybrid", seed=s, swarm="pso",
                                                 swarm_options={"max_iter": hyb}, polish_options=lm_m),
        # the same swarms on the general kinematics path (CalibrationProblem(compact=False))
        "pso-general": lambda s: get_solver("pso", seed=s, max_iter=it),
        "ldpso-bt-general": lambda s: get_solver("ldpso-bt", seed=s, max_iter=it),
    }


LABELS = {
    "pso": "PSO (seed settings)", "ldpso-bt": "LDPSO-BT (seed settings)",
    "lm": "LM from 0 (library defaults)", "lm-marquardt": "LM from 0 (scaling=marquardt)",
    "hybrid": "hybrid PSO{h}+LM (defaults)", "hybrid-marquardt": "hybrid PSO{h}+LM (marquardt)",
    "pso-general": "PSO, general FK path", "ldpso-bt-general": "LDPSO-BT, general FK path",
}


def run_all(args, robot, ps, prob, prob_general, truth, q, q_fresh):
    specs = method_specs(args)
    names = list(specs)
    runs = {n: [] for n in names}
    for rnd in range(args.runs):
        order = names[rnd % len(names):] + names[:rnd % len(names)]  # rotate: share load noise
        for n in order:
            solver = specs[n](rnd)
            c0 = time.thread_time()
            res = solver.minimize(prob_general if n.endswith("-general") else prob)
            cpu = time.thread_time() - c0
            full = ps.expand(res.x.detach())
            runs[n].append(dict(
                fun_mm=res.fun * 1e3, time_s=res.wall_time_s, cpu_s=cpu, n_evals=res.n_evals, n_iter=res.n_iter,
                history_mm=[h * 1e3 for h in res.history] if n in ("pso", "ldpso-bt") else None,
                pop_sizes=res.extra.get("pop_sizes"), message=res.message,
                x=full.tolist(),
                axis_cal=axis_err(robot, q, full, truth), axis_fresh=axis_err(robot, q_fresh, full, truth),
                rms_fresh=rms_err(robot, q_fresh, full, truth)))
        line = "  ".join(f"{n}={runs[n][-1]['fun_mm']:.3g}mm/{runs[n][-1]['time_s']:.2f}s"
                         f"({runs[n][-1]['cpu_s']:.2f} cpu)" for n in names)
        print(f"  round {rnd + 1}/{args.runs}: {line}", flush=True)
    return runs


def batched_restarts(args, prob, ps, runs: dict) -> dict:
    """PSO and LDPSO-BT, ``args.runs`` seeds each as one batch, ``args.batch_reps`` times alternately:
    wall and thread-CPU time per batch, their LDPSO-BT / PSO ratios (median over the repeats), and
    whether each run's result equals its run alone in ``runs`` (bit for bit)."""
    seeds = list(range(args.runs))
    times = {m: {"wall": [], "cpu": []} for m in ("pso", "ldpso-bt")}
    same = True
    for rep in range(args.batch_reps):
        for m in (("pso", "ldpso-bt") if rep % 2 == 0 else ("ldpso-bt", "pso")):
            c0, t0 = time.thread_time(), time.perf_counter()
            res = minimize_runs(prob, m, seeds=seeds, max_iter=args.iters)
            times[m]["wall"].append(time.perf_counter() - t0)
            times[m]["cpu"].append(time.thread_time() - c0)
            for r, alone in zip(res, runs[m]):
                same &= ps.expand(r.x).tolist() == alone["x"] and r.fun * 1e3 == alone["fun_mm"]
    med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
    out = {f"batched_{k}_{m.replace('-bt', '')}_s": med(times[m][k]) for m in times for k in ("wall", "cpu")}
    out.update(batched_time_ratio=med(times["ldpso-bt"]["wall"]) / med(times["pso"]["wall"]),
               batched_time_ratio_cpu=med(times["ldpso-bt"]["cpu"]) / med(times["pso"]["cpu"]),
               batched_identical_to_one_by_one=same, batched_runs=len(seeds), batched_reps=args.batch_reps,
               batched_times=times)
    return out


def print_batched(b: dict) -> None:
    print(f"  as one batch of {b['batched_runs']} runs: LDPSO-BT / PSO wall {b['batched_time_ratio']:.3f} "
          f"({b['batched_wall_ldpso_s']:.2f} / {b['batched_wall_pso_s']:.2f} s), thread CPU "
          f"{b['batched_time_ratio_cpu']:.3f} ({b['batched_cpu_ldpso_s']:.2f} / {b['batched_cpu_pso_s']:.2f} s); "
          f"median of {b['batched_reps']}; each run equal to its run alone: {b['batched_identical_to_one_by_one']}")


def lm_side_study(args, robot, ps, truth, q, q_fresh):
    """LM on noise-free data and on ``--lm-noise-mm`` noisy data (several draws), both LM
    variants. Noise floor = RMS ‖P_true − P_meas‖ on the calibration poses (what the true model
    leaves on the noisy measurements)."""
    out = {}
    clean = make_problem(robot, ps, q, robot.positions(q, truth))
    for key, opts in (("lm", {}), ("lm-marquardt", {"scaling": "marquardt"})):
        res = get_solver("lm", **opts).minimize(clean)
        full = ps.expand(res.x)
        out[key] = {"noisefree": dict(max_axis_fresh_mm=max(axis_err(robot, q_fresh, full, truth)),
                                      max_axis_cal_mm=max(axis_err(robot, q, full, truth)),
                                      rms_fresh_mm=rms_err(robot, q_fresh, full, truth),
                                      n_iter=res.n_iter, time_s=res.wall_time_s, message=res.message),
                    "noisy": []}
    sigma = args.lm_noise_mm * 1e-3
    for d in range(args.lm_noise_draws):
        meas = noisy(robot, q, truth, sigma, seed=10_000 + 97 * d + args.seed)
        floor = float((meas - robot.positions(q, truth)).norm(dim=-1).pow(2).mean().sqrt() * 1e3)
        prob = make_problem(robot, ps, q, meas)
        for key, opts in (("lm", {}), ("lm-marquardt", {"scaling": "marquardt"})):
            res = get_solver("lm", **opts).minimize(prob)
            full = ps.expand(res.x)
            resid = float((robot.positions(q, full) - meas).norm(dim=-1).pow(2).mean().sqrt() * 1e3)
            out[key]["noisy"].append(dict(
                noise_rms_mm=floor, rms_fresh_mm=rms_err(robot, q_fresh, full, truth),
                resid_rms_mm=resid, max_axis_fresh_mm=max(axis_err(robot, q_fresh, full, truth)),
                n_iter=res.n_iter, time_s=res.wall_time_s, at_bound=int(((res.x <= clean.lower) |
                                                                         (res.x >= clean.upper)).sum())))
    for key in out:
        nz = out[key]["noisy"]
        if nz:
            floor = sum(r["noise_rms_mm"] for r in nz) / len(nz)
            out[key]["noise_floor_ratio"] = sum(r["rms_fresh_mm"] for r in nz) / len(nz) / floor
            out[key]["resid_ratio"] = sum(r["resid_rms_mm"] for r in nz) / len(nz) / floor
            out[key]["noise_rms_mm"] = floor
    return out


def _fitness_cost(prob, X: dict, reps: int, calls: int) -> dict:
    """Thread CPU of one fitness call per population size (best of ``reps`` interleaved repeats)."""
    best = {P: float("inf") for P in X}
    for _ in range(reps):
        for P, x in X.items():
            c0 = time.thread_time()
            for _ in range(calls):
                prob.fitness(x)
            best[P] = min(best[P], (time.thread_time() - c0) / calls)
    return best


def _iteration_cost(prob, sizes, reps: int, iters: int) -> dict:
    """Thread CPU of one PSO iteration (update + fitness) per population size: a run of ``iters``
    iterations minus a run of none (the initial evaluation), best of ``reps`` interleaved repeats."""
    best = {P: float("inf") for P in sizes}
    for _ in range(reps):
        for P in sizes:
            c0 = time.thread_time()
            get_solver("pso", pop_size=P, max_iter=iters).minimize(prob)
            c1 = time.thread_time()
            get_solver("pso", pop_size=P, max_iter=0).minimize(prob)
            c2 = time.thread_time()
            best[P] = min(best[P], ((c1 - c0) - (c2 - c1)) / iters)
    return best


def _linear(best: dict, n_min: int, n_max: int, iters: int) -> dict:
    """``t(P) = a + b P`` through the two sizes, and the LDPSO-BT / PSO time ratio it predicts."""
    from torchcal.optim.pso import ldpso_pop_sizes

    b = (best[n_max] - best[n_min]) / (n_max - n_min)
    a = best[n_min] - b * n_min
    pso = (iters + 1) * (a + b * n_max)
    ld = (a + b * n_max) + sum(a + b * n for n in ldpso_pop_sizes(n_max, n_min, iters))
    return dict(t_ms={str(P): v * 1e3 for P, v in best.items()}, fixed_ms=a * 1e3, per_particle_us=b * 1e6,
                fixed_equiv_particles=a / b if b > 0 else float("inf"), predicted_ratio=ld / pso)


def timing_model(prob, prob_general, n_max=240, n_min=40, iters=500, reps=7, calls=20, probe_iters=40):
    """Cost models ``t(P) = a + b P`` (thread CPU) of a fitness call and of a whole PSO iteration,
    for the compact and the general fitness path, with the LDPSO-BT / PSO ratios they predict,
    and the largest fixed part (in particles' worth) for which the ratio is 0.6."""
    from torchcal.optim.pso import ldpso_pop_sizes

    g = torch.Generator().manual_seed(0)
    X = {P: prob.lower + torch.rand(P, prob.dim, generator=g, dtype=prob.dtype) * (prob.upper - prob.lower)
         for P in (n_min, n_max)}
    out = {}
    for key, pr in (("compact", prob), ("general", prob_general)):
        out[key] = {"fitness": _linear(_fitness_cost(pr, X, reps, calls), n_min, n_max, iters),
                    "iteration": _linear(_iteration_cost(pr, (n_min, n_max), reps, probe_iters), n_min, n_max, iters)}
    e_pso = (iters + 1) * n_max
    e_ld = n_max + sum(ldpso_pop_sizes(n_max, n_min, iters))
    out["fixed_equiv_particles_for_0.6"] = (0.6 * e_pso - e_ld) / (0.4 * (iters + 1))
    out["eval_ratio"] = e_ld / e_pso
    return out


# ---------------------------------------------------------------------------- reporting
def mean(xs):
    xs = list(xs)
    return sum(xs) / len(xs) if xs else float("nan")


def sem(xs):
    if len(xs) < 2:
        return float("nan")
    mu = mean(xs)
    return math.sqrt(sum((x - mu) ** 2 for x in xs) / (len(xs) - 1) / len(xs))


def print_table3(runs, f0_mm, args):
    print("\nTable 3 (cf. the seed): final fitness Σ‖ΔP‖ over the "
          f"{args.poses} poses (mm), {args.runs} runs; before calibration f = {f0_mm:.2f} mm")
    print(f"  {'method':<34} {'mean f (mm)':>12} {'best f (mm)':>12} {'worst f':>10} {'mean t (s)':>11} "
          f"{'min t':>7} {'mean cpu':>9} {'mean evals':>11}")
    for n, rs in runs.items():
        lab = LABELS[n].format(h=args.hybrid_iters)
        print(f"  {lab:<34} {mean(r['fun_mm'] for r in rs):>12.4g} {min(r['fun_mm'] for r in rs):>12.4g} "
              f"{max(r['fun_mm'] for r in rs):>10.4g} {mean(r['time_s'] for r in rs):>11.3f} "
              f"{min(r['time_s'] for r in rs):>7.3f} {mean(r['cpu_s'] for r in rs):>9.3f} "
              f"{mean(r['n_evals'] for r in rs):>11.0f}")
    print("  (t = wall time; min t = fastest run; cpu = thread CPU time, less sensitive to other jobs on "
          "this shared machine)")


def print_axis(runs, before_cal, before_fresh, args):
    print(f"\nMax per-axis |error| X / Y / Z (mm), identified vs true model, base frame; "
          f"{args.poses} calibration poses | {args.fresh} fresh poses")
    print(f"  {'':<34} {'calibration poses':>26}   {'fresh poses':>26}")
    f = lambda v: " / ".join(f"{x:7.3g}" for x in v)  # noqa: E731
    print(f"  {'before calibration':<34} {f(before_cal):>26}   {f(before_fresh):>26}")
    for n, rs in runs.items():
        lab = LABELS[n].format(h=args.hybrid_iters)
        mc = [mean(r["axis_cal"][i] for r in rs) for i in range(3)]
        mf = [mean(r["axis_fresh"][i] for r in rs) for i in range(3)]
        print(f"  {lab + ' (mean)':<34} {f(mc):>26}   {f(mf):>26}")
        if len(rs) > 1 and n in ("pso", "ldpso-bt", "hybrid", "hybrid-marquardt"):
            wc = max(rs, key=lambda r: max(r["axis_fresh"]))
            print(f"  {'   worst run':<34} {f(wc['axis_cal']):>26}   {f(wc['axis_fresh']):>26}")
    print(f"  seed reported: before {SEED_REPORTED['before']}, PSO {SEED_REPORTED['pso']}, "
          f"LDPSO-BT {SEED_REPORTED['ldpso-bt']} (which poses: not stated)")


def combos(rep, names):
    """Identifiable combinations from the dropped parameters' relations:
    partner + Σ coef · dropped, as ``{label: {name: coef}}``."""
    out = {}
    for dname, rel in rep.relations.items():
        for partner, coef in rel.items():
            c = out.setdefault(partner, {partner: 1.0})
            c[dname] = c.get(dname, 0.0) + coef
    labs = {}
    for partner, c in out.items():
        terms = [partner] + [f"{v:+.4g}·{k}" for k, v in c.items() if k != partner]
        labs[" ".join(terms)] = c
    return labs


def print_params(runs, rep, rep_true, dh, ps, truth, args):
    idx = {n: ps.index(n) for n in dh}
    units = {n: ps.units[ps.index(n)] for n in dh}
    show = ["pso", "ldpso-bt", "lm", "lm-marquardt"]
    print("\nParameter errors |identified − true| (mm for lengths, mrad for angles; swarm: mean over runs)")
    print(f"  {'parameter':<18} {'class':<8} {'true':>9} " + " ".join(f"{m:>13}" for m in show))
    summary = {}
    for n in dh:
        cls = "ident" if n in rep.identifiable else "UNIDENT"
        t = float(truth[idx[n]]) * 1e3
        errs = [mean(abs(r["x"][idx[n]] * 1e3 - t) for r in runs[m]) for m in show]
        for m, e in zip(show, errs):
            summary.setdefault(m, {"ident": [], "UNIDENT": []})[cls].append(e)
        print(f"  {n:<18} {cls:<8} {t:>9.4f} " + " ".join(f"{e:>13.4g}" for e in errs))
    cb = combos(rep, dh)
    print("  identifiable combinations (coefficients from the nominal analysis; units m and rad):")
    comb_err = {}
    for lab, c in cb.items():
        t = sum(v * float(truth[idx[k]]) for k, v in c.items()) * 1e3
        errs = [mean(abs(sum(v * r["x"][idx[k]] for k, v in c.items()) * 1e3 - t) for r in runs[m]) for m in show]
        for m, e in zip(show, errs):
            comb_err.setdefault(m, []).append(e)
        print(f"  {lab:<60} true {t:9.4f} mm   err " + " ".join(f"{m}={e:.3g}" for m, e in zip(show, errs)))
    print("  mean |error| per class (mm or mrad, mixed): " + "; ".join(
        f"{m}: identifiable {mean(summary[m]['ident']):.3g}, unidentifiable {mean(summary[m]['UNIDENT']):.3g}, "
        f"combinations {mean(comb_err.get(m, [])):.3g}" for m in show))
    return {m: dict(identifiable_mean_abs_err=mean(summary[m]["ident"]),
                    unidentifiable_mean_abs_err=mean(summary[m]["UNIDENT"]),
                    combination_mean_abs_err_mm=mean(comb_err.get(m, []))) for m in show}, list(cb)


def plot_convergence(runs, path, args):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for n, col in (("pso", "tab:blue"), ("ldpso-bt", "tab:red")):
        H = np.array([r["history_mm"] for r in runs[n]])
        it = np.arange(H.shape[1])
        if n == "pso":
            ev = 240 * (it + 1)
        else:
            ev = 240 + np.concatenate([[0], np.cumsum(runs[n][0]["pop_sizes"])])
        for ax, x in ((axes[0], it), (axes[1], ev)):
            ax.fill_between(x, H.min(0), H.max(0), color=col, alpha=0.2, lw=0)
            ax.plot(x, H.mean(0), color=col, label=f"{LABELS[n]} (mean, min/max band, {len(H)} runs)")
    axes[0].set_xlabel("iteration")
    axes[1].set_xlabel("fitness evaluations")
    for ax in axes:
        ax.set_yscale("log")
        ax.set_ylabel("best fitness Σ‖ΔP‖ (mm)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Seed 000 reproduction: KR5 arc, 24 DH errors, {args.poses} poses, noise {args.noise_mm} mm")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "out" / "seed000"))
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--fresh", type=int, default=200)
    ap.add_argument("--noise-mm", type=float, default=0.0, help="noise std per axis on the main data (mm)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the true errors, poses and noise")
    ap.add_argument("--iters", type=int, default=500, help="swarm iterations (seed: 500)")
    ap.add_argument("--hybrid-iters", type=int, default=100, help="PSO iterations of the hybrid's swarm stage")
    ap.add_argument("--lm-noise-mm", type=float, default=0.02, help="noise of the LM noise-floor side study")
    ap.add_argument("--lm-noise-draws", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="smoke test: 2 runs, 60 iterations, 2 noise draws")
    ap.add_argument("--batch-reps", type=int, default=3, help="repeats of the batched restarts (each method)")
    ap.add_argument("--batched-only", action="store_true",
                    help="only the restarts as one batch (and two runs one by one, to check the results)")
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.iters, args.hybrid_iters, args.lm_noise_draws = 2, 60, 20, 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    load0 = os.getloadavg()

    robot, dh, ps, truth, q, q_fresh = build(args)
    meas = noisy(robot, q, truth, args.noise_mm * 1e-3, seed=args.seed + 777)
    prob = make_problem(robot, ps, q, meas)
    zero = torch.zeros(len(ps), dtype=torch.float64)
    f0_mm = float(prob.fitness(prob.start()[None])[0]) * 1e3
    f_true_mm = float(prob.fitness(truth[ps.free_index][None])[0]) * 1e3
    before_cal, before_fresh = axis_err(robot, q, zero, truth), axis_err(robot, q_fresh, zero, truth)
    print(f"Seed 000 reproduction: KUKA KR5 arc (DH), 24 DH errors free ({', '.join(dh[:4])}, ...), "
          f"base.* and flange.* fixed at 0")
    print(f"  true errors uniform ±{LEN_RANGE * 1e3} mm / ±{ANG_RANGE} rad (seed {args.seed}); {args.poses} poses; "
          f"{args.fresh} fresh poses; noise {args.noise_mm} mm; swarm {args.iters} iterations; "
          f"torch threads {torch.get_num_threads()}; load avg at start {load0[0]:.2f}")
    print(f"  fitness before calibration {f0_mm:.3f} mm, at the true parameters {f_true_mm:.4g} mm")
    if args.batched_only:
        alone = {m: [] for m in ("pso", "ldpso-bt")}
        for m in alone:
            for sd in range(min(2, args.runs)):
                r = get_solver(m, seed=sd, max_iter=args.iters).minimize(prob)
                alone[m].append({"x": ps.expand(r.x).tolist(), "fun_mm": r.fun * 1e3})
        bt = batched_restarts(args, prob, ps, alone)
        print_batched(bt)
        print(json.dumps(dict(bt, runs=args.runs, iters=args.iters, poses=args.poses, seed=args.seed,
                              checked_against_runs_alone=min(2, args.runs), threads=torch.get_num_threads(),
                              load_avg_start_end=[load0[0], os.getloadavg()[0]],
                              target_batched_ratio_le_0_6=bt["batched_time_ratio"] <= 0.6)))
        return

    # identifiability: at the nominal parameters (the textbook statement) and at the truth
    rep = identifiability(robot, q, free=dh)
    rep_true = identifiability(robot, q, params=truth, free=dh)
    print("\nIdentifiability from the 30 flange positions, linearised at the nominal parameters:")
    print("  " + rep.summary().replace("\n", "\n  "))
    sv = rep_true.singular_values
    print(f"  at the TRUE parameters instead: rank {rep_true.rank} of 24, dropped {rep_true.dropped}; "
          f"smallest singular values (unit columns) {', '.join(f'{s:.2g}' for s in sv[-6:])} "
          f"(largest {sv[0]:.3g}): the 4 extra directions are only second-order visible")

    print(f"\nRunning {args.runs} interleaved rounds of {len(method_specs(args))} methods ...", flush=True)
    prob_general = make_problem(robot, ps, q, meas, compact=False)
    runs = run_all(args, robot, ps, prob, prob_general, truth, q, q_fresh)
    print(f"\nThe same {args.runs} runs of each swarm as one batch, {args.batch_reps} times alternately ...", flush=True)
    batched = batched_restarts(args, prob, ps, runs)
    print_batched(batched)
    print_table3(runs, f0_mm, args)
    print_axis(runs, before_cal, before_fresh, args)
    perr, comb_labels = print_params(runs, rep, rep_true, dh, ps, truth, args)

    print(f"\nLM side study (same truth and poses): noise-free, and {args.lm_noise_draws} draws of "
          f"{args.lm_noise_mm} mm noise", flush=True)
    lms = lm_side_study(args, robot, ps, truth, q, q_fresh)
    for key, v in lms.items():
        nf = v["noisefree"]
        print(f"  {key:<13} noise-free: max per-axis fresh error {nf['max_axis_fresh_mm']:.3g} mm "
              f"(calibration poses {nf['max_axis_cal_mm']:.3g}), {nf['n_iter']} iterations, "
              f"{nf['time_s']:.2f} s, {nf['message']}")
        if v["noisy"]:
            print(f"  {'':<13} noisy: fresh-pose RMS error {mean(r['rms_fresh_mm'] for r in v['noisy']):.4g} mm vs "
                  f"noise-only RMS {v['noise_rms_mm']:.4g} mm -> ratio {v['noise_floor_ratio']:.3f}; in-sample "
                  f"residual RMS / noise RMS {v['resid_ratio']:.3f}; max per-axis fresh error "
                  f"{mean(r['max_axis_fresh_mm'] for r in v['noisy']):.3g} mm; mean "
                  f"{mean(r['n_iter'] for r in v['noisy']):.0f} iterations; parameters on a bound: "
                  f"{mean(r['at_bound'] for r in v['noisy']):.1f} of 24")

    tm = timing_model(prob, prob_general, iters=args.iters)
    print("\nCost model t(P) = a + b P (thread CPU, best of interleaved repeats); the ratio it predicts from "
          "the schedules; a in particles' worth (a / b)")
    for key in ("compact", "general"):
        for part in ("iteration", "fitness"):
            c = tm[key][part]
            print(f"  {key + ' path, ' + part:<26} a = {c['fixed_ms'] * 1e3:7.1f} us, b = {c['per_particle_us']:5.2f} us "
                  f"-> a = {c['fixed_equiv_particles']:5.1f} particles; t(240) = {c['t_ms']['240'] * 1e3:7.1f} us; "
                  f"predicted ratio {c['predicted_ratio']:.3f}")
    print(f"  evaluation ratio {tm['eval_ratio']:.3f}; a ratio of 0.6 needs a <= "
          f"{tm['fixed_equiv_particles_for_0.6']:.1f} particles' worth per iteration")

    plot_path = out / "convergence.png"
    plot_convergence(runs, plot_path, args)
    print(f"\nconvergence plot: {plot_path}")

    # ------------------------------------------------------------------ headline + targets
    m = lambda n, k: mean(r[k] for r in runs[n])  # noqa: E731
    mx = lambda n: mean(max(r["axis_fresh"]) for r in runs[n])  # noqa: E731
    worst = lambda n: max(max(r["axis_fresh"]) for r in runs[n])  # noqa: E731
    pso_t, ld_t = m("pso", "time_s"), m("ldpso-bt", "time_s")
    # per-round ratios: the two runs of a round are neighbours in time, so they share the load
    rr = sorted(a["cpu_s"] / b["cpu_s"] for a, b in zip(runs["ldpso-bt"], runs["pso"]))
    rg = sorted(a["cpu_s"] / b["cpu_s"] for a, b in zip(runs["ldpso-bt-general"], runs["pso-general"]))
    quant = lambda f, x=rr: x[min(len(x) - 1, max(0, round(f * (len(x) - 1))))]  # noqa: E731
    J = {
        "noise_mm": args.noise_mm, "runs": args.runs, "iters": args.iters, "poses": args.poses,
        "fresh": args.fresh, "seed": args.seed, "quick": args.quick,
        "fitness_before_mm": f0_mm,
        "pso_time_s": pso_t, "ldpso_time_s": ld_t, "time_ratio": ld_t / pso_t,
        "time_ratio_cpu_median": quant(0.5), "time_ratio_cpu_min": rr[0], "time_ratio_cpu_max": rr[-1],
        "time_ratio_cpu_q25": quant(0.25), "time_ratio_cpu_q75": quant(0.75), "time_ratio_cpu_rounds": rr,
        "general_time_ratio_cpu_median": quant(0.5, rg), "general_time_ratio_cpu_min": rg[0],
        "general_time_ratio_cpu_max": rg[-1], "general_pso_cpu_s": m("pso-general", "cpu_s"),
        "general_ldpso_cpu_s": m("ldpso-bt-general", "cpu_s"),
        "time_ratio_min": min(r["time_s"] for r in runs["ldpso-bt"]) / min(r["time_s"] for r in runs["pso"]),
        "time_ratio_cpu": m("ldpso-bt", "cpu_s") / m("pso", "cpu_s"),
        "pso_time_min_s": min(r["time_s"] for r in runs["pso"]), "pso_cpu_s": m("pso", "cpu_s"),
        "ldpso_cpu_s": m("ldpso-bt", "cpu_s"),
        "pso_fitness_sem": sem([r["fun_mm"] for r in runs["pso"]]),
        "ldpso_fitness_sem": sem([r["fun_mm"] for r in runs["ldpso-bt"]]),
        "eval_ratio": m("ldpso-bt", "n_evals") / m("pso", "n_evals"),
        "pso_fitness_mean": m("pso", "fun_mm"), "ldpso_fitness_mean": m("ldpso-bt", "fun_mm"),
        "pso_fitness_best": min(r["fun_mm"] for r in runs["pso"]),
        "ldpso_fitness_best": min(r["fun_mm"] for r in runs["ldpso-bt"]),
        "pso_max_axis_err_mm": mx("pso"), "ldpso_max_axis_err_mm": mx("ldpso-bt"),
        "pso_max_axis_err_worst_mm": worst("pso"), "ldpso_max_axis_err_worst_mm": worst("ldpso-bt"),
        "before_max_axis_err_mm": max(before_fresh),
        "lm_max_err_mm": mx("lm"), "lm_marquardt_max_err_mm": mx("lm-marquardt"),
        "lm_time_s": m("lm", "time_s"), "lm_marquardt_time_s": m("lm-marquardt", "time_s"),
        "hybrid_max_err_mm": mx("hybrid"), "hybrid_marquardt_max_err_mm": mx("hybrid-marquardt"),
        "hybrid_time_s": m("hybrid", "time_s"), "hybrid_marquardt_time_s": m("hybrid-marquardt", "time_s"),
        "hybrid_swarm_iters": args.hybrid_iters,
        "time_ratio_predicted_from_cost_model": tm["compact"]["iteration"]["predicted_ratio"], "timing_model": tm,
        "lm_noisefree_max_err_mm": lms["lm"]["noisefree"]["max_axis_fresh_mm"],
        "lm_marquardt_noisefree_max_err_mm": lms["lm-marquardt"]["noisefree"]["max_axis_fresh_mm"],
        "lm_noise_floor_ratio": lms["lm"].get("noise_floor_ratio"),
        "lm_marquardt_noise_floor_ratio": lms["lm-marquardt"].get("noise_floor_ratio"),
        "lm_noise_floor_noise_mm": args.lm_noise_mm,
        "rank": rep.rank, "unidentifiable": rep.dropped, "rank_at_truth": rep_true.rank,
        "param_errors": perr, **batched,
    }
    tg = {
        "ldpso_cpu_time_median_ratio_le_0.6": J["time_ratio_cpu_median"] <= 0.6,
        "pso_max_axis_err_le_0.10mm": J["pso_max_axis_err_mm"] <= 0.10,
        "ldpso_max_axis_err_le_0.10mm": J["ldpso_max_axis_err_mm"] <= 0.10,
        "lm_noisefree_lt_1e-6mm": J["lm_noisefree_max_err_mm"] < 1e-6,
        "lm_marquardt_noisefree_lt_1e-6mm (variant)": J["lm_marquardt_noisefree_max_err_mm"] < 1e-6,
        "lm_noise_floor_ratio_le_1.2": (J["lm_noise_floor_ratio"] or float("inf")) <= 1.2,
        "ldpso_batched_wall_ratio_le_0.6": J["batched_time_ratio"] <= 0.6,
        "pso_240x500_le_1.5s_cpu (mean wall)": pso_t <= 1.5 and args.iters == 500,
        "pso_240x500_le_1.5s_cpu (fastest run)": J["pso_time_min_s"] <= 1.5 and args.iters == 500,
    }
    J["targets"] = tg
    print("\nTargets:" + (" (QUICK MODE: fewer runs and iterations, not meaningful)" if args.quick else ""))
    print(f"  LDPSO-BT / PSO thread CPU time per round: median {J['time_ratio_cpu_median']:.3f}, quartiles "
          f"{J['time_ratio_cpu_q25']:.3f}-{J['time_ratio_cpu_q75']:.3f}, range {J['time_ratio_cpu_min']:.3f}-"
          f"{J['time_ratio_cpu_max']:.3f} over {len(rr)} rounds (evaluation ratio {J['eval_ratio']:.3f}; seed: "
          f"{1 - SEED_REPORTED['time_saving']:.3f}; cost model predicts "
          f"{J['time_ratio_predicted_from_cost_model']:.3f})")
    print(f"  general kinematics path, same rounds: median {J['general_time_ratio_cpu_median']:.3f}, range "
          f"{J['general_time_ratio_cpu_min']:.3f}-{J['general_time_ratio_cpu_max']:.3f}; mean CPU PSO "
          f"{J['general_pso_cpu_s']:.2f} s (compact {J['pso_cpu_s']:.2f} s), LDPSO-BT {J['general_ldpso_cpu_s']:.2f} s "
          f"(compact {J['ldpso_cpu_s']:.2f} s)")
    print(f"  mean times: LDPSO-BT {ld_t:.2f} s vs PSO {pso_t:.2f} s wall (ratio {J['time_ratio']:.3f}), "
          f"{J['ldpso_cpu_s']:.2f} vs {J['pso_cpu_s']:.2f} s CPU; ratio of fastest runs {J['time_ratio_min']:.3f}")
    print(f"  final fitness mean ± s.e.: LDPSO-BT {J['ldpso_fitness_mean']:.4g} ± {J['ldpso_fitness_sem']:.2g} vs PSO "
          f"{J['pso_fitness_mean']:.4g} ± {J['pso_fitness_sem']:.2g} mm")
    print(f"  PSO 240x{args.iters}: mean wall {pso_t:.2f} s, fastest {J['pso_time_min_s']:.2f} s, mean CPU "
          f"{J['pso_cpu_s']:.2f} s")
    print(f"  max per-axis fresh error: PSO mean {J['pso_max_axis_err_mm']:.3g} (worst {J['pso_max_axis_err_worst_mm']:.3g})"
          f", LDPSO-BT mean {J['ldpso_max_axis_err_mm']:.3g} (worst {J['ldpso_max_axis_err_worst_mm']:.3g}) mm")
    for k, v in tg.items():
        print(f"  [{'MET' if v else 'MISSED'}] {k}")
    load1 = os.getloadavg()
    J["load_avg_start_end"] = [load0[0], load1[0]]
    J["total_wall_s"] = time.perf_counter() - t_start
    full_json = dict(J, runs_detail={n: [{k: v for k, v in r.items()} for r in rs] for n, rs in runs.items()},
                     lm_side_study=lms, identifiability=rep.to_dict(), identifiability_at_truth=rep_true.to_dict(),
                     truth=dict(zip(ps.names, truth.tolist())), combinations=comb_labels)
    (out / "results.json").write_text(json.dumps(full_json, indent=1) + "\n")
    print(f"results: {out / 'results.json'}; total {J['total_wall_s']:.0f} s; load avg end {load1[0]:.2f}")
    print(json.dumps(J))


if __name__ == "__main__":
    main()
