"""Fleet reports: how every parameter spreads over the robots, which robots stand out, and the
files ``torchcal fleet`` writes (``<robot>/calibrated.urdf``, ``report.md/json``, ``fleet.md/json``).

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

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np

from torchcal.params import display_unit
from torchcal.report.calibration import write_json
from torchcal.report.figures import fleet_figure
from torchcal.report.html import write_html
from torchcal.report.sections import stat_cell
from torchcal.report.units import shown, with_error

__all__ = ["parameter_spread", "sibling_z", "fleet_report", "fleet_markdown", "save_fleet", "MIN_ROBOTS",
           "FALSE_ALARM", "spread_rows", "SPREAD_FIGURE"]

SPREAD_FIGURE = "fleet_spread.png"

MIN_ROBOTS = 5  # fewer robots than this: a median and a MAD say too little to flag anyone
SCREEN = 4.0  # siblings beyond this many robust standard deviations do not set the yardstick
FALSE_ALARM = 0.05  # default chance that a fleet of healthy robots raises any flag
_MAD = 1.4826  # MAD -> standard deviation for a normal distribution


def _columns(results, extra) -> list[tuple[str, str, list[float | None], list[float | None]]]:
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
    s0 = max(_MAD * float(np.median(np.abs(d))), floor)
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
    cols = _columns(results, extra)
    judged = [(n, u, vals, ses) for n, u, vals, ses in cols if sum(v is not None for v in vals) >= MIN_ROBOTS]
    n_tests = sum(sum(v is not None for v in vals) for _, _, vals, _ in judged)
    # the two-sided tail each test may spend: Bonferroni over every robot and parameter judged
    tail = false_alarm / (2 * max(n_tests, 1))
    spread, flags = {}, []
    for n, u, vals, ses in cols:
        who = [i for i, v in enumerate(vals) if v is not None]
        x = np.array([vals[i] for i in who], dtype=float)
        med = float(np.median(x))
        mad = float(np.median(np.abs(x - med)))
        se_all = np.array([ses[i] if ses[i] is not None and math.isfinite(ses[i]) else np.nan for i in who])
        floor = float(np.nanmedian(se_all)) if np.isfinite(se_all).any() else 0.0
        entry = {"unit": u, "n": len(who), "mean": float(x.mean()),
                 "std": float(x.std(ddof=1)) if len(who) > 1 else 0.0,
                 "median": med, "robust_std": _MAD * mad, "median_std_error": floor,
                 "z_scale": max(_MAD * mad, floor), "z_needed": None, "min": float(x.min()), "max": float(x.max()),
                 "outliers": []}
        if len(who) >= MIN_ROBOTS and entry["z_scale"] > 0:
            from scipy import stats  # scipy costs start-up time; only a fleet's spread needs it

            z, k = sibling_z(x, np.nan_to_num(se_all, nan=0.0), floor)
            need = np.maximum(z_threshold, stats.t.isf(tail, k - 1))
            entry["z_needed"] = float(max(z_threshold, stats.t.isf(tail, len(who) - 2)))
            for i, zi, ni in zip(who, z.tolist(), need.tolist()):
                if abs(zi) > ni:
                    entry["outliers"].append(names[i])
                    flags.append({"robot": names[i], "parameter": n, "value": vals[i], "median": med, "z": zi,
                                  "z_needed": ni, "unit": u})
        spread[n] = entry
    flags.sort(key=lambda f: -abs(f["z"]))
    return spread, flags


def _mean_mm(stage, split: str) -> float | None:
    """The mean error (mm) of a :class:`~torchcal.measure.records.Stage` on ``split`` (None: no such rows)."""
    st = getattr(stage, split)
    return None if st is None or not st.n else st.mean




def spread_rows(fr) -> list[dict]:
    """Per parameter judged over the fleet (at least 4 robots fitted it): every robot's distance
    from its siblings in their standard deviations (:func:`sibling_z`), the robots flagged and the
    flag bound, for :func:`~torchcal.report.figures.fleet_figure`."""
    rows = []
    for n, u, vals, ses in _columns(fr.results, fr.effects):
        e = fr.spread.get(n)
        who = [i for i, v in enumerate(vals) if v is not None]
        if e is None or len(who) < 4:
            continue
        x = np.array([vals[i] for i in who], dtype=float)
        se = np.array([ses[i] if ses[i] is not None and math.isfinite(ses[i]) else 0.0 for i in who])
        z, _ = sibling_z(x, se, e["median_std_error"])
        rows.append({"name": n, "z": z, "robots": [fr.names[i] for i in who], "flagged": set(e["outliers"]),
                     "z_needed": e.get("z_needed")})
    return rows


def fleet_report(fr) -> dict:
    """``fleet.json``: robots, parameter spread, flags, the prior and shared effect parameters."""
    robots = []
    flagged: dict[str, list[str]] = {}
    for f in fr.flags:
        flagged.setdefault(f["robot"], []).append(f["parameter"])
    for n, r in zip(fr.names, fr.results):
        robots.append({"robot": n, "n_train": r.n_train, "n_test": r.n_test, "n_params": r.stages[-1].n_params,
                       "train_mean_mm": {s.name: _mean_mm(s, "train") for s in r.stages},
                       "test_mean_mm": {s.name: _mean_mm(s, "test") for s in r.stages} if r.n_test else None,
                       "solver": {"n_iter": r.solver.n_iter, "converged": r.solver.converged,
                                  "message": r.solver.message},
                       "flags": flagged.get(n, [])})
    return {"model": fr.robot.name, "n_robots": len(fr.names), "identify": fr.identify,
            "z_threshold": fr.z_threshold, "false_alarm": fr.false_alarm, "z_needed": _bound(fr),
            "min_robots_for_flags": MIN_ROBOTS, "wall_time_s": fr.wall_time_s,
            "prior": fr.prior, "effects": None if fr.effects is None else
            {k: v for k, v in fr.effects.items() if k in ("names", "units", "shared", "payload")},
            "robots": robots, "flags": fr.flags, "spread": fr.spread}


def fleet_markdown(fr, figure: str | None = None) -> str:
    """``fleet.md``: flags first, then each robot's errors, then the spread of every parameter
    (``figure``: the spread figure's file name, shown with the flags)."""
    last = fr.results[0].stages[-1]["name"]
    lines = [f"# Fleet calibration: {len(fr.names)} × {fr.robot.name}", "",
             f"Identifiable parameters judged {'per robot' if fr.identify == 'per_robot' else 'on the pooled design'}; "
             f"solved together in {fr.wall_time_s:.2f} s.", ""]
    if fr.prior:
        lines += [f"Hierarchical prior: each robot's geometric errors around the fleet mean; noise σ = "
                  f"{fr.prior['sigma_m'] * 1e3:.4f} mm, {fr.prior['n_outer']} rounds of scale estimation.", ""]
    if fr.effects and fr.effects.get("shared"):
        su = fr.effects.get("shared_units", {})
        lines += ["Shared by the fleet: " + ", ".join(f"{k} = {' '.join(shown(v, su.get(k, '')))}"
                                                      for k, v in fr.effects["shared"].items()), ""]
    bound = _bound(fr)
    lines += [f"## Flags (|z| from the siblings > {fr.z_threshold:g}" +
              (f" and > {bound:.1f}, the bound for {len(fr.names)} robots" if bound and bound > fr.z_threshold else "")
              + ")", ""]
    if len(fr.names) < MIN_ROBOTS:
        lines.append(f"Too few robots ({len(fr.names)} < {MIN_ROBOTS}) to flag outliers.")
    else:
        note = ("z is a robot's distance from its siblings' mean in their standard deviations. A fleet of healthy "
                f"robots raises any flag with probability {fr.false_alarm:g}: the bound is the Student-t value for "
                "that chance over every robot and parameter, since a spread estimated from few siblings is itself "
                "uncertain.")
        if bound and bound > fr.z_threshold:
            note += (f" With {len(fr.names)} robots only a parameter about {bound:.0f} standard deviations away is "
                     f"flagged; more robots lower the bound towards {fr.z_threshold:g}.")
        lines.append(note)
        lines.append("")
        if not fr.flags:
            lines.append("No robot stands out.")
        else:
            lines += ["| robot | parameter | value | fleet median | z | bound |", "|---|---|---|---|---|---|"]
            for f in fr.flags:
                sc, us = display_unit(f["unit"])
                lines.append(f"| {f['robot']} | {f['parameter']} | {f['value'] * sc:.4f} {us} | "
                             f"{f['median'] * sc:.4f} {us} | {f['z']:+.1f} | {f['z_needed']:.1f} |")
            lines += ["", "A joint offset far from its siblings usually means a re-mastered or damaged axis. An "
                      "identified parameter also carries what the robot's unidentifiable errors project onto it: "
                      "confirm a flag by measuring that axis again."]
    if figure:
        lines += ["", f"![each parameter's spread over the fleet, flagged robots marked]({figure})"]
    lines += ["", "## Robots", "", f"Errors in mm; {last} model unless marked. Each robot's own report: its name.", "",
              f"| robot | rows | parameters | train mean: nominal → {last} | train RMSE | train p95 | train max | "
              "test mean: nominal → final | test RMSE | test p95 | test max | solver |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for n, r in zip(fr.names, fr.results):
        s0, s1 = r.stages[0], r.stages[-1]
        te = f"{_mean_mm(s0, 'test'):.4f} → {_mean_mm(s1, 'test'):.4f}" if r.n_test else "–"
        cell = lambda split, k: stat_cell(getattr(s1, split), k)  # noqa: E731
        lines.append(f"| [{n}]({n}/report.md) | {r.n_train} | {s1.n_params} | {_mean_mm(s0, 'train'):.4f} → "
                     f"{_mean_mm(s1, 'train'):.4f} | {cell('train', 'rmse')} | {cell('train', 'p95')} | "
                     f"{cell('train', 'max')} | {te} | {cell('test', 'rmse')} | {cell('test', 'p95')} | "
                     f"{cell('test', 'max')} | {r.solver.n_iter} it, {r.solver.message} |")
    lines += ["", "## Parameter spread over the fleet", "",
              "| parameter | robots | mean | std | median | robust std | min | max | unit | flag bound | outliers |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for n, e in fr.spread.items():
        sc, us = display_unit(e["unit"])
        v = " | ".join(f"{e[k] * sc:.4g}" for k in ("mean", "std", "median", "robust_std", "min", "max"))
        zb = "–" if e.get("z_needed") is None else f"{e['z_needed']:.1f}"
        lines.append(f"| {n} | {e['n']} | {v} | {us} | {zb} | {', '.join(e['outliers']) or '–'} |")
    return "\n".join(lines) + "\n"


def _bound(fr) -> float | None:
    """The flag bound of a parameter that every robot fits (fewer robots fit the others, whose
    bounds are higher: each parameter's own is in the spread table)."""
    b = [e["z_needed"] for e in fr.spread.values() if e.get("z_needed") is not None]
    return min(b) if b else None


_SAFE = re.compile(r"^[A-Za-z0-9_.\-]+$")


def save_fleet(fr, out_dir, figures: bool = True) -> Path:
    """Write every robot's calibration (``<out>/<robot>/``) and the fleet report."""
    out = Path(out_dir)
    bad = [n for n in fr.names if not _SAFE.match(n) or n in (".", "..")]
    if bad:
        raise ValueError(f"robot ids {bad[:5]} cannot name folders; use letters, digits, '_', '-' and '.'")
    out.mkdir(parents=True, exist_ok=True)
    for b, (n, r) in enumerate(zip(fr.names, fr.results)):
        d = r.save(out / n) if figures else dataclasses.replace(r, errors={}).save(out / n)
        if fr.effects:
            _add_effects(d, fr.effects, b)
            write_html(d, "report.md", title=f"Calibration of {fr.robot.name}: robot {n}")
    write_json(out / "fleet.json", fr.report())
    fig = None
    if figures and fleet_figure(spread_rows(fr), out / SPREAD_FIGURE, fr.z_threshold,
                                f"{len(fr.names)} × {fr.robot.name}: each parameter's spread, flagged robots "
                                "marked") is not None:
        fig = SPREAD_FIGURE
    (out / "fleet.md").write_text(fleet_markdown(fr, fig))
    write_html(out, "fleet.md", title=f"Fleet calibration: {len(fr.names)} × {fr.robot.name}")
    return out


def _add_effects(d: Path, eff: dict, b: int) -> None:
    """Append a robot's effect parameters (and the shared ones) to its report files."""
    rows = [(n, u, v[b] if isinstance(v, list) else v, s) for n, u, v, s in
            zip(eff["names"], eff["units"], eff["values"][b], eff["std_errors"][b])]
    rep = json.loads((d / "report.json").read_text())
    rep["effects"] = {n: {"value": v, "std_error": s, "unit": u} for n, u, v, s in rows}
    rep["effects_shared"] = eff.get("shared", {})
    write_json(d / "report.json", rep)
    md = ["", "## Effects", "", "| parameter | value ± standard error |", "|---|---|"]
    md += [f"| {n} | {with_error(v, s, u)} |" for n, u, v, s in rows if v is not None]
    md += [f"| {n} (shared by the fleet) | {' '.join(shown(v, eff['shared_units'].get(n, '')))} |"
           for n, v in eff.get("shared", {}).items()]
    with open(d / "report.md", "a") as fh:
        fh.write("\n".join(md) + "\n")
