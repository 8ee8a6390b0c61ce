"""The 3-RRRU calibration of seed 004 as a study: simulated tracker data on the seed's lines and a
spiral, LM and the real-coded GA on each (:mod:`torchcal.pipelines.rrru`), every calibration
evaluated by compensation on every trajectory (the seed's Figs. 9-12), and a Monte Carlo of the
lesson. ``scripts/seed004_rrru_ga.py`` prints and plots what :func:`study` returns. Lengths in m
(mm where a name says so), angles in rad."""
from __future__ import annotations

import time

import torch
from torch import Tensor

from torchcal.kinematics.rrru import RRRU
from torchcal.kinematics.rrru_params import PARAM_NAMES
from torchcal.kinematics.rrru_paths import line_trajectories, spiral_trajectory
from torchcal.optim import get_solver
from torchcal.pipelines.rrru import FREE, MM, calibrate_rrru, data_observability
from torchcal.problems.rrru import RRRUCalibration
from torchcal.sim.rrru import compensation, simulate_tracker

__all__ = ["TRUE_ERRORS", "evaluate", "stats", "study"]

#: The simulated robot's errors (rad, m), seed-sized (Tables 5-6), different per branch.
TRUE_ERRORS = {
    "dtheta_11": 0.0009, "dtheta_21": -0.0006, "dtheta_31": 0.0010,
    "dL_11": 0.25 * MM, "dL_12": 0.19 * MM, "dL_13": -0.14 * MM,
    "dL_21": 0.20 * MM, "dL_22": 0.16 * MM, "dL_23": -0.12 * MM,
    "dL_31": 0.29 * MM, "dL_32": 0.22 * MM, "dL_33": -0.18 * MM,
    "dR": -0.97 * MM, "dr": 0.71 * MM,
}


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


def _effective_truth(truth: Tensor) -> Tensor:
    """What the fitted parameters can converge to: dR absorbs -dr (only r - R is seen)."""
    eff = truth[[PARAM_NAMES.index(n) for n in FREE]].clone()
    eff[FREE.index("dR")] = truth[PARAM_NAMES.index("dR")] - truth[PARAM_NAMES.index("dr")]
    return eff


def _agreement(cal: dict, eff: Tensor) -> dict:
    """GA vs LM (and LM vs the effective truth) per data set, in LM standard errors."""
    agree = {}
    for k, c in cal.items():
        sd = c["cov"].diagonal().sqrt()
        z = ((c["x_ga"] - c["x_lm"]) / sd).abs()
        agree[k] = dict(max_abs_z=float(z.max()), worst=FREE[int(z.argmax())],
                        lm_vs_truth_max_abs_z=float(((c["x_lm"] - eff) / sd).abs().max()))
        if "x_ga_raw" in c:
            agree[k]["raw_ga_max_abs_z"] = float(((c["x_ga_raw"] - c["x_lm"]) / sd).abs().max())
    return agree


def _monte_carlo(model: RRRU, truth: Tensor, sets: dict, trajs: dict, sigma: float, draws: int) -> list[dict]:
    """The lesson over ``draws`` noise draws (LM only: cheap). Each draw: fresh calibration noise,
    fresh evaluation noise; maxima over the lines (all 7) and over the spiral, measured (tracker)
    and true (noise-free). "perfect" = the controller knows the true parameters, so its measured
    error is the tracker noise alone: the floor."""
    names = list(trajs)
    mc = []
    for i in range(draws):
        gi = torch.Generator().manual_seed(1000 + i)
        fits = {"perfect": truth}
        for key, T in sets.items():
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
    return mc


def _worst(st: dict, run: str, which: str) -> float:
    """Largest measured error (mm) of ``run`` over the spiral or over the lines."""
    return max(v["max_mm"] for n, v in st[run].items() if (n == "spiral") == (which == "spiral"))


