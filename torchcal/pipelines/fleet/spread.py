"""How every parameter spreads over a fleet's robots, and which robots stand out (the statistics
:mod:`torchcal.report.fleet` reports).

A robot's parameter is judged against its siblings: ``z = (x − m) / sqrt(s² (1 + 1/k) + se²)``,
with ``m`` and ``s`` the mean and standard deviation of the ``k`` siblings that lie within
:data:`SCREEN` robust standard deviations (1.4826 · MAD) of the fleet median, ``s`` floored at the
median standard error (a fleet whose spread is below the measurement precision does not flag
noise), and ``se`` the robot's own standard error (a value its own data barely fix is no outlier).
Leaving the robot itself and the far siblings out of ``m`` and ``s`` keeps one damaged robot from
hiding itself or another.

A robot is flagged where ``|z|`` exceeds both ``z_threshold`` (5: in practice a re-mastered or
damaged axis) and the Student-t bound at which a fleet of healthy robots with normally spread
parameters would raise any flag at all with probability ``false_alarm`` (Bonferroni over every
robot and parameter, ``k − 1`` degrees of freedom). A spread estimated from a handful of siblings
is itself uncertain: with 6 robots the bound is about 13, with 10 about 7, and from about 20
robots on ``z_threshold`` decides alone. The instrument frame (``base.*``) is where the tracker
stood and the marker points are the tooling, not properties of the robot, so they are left out.
"""
from __future__ import annotations

import math

import numpy as np

from torchcal.measure.noise import mad_sigma

__all__ = ["parameter_spread", "parameter_columns", "sibling_z", "MIN_ROBOTS", "FALSE_ALARM", "SCREEN"]

MIN_ROBOTS = 5  # fewer robots than this: a median and a MAD say too little to flag anyone
SCREEN = 4.0  # siblings beyond this many robust standard deviations do not set the yardstick
FALSE_ALARM = 0.05  # default chance that a fleet of healthy robots raises any flag


def parameter_columns(results, extra) -> list[tuple[str, str, list[float | None], list[float | None]]]:
    """(name, unit, value per robot or None where not fitted, standard error per robot)."""
    if hasattr(results, "table"):  # a fleet's results, built lazily: read its tensors, build no robot's result
        t = results.table()
        pnames, punits, markers = t["names"], t["units"], set(t["markers"])
        values, free, ses = t["values"], t["free"], t["std_errors"]
    else:
        p0 = results[0].params
        pnames, punits, markers = p0.names, p0.units, set(results[0].robot.marker_names)
        values = [r.params.values.tolist() for r in results]  # one conversion per robot, not per entry
        free = [r.params.free.tolist() for r in results]
        ses = None
    cols = []
    for i, (n, u) in enumerate(zip(pnames, punits)):
        if n.startswith("base.") or n.split(".")[0] in markers:
            continue
        vals = [v[i] if f[i] else None for v, f in zip(values, free)]
        if any(v is not None for v in vals):
            se = [r.std_errors.get(n) for r in results] if ses is None else [s[i] if f[i] else None
                                                                               for s, f in zip(ses, free)]
            cols.append((n, u, vals, se))
    if extra:
        for j, (n, u) in enumerate(zip(extra["names"], extra["units"])):
            vals = [v[j] if f[j] else None for v, f in zip(extra["values"], extra["free"])]
            if any(v is not None for v in vals):
                cols.append((n, u, vals, [s[j] for s in extra["std_errors"]]))
    return cols


