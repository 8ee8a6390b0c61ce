"""The 3-RRRU calibration of seed 004 as a pipeline: simulated tracker data on the seed's lines and
a spiral, LM and the real-coded GA on :class:`~torchcal.problems.rrru.RRRUCalibration`, every
calibration evaluated by compensation on every trajectory (the seed's Figs. 9-12), and a Monte
Carlo of the lesson. ``scripts/seed004_rrru_ga.py`` prints and plots what :func:`study` returns.
Lengths in m (mm where a name says so), angles in rad."""
from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_params import PARAM_NAMES
from torchcal.kinematics.rrru_paths import line_trajectories, spiral_trajectory
from torchcal.optim import get_solver
from torchcal.problems.identifiability import jacobian_observability
from torchcal.problems.rrru import DecorrelatedProblem, RRRUCalibration, identifiability, prediction_std
from torchcal.problems.uncertainty import covariance
from torchcal.sim.rrru import compensation, simulate_tracker

__all__ = ["TRUE_ERRORS", "FREE", "calibrate_rrru", "evaluate", "stats", "study", "MM"]

MM = 1e-3
#: The simulated robot's errors (rad, m), seed-sized (Tables 5-6), different per branch.
TRUE_ERRORS = {
    "dtheta_11": 0.0009, "dtheta_21": -0.0006, "dtheta_31": 0.0010,
    "dL_11": 0.25 * MM, "dL_12": 0.19 * MM, "dL_13": -0.14 * MM,
    "dL_21": 0.20 * MM, "dL_22": 0.16 * MM, "dL_23": -0.12 * MM,
    "dL_31": 0.29 * MM, "dL_32": 0.22 * MM, "dL_33": -0.18 * MM,
    "dR": -0.97 * MM, "dr": 0.71 * MM,
}
FREE = [n for n in PARAM_NAMES if n != "dr"]      # identifiable subset (see identifiability)


def calibrate_rrru(model: RRRU, theta: Tensor, meas: Tensor, targets: Tensor, *, seed: int = 0, ga_iter: int = 3000,
                   raw_ga: bool = False) -> dict:
    """LM and the seed's GA (in decorrelated coordinates; also in raw ones with ``raw_ga``) on one data
    set: commanded angles ``theta (N, 3)`` rad, tracker readings ``meas (N, 3)`` m at ``targets (N, 3)``
    m. Returns the problem, the fits (free values, m / rad), LM's covariance and the RMS residuals (m)."""
    prob = RRRUCalibration(model, theta, meas, free=FREE, p0=targets)
    t0 = time.perf_counter()
    lm = get_solver("lm").minimize(prob)
    t_lm = time.perf_counter() - t0
    J, r = lm.extra["jacobian"], lm.extra["residuals"]
    cov = covariance(J, r)
    dec = DecorrelatedProblem(prob)
    t0 = time.perf_counter()
    ga = get_solver("ga", seed=seed, max_iter=ga_iter, mutation_scale=0.05).minimize(dec)
    t_ga = time.perf_counter() - t0
    x_ga = dec.to_x(ga.x)
    out = dict(problem=prob, lm=lm, x_lm=lm.x, x_ga=x_ga, cov=cov, t_lm=t_lm, t_ga=t_ga,
               rms_lm=float(r.pow(2).mean().sqrt()),
               rms_ga=float(prob.residuals(x_ga[None]).pow(2).mean().sqrt()))
    if raw_ga:
        t0 = time.perf_counter()
        gr = get_solver("ga", seed=seed, max_iter=ga_iter, mutation_scale=0.05).minimize(prob)
        out.update(x_ga_raw=gr.x, t_ga_raw=time.perf_counter() - t0,
                   rms_ga_raw=float(prob.residuals(gr.x[None]).pow(2).mean().sqrt()))
    return out


def evaluate(model: RRRU, truth: Tensor, params: Tensor | None, trajs: dict, noise: float, seed: int) -> dict:
    """Compensation errors on every trajectory; the tracker noise of trajectory k is the same draw
    for every calibration (common random numbers)."""
    out = {}
    for k, (name, T) in enumerate(trajs.items()):
        g = torch.Generator().manual_seed(10_000 * seed + 100 + k)
        out[name] = compensation(model, truth, params, T, noise, generator=g)
    return out


def stats(c: dict) -> dict:
    """Max, min and RMS of one compensation run's measured error and the max true error (mm)."""
    d, t = c["distance"] / MM, c["true_distance"] / MM
    return dict(max_mm=float(d.max()), min_mm=float(d.min()), true_max_mm=float(t.max()),
                rms_mm=float(d.pow(2).mean().sqrt()))