def _summary(noise_mm: float, st: dict, agree: dict, ident: dict, obs: dict, amp: dict) -> dict:
    """The headline figures of one draw (mm)."""
    w = lambda run, which: _worst(st, run, which)  # noqa: E731
    return dict(
        tracker_noise_mm=noise_mm,
        before_max_mm=max(w("before", "lines"), w("before", "spiral")),
        before_lines_max_mm=w("before", "lines"), before_spiral_max_mm=w("before", "spiral"),
        line_cal_on_lines_max_mm=w("lines-GA", "lines"),
        line_cal_on_spiral_max_mm=w("lines-GA", "spiral"),
        spiral_cal_on_lines_max_mm=w("spiral-GA", "lines"),
        spiral_cal_on_spiral_max_mm=w("spiral-GA", "spiral"),
        lm=dict(line_cal_on_lines_max_mm=w("lines-LM", "lines"),
                line_cal_on_spiral_max_mm=w("lines-LM", "spiral"),
                spiral_cal_on_lines_max_mm=w("spiral-LM", "lines"),
                spiral_cal_on_spiral_max_mm=w("spiral-LM", "spiral")),
        ga_minus_lm_max_sigma=dict(lines=agree["lines"]["max_abs_z"], spiral=agree["spiral"]["max_abs_z"]),
        raw_ga_minus_lm_max_sigma=agree["spiral"].get("raw_ga_max_abs_z"),
        identifiable=f"{ident['spiral'].rank} of {len(PARAM_NAMES)}", dropped=ident["spiral"].dropped,
        O1=dict(lines=obs["lines"]["O1"], spiral=obs["spiral"]["O1"]),
        condition=dict(lines=obs["lines"]["condition"], spiral=obs["spiral"]["condition"]),
        noise_amplification_max=dict(line_cal_on_spiral=amp["line_cal_on_spiral"]["max"],
                                     spiral_cal_on_lines=amp["spiral_cal_on_lines"]["max"]),
    )


def _monte_carlo_summary(summary: dict, mc: list[dict], s4: float) -> None:
    """Medians of the Monte Carlo maxima and how often the lesson's targets hold (into ``summary``)."""
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


def _targets(summary: dict, s4: float) -> None:
    """Whether the seed's targets and its lesson hold on this draw (into ``summary``)."""
    lm = summary["lm"]
    summary["target_spiral_cal_within_4sigma"] = bool(
        max(summary["spiral_cal_on_lines_max_mm"], summary["spiral_cal_on_spiral_max_mm"],
            lm["spiral_cal_on_lines_max_mm"], lm["spiral_cal_on_spiral_max_mm"]) <= s4)
    summary["target_lm_ga_agree_1sigma"] = bool(max(summary["ga_minus_lm_max_sigma"].values()) <= 1.0)
    summary["lesson_line_cal_fails_spiral"] = bool(summary["line_cal_on_spiral_max_mm"] > s4
                                                   and lm["line_cal_on_spiral_max_mm"] > s4)


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
    eff = _effective_truth(truth)
    lines = line_trajectories()                      # (7, 26, 3)
    spiral = spiral_trajectory()                     # (40, 3)
    trajs = {f"line {k + 1}": lines[k] for k in range(lines.shape[0])}
    trajs["spiral"] = spiral
    names = list(trajs)
    sets = {"lines": lines.reshape(-1, 3), "spiral": spiral}

    g = torch.Generator().manual_seed(seed)
    data = {}
    for key, T in sets.items():
        th, _, meas = simulate_tracker(model, T, truth, sigma, generator=g)
        data[key] = (th, meas, T)
    ident, obs, amp = data_observability(model, truth, data)
    cal = {k: calibrate_rrru(model, th, meas, T, seed=seed, ga_iter=ga_iter, raw_ga=(k == "spiral" and raw_ga))
           for k, (th, meas, T) in data.items()}

    runs = {"before": None}
    for k, c in cal.items():
        runs[f"{k}-LM"] = c["problem"].full(c["x_lm"])
        runs[f"{k}-GA"] = c["problem"].full(c["x_ga"])
    ev = {r: evaluate(model, truth, p, trajs, sigma, seed) for r, p in runs.items()}
    st = {r: {n: stats(ev[r][n]) for n in names} for r in runs}
    agree = _agreement(cal, eff)
    mc = _monte_carlo(model, truth, sets, trajs, sigma, mc_draws)

    s4 = 4 * noise_mm
    summary = {**_summary(noise_mm, st, agree, ident, obs, amp), "mc_draws": len(mc)}
    if mc:
        _monte_carlo_summary(summary, mc, s4)
    _targets(summary, s4)
    summary["wall_s"] = round(time.perf_counter() - t_start, 1)
    return dict(summary=summary, stats=st, agree=agree, amp=amp, obs=obs, ident=ident, mc=mc, cal=cal, ev=ev,
                trajs=trajs, names=names, eff=eff, sigma=sigma, t_start=t_start)