def sibling_z(x: np.ndarray, se: np.ndarray, floor: float = 0.0, screen: float = SCREEN
              ) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's distance from its siblings in their standard deviations.

    Args:
        x: ``(n,)`` one parameter over the ``n ≥ 4`` robots that fitted it; ``se``: ``(n,)`` their
            standard errors (0 where unknown); ``floor``: the least standard deviation the siblings
            are given (the measurement precision), in the parameter's unit.
    Returns:
        ``(z, k)``: ``(n,)`` z-scores as the module docstring defines them, and how many siblings
        set each robot's yardstick (its Student-t bound has ``k − 1`` degrees of freedom).
    """
    n = x.size
    if n < 4:
        raise ValueError(f"sibling_z needs at least 4 robots (3 siblings to estimate a spread), got {n}")
    med = float(np.median(x))
    d = x - med  # centred: the sums below then lose no digits to the parameter's nominal size
    s0 = max(mad_sigma(d, center=0.0), floor)
    near = np.abs(d) <= screen * s0 if s0 > 0 else np.ones(n, dtype=bool)
    # leave-one-out sums over each robot's siblings: the near ones, or all of them where fewer than
    # 3 near siblings are left to say how far is far
    k = near.sum() - near
    few = k < 3
    w = near.astype(float)
    s1 = np.where(few, d.sum() - d, (w * d).sum() - near * d)
    s2 = np.where(few, (d * d).sum() - d * d, (w * d * d).sum() - near * d * d)
    k = np.where(few, n - 1, k)
    mean = s1 / k
    var = np.maximum(s2 - k * mean * mean, 0.0) / (k - 1)
    s = np.maximum(np.sqrt(var), floor)
    den = np.sqrt(s * s * (1.0 + 1.0 / k) + se * se)
    z = np.where(den > 0, (d - mean) / np.where(den > 0, den, 1.0), 0.0)
    return z, k


def parameter_spread(names: list[str], results, z_threshold: float = 5.0, extra: dict | None = None,
                     false_alarm: float = FALSE_ALARM) -> tuple[dict, list[dict]]:
    """Per parameter: mean, std, median, robust spread and outliers over the robots that fitted it.

    Args:
        names: robot ids; ``results``: their :class:`~torchcal.pipelines.calibrate.CalibrationResult`.
        z_threshold: the least ``|z|`` that flags (see the module docstring).
        extra: per-robot effect parameters (``names``, ``units``, ``values``, ``free``,
            ``std_errors``: lists per robot) to include.
        false_alarm: the chance that a fleet of healthy robots raises any flag; with few robots it
            raises the bound above ``z_threshold``.
    Returns:
        ``(spread, flags)``: ``spread[param]`` holds values in SI units (m, rad, …), the bound
        ``z_needed`` (at ``n − 1`` siblings) and the robots flagged; ``flags`` lists ``{robot,
        parameter, value, median, z, z_needed, unit}``, largest ``|z|`` first.
    """
    cols = parameter_columns(results, extra)
    judged = [(n, u, vals, ses) for n, u, vals, ses in cols if sum(v is not None for v in vals) >= MIN_ROBOTS]
    n_tests = sum(sum(v is not None for v in vals) for _, _, vals, _ in judged)
    # the two-sided tail each test may spend: Bonferroni over every robot and parameter judged
    tail = false_alarm / (2 * max(n_tests, 1))
    spread, flags = {}, []
    for n, u, vals, ses in cols:
        who = [i for i, v in enumerate(vals) if v is not None]
        x = np.array([vals[i] for i in who], dtype=float)
        med = float(np.median(x))
        rstd = mad_sigma(x)
        se_all = np.array([ses[i] if ses[i] is not None and math.isfinite(ses[i]) else np.nan for i in who])
        floor = float(np.nanmedian(se_all)) if np.isfinite(se_all).any() else 0.0
        entry = {"unit": u, "n": len(who), "mean": float(x.mean()),
                 "std": float(x.std(ddof=1)) if len(who) > 1 else 0.0,
                 "median": med, "robust_std": rstd, "median_std_error": floor,
                 "z_scale": max(rstd, floor), "z_needed": None, "min": float(x.min()), "max": float(x.max()),
                 "outliers": []}
        if len(who) >= MIN_ROBOTS and entry["z_scale"] > 0:
            # Student-t's upper tail bound, -stdtrit(df, p) = t.isf(p, df), from scipy.special: scipy.stats
            # costs half a second of import
            from scipy.special import stdtrit

            z, k = sibling_z(x, np.nan_to_num(se_all, nan=0.0), floor)
            need = np.maximum(z_threshold, -stdtrit(k - 1, tail))
            entry["z_needed"] = float(max(z_threshold, -stdtrit(len(who) - 2, tail)))
            for i, zi, ni in zip(who, z.tolist(), need.tolist()):
                if abs(zi) > ni:
                    entry["outliers"].append(names[i])
                    flags.append({"robot": names[i], "parameter": n, "value": vals[i], "median": med, "z": zi,
                                  "z_needed": ni, "unit": u})
        spread[n] = entry
    flags.sort(key=lambda f: -abs(f["z"]))
    return spread, flags