def study(*, noise_mm: float = 0.02, seed: int = 0, ga_iter: int = 3000, mc_draws: int = 20,
          raw_ga: bool = True) -> dict:
    """Seed 004's study: simulate lines and a spiral, judge identifiability and observability,
    calibrate each data set with LM and the GA, evaluate every calibration on every trajectory,
    and repeat the LM calibrations for ``mc_draws`` fresh noise draws.

    Args:
        noise_mm: tracker noise, mm (σ per axis); seed: seeds the noise and the GA; ga_iter: GA
            generations; raw_ga: also run the GA in raw parameter coordinates on the spiral.
    Returns:
        ``summary`` (the headline figures, mm), per-run trajectory ``stats``, ``agree`` (GA vs LM in
        LM standard errors), noise ``amp`` lification, observability ``obs``, identifiability
        ``ident``, Monte Carlo rows ``mc``, the calibrations ``cal``, evaluations ``ev``, the
        trajectories and the effective truth ``eff``.
    """
    t_start = time.perf_counter()
    sigma = noise_mm * MM
    model = RRRU()
    truth = torch.tensor([TRUE_ERRORS[n] for n in PARAM_NAMES], dtype=torch.float64)
    # what the fitted parameters can converge to: dR absorbs -dr (only r - R is seen)
    eff = truth[[PARAM_NAMES.index(n) for n in FREE]].clone()
    eff[FREE.index("dR")] = truth[PARAM_NAMES.index("dR")] - truth[PARAM_NAMES.index("dr")]

    lines = line_trajectories()                      # (7, 26, 3)
    spiral = spiral_trajectory()                     # (40, 3)
    trajs = {f"line {k + 1}": lines[k] for k in range(lines.shape[0])}
    trajs["spiral"] = spiral
    names = list(trajs)

    # -- calibration measurements --------------------------------------------------------------
    g = torch.Generator().manual_seed(seed)
    data = {}
    for key, T in (("lines", lines.reshape(-1, 3)), ("spiral", spiral)):
        th, _, meas = simulate_tracker(model, T, truth, sigma, generator=g)
        data[key] = (th, meas, T)

    # -- identifiability and observability of each data set ------------------------------------
    ident = {k: identifiability(model, th, truth, p0=T) for k, (th, _, T) in data.items()}
    Jfree = {k: model.param_jacobian(th, truth, p0=T)[..., [PARAM_NAMES.index(n) for n in FREE]]
             for k, (th, _, T) in data.items()}
    allJ = torch.cat([J.reshape(-1, len(FREE)) for J in Jfree.values()])
    common = torch.linalg.vector_norm(allJ, dim=0) / math.sqrt(allJ.shape[0])
    obs = {k: jacobian_observability(J.reshape(-1, len(FREE)), common) for k, J in Jfree.items()}
    amp = {  # tracker-noise amplification: prediction std / σ at the other data set's poses
        "line_cal_on_lines": prediction_std(Jfree["lines"].reshape(-1, len(FREE)), Jfree["lines"]),
        "line_cal_on_spiral": prediction_std(Jfree["lines"].reshape(-1, len(FREE)), Jfree["spiral"]),
        "spiral_cal_on_spiral": prediction_std(Jfree["spiral"].reshape(-1, len(FREE)), Jfree["spiral"]),
        "spiral_cal_on_lines": prediction_std(Jfree["spiral"].reshape(-1, len(FREE)), Jfree["lines"]),
    }
    poses = {"lines": lines.reshape(-1, 3), "spiral": spiral}
    amp = {k: dict(max=float(v.max()), mean=float(v.mean()),
                   at_mm=(poses[k.split("_on_")[1]][int(v.argmax())] / MM).tolist()) for k, v in amp.items()}

    # -- calibrations ----------------------------------------------------------------------------
    cal = {k: calibrate_rrru(model, th, meas, T, seed=seed, ga_iter=ga_iter, raw_ga=(k == "spiral" and raw_ga))
           for k, (th, meas, T) in data.items()}

    # -- evaluation on every trajectory ----------------------------------------------------------
    runs = {"before": None}
    for k, c in cal.items():
        runs[f"{k}-LM"] = c["problem"].full(c["x_lm"])
        runs[f"{k}-GA"] = c["problem"].full(c["x_ga"])
    ev = {r: evaluate(model, truth, p, trajs, sigma, seed) for r, p in runs.items()}
    st = {r: {n: stats(ev[r][n]) for n in names} for r in runs}

    def worst(run: str, which: str) -> float:
        sel = [n for n in names if (n == "spiral") == (which == "spiral")]
        return max(st[run][n]["max_mm"] for n in sel)

    # -- LM vs GA agreement ----------------------------------------------------------------------
    agree = {}
    for k, c in cal.items():
        sd = c["cov"].diagonal().sqrt()
        z = ((c["x_ga"] - c["x_lm"]) / sd).abs()
        agree[k] = dict(max_abs_z=float(z.max()), worst=FREE[int(z.argmax())],
                        lm_vs_truth_max_abs_z=float(((c["x_lm"] - eff) / sd).abs().max()))
        if "x_ga_raw" in c:
            agree[k]["raw_ga_max_abs_z"] = float(((c["x_ga_raw"] - c["x_lm"]) / sd).abs().max())

    # -- Monte Carlo of the lesson (LM only: cheap) ----------------------------------------------
    # Each draw: fresh calibration noise, fresh evaluation noise; maxima over the lines (all 7)
    # and over the spiral, measured (tracker) and true (noise-free). "perfect" = the controller
    # knows the true parameters, so its measured error is the tracker noise alone: the floor.
    mc = []
    for i in range(mc_draws):
        gi = torch.Generator().manual_seed(1000 + i)
        fits = {"perfect": truth}
        for key, T in (("lines", lines.reshape(-1, 3)), ("spiral", spiral)):
            th, _, meas = simulate_tracker(model, T, truth, sigma, generator=gi)
            p = RRRUCalibration(model, th, meas, free=FREE, p0=T)
            fits[key] = p.full(get_solver("lm").minimize(p).x)
        row = {}
        for key, par in fits.items():
            e = evaluate(model, truth, par, trajs, sigma, 1000 + i)
            for which, sel in (("lines", names[:-1]), ("spiral", ["spiral"])):
                row[f"{key}_cal_on_{which}"] = max(float(e[n]["distance"].max()) for n in sel) / MM
                row[f"{key}_cal_on_{which}_true"] = max(float(e[n]["true_distance"].max()) for n in sel) / MM
        mc.append(row)

    s4 = 4 * noise_mm
    summary = dict(
        tracker_noise_mm=noise_mm,
        before_max_mm=max(worst("before", "lines"), worst("before", "spiral")),
        before_lines_max_mm=worst("before", "lines"), before_spiral_max_mm=worst("before", "spiral"),
        line_cal_on_lines_max_mm=worst("lines-GA", "lines"),
        line_cal_on_spiral_max_mm=worst("lines-GA", "spiral"),
        spiral_cal_on_lines_max_mm=worst("spiral-GA", "lines"),
        spiral_cal_on_spiral_max_mm=worst("spiral-GA", "spiral"),
        lm=dict(line_cal_on_lines_max_mm=worst("lines-LM", "lines"),
                line_cal_on_spiral_max_mm=worst("lines-LM", "spiral"),
                spiral_cal_on_lines_max_mm=worst("spiral-LM", "lines"),
                spiral_cal_on_spiral_max_mm=worst("spiral-LM", "spiral")),
        ga_minus_lm_max_sigma=dict(lines=agree["lines"]["max_abs_z"], spiral=agree["spiral"]["max_abs_z"]),
        raw_ga_minus_lm_max_sigma=agree["spiral"].get("raw_ga_max_abs_z"),
        identifiable=f"{ident['spiral'].rank} of {len(PARAM_NAMES)}", dropped=ident["spiral"].dropped,
        O1=dict(lines=obs["lines"]["O1"], spiral=obs["spiral"]["O1"]),
        condition=dict(lines=obs["lines"]["condition"], spiral=obs["spiral"]["condition"]),
        noise_amplification_max=dict(line_cal_on_spiral=amp["line_cal_on_spiral"]["max"],
                                     spiral_cal_on_lines=amp["spiral_cal_on_lines"]["max"]),
        mc_draws=len(mc),
    )
    if mc:
        med = lambda k: sorted(r[k] for r in mc)[len(mc) // 2]  # noqa: E731
        frac = lambda f: sum(bool(f(r)) for r in mc) / len(mc)  # noqa: E731
        for k in ("lines_cal_on_spiral", "spiral_cal_on_spiral", "spiral_cal_on_lines", "perfect_cal_on_lines",
                  "perfect_cal_on_spiral", "lines_cal_on_spiral_true", "spiral_cal_on_spiral_true",
                  "spiral_cal_on_lines_true"):
            summary[f"mc_{k}_median_mm"] = med(k)
        summary["mc_spiral_cal_within_4sigma_frac"] = frac(
            lambda r: max(r["spiral_cal_on_lines"], r["spiral_cal_on_spiral"]) <= s4)
        summary["mc_noise_alone_within_4sigma_frac"] = frac(
            lambda r: max(r["perfect_cal_on_lines"], r["perfect_cal_on_spiral"]) <= s4)
        summary["mc_line_cal_on_spiral_above_4sigma_frac"] = frac(lambda r: r["lines_cal_on_spiral"] > s4)
        summary["mc_line_cal_worse_on_spiral_true_frac"] = frac(
            lambda r: r["lines_cal_on_spiral_true"] > r["spiral_cal_on_spiral_true"])
    summary["target_spiral_cal_within_4sigma"] = bool(
        max(summary["spiral_cal_on_lines_max_mm"], summary["spiral_cal_on_spiral_max_mm"],
            summary["lm"]["spiral_cal_on_lines_max_mm"], summary["lm"]["spiral_cal_on_spiral_max_mm"]) <= s4)
    summary["target_lm_ga_agree_1sigma"] = bool(max(summary["ga_minus_lm_max_sigma"].values()) <= 1.0)
    summary["lesson_line_cal_fails_spiral"] = bool(summary["line_cal_on_spiral_max_mm"] > s4
                                                   and summary["lm"]["line_cal_on_spiral_max_mm"] > s4)
    summary["wall_s"] = round(time.perf_counter() - t_start, 1)
    return dict(summary=summary, stats=st, agree=agree, amp=amp, obs=obs, ident=ident, mc=mc, cal=cal, ev=ev,
                trajs=trajs, names=names, eff=eff, sigma=sigma, t_start=t_start)
