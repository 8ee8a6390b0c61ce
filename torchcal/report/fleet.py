"""Fleet reports: how every parameter spreads over the robots, which robots stand out, and the
files ``torchcal fleet`` writes (``<robot>/calibrated.urdf``, ``report.md/json``, ``fleet.md/json``).

Outliers are judged by a robust z-score per parameter, ``z = (x − median) / sqrt(s² + se²)``, with
``s = max(1.4826 · MAD, median standard error)`` and ``se`` the robot's own standard error: the
median absolute deviation ignores the outliers it is looking for, the floor keeps a fleet whose
spread is below the measurement precision from flagging noise, and a value the robot's own data
barely fix is not called an outlier. A joint offset 5 s from its siblings is, in practice, a
re-mastered or damaged axis. The instrument frame (``base.*``) is where the tracker stood and the
marker points are the tooling, not properties of the robot, so they are left out.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import torch

from torchcal.params import display_unit
from torchcal.report.calibration import write_json

__all__ = ["parameter_spread", "fleet_report", "fleet_markdown", "save_fleet", "MIN_ROBOTS"]

MIN_ROBOTS = 5  # fewer robots than this: a median and a MAD say too little to flag anyone
# below this many robots, simulated healthy fleets still drew flags (KR5, 0.2x spread: none at 40)
FEW_ROBOTS = 20
_MAD = 1.4826  # MAD -> standard deviation for a normal distribution


def _columns(results, extra) -> list[tuple[str, str, list[float | None], list[float | None]]]:
    """(name, unit, value per robot or None where not fitted, standard error per robot)."""
    p0 = results[0].params
    markers = set(results[0].robot.marker_names)
    cols = []
    for i, (n, u) in enumerate(zip(p0.names, p0.units)):
        if n.startswith("base.") or n.split(".")[0] in markers:
            continue
        vals = [float(r.params.values[i]) if bool(r.params.free[i]) else None for r in results]
        if any(v is not None for v in vals):
            cols.append((n, u, vals, [r.std_errors.get(n) for r in results]))
    if extra:
        for j, (n, u) in enumerate(zip(extra["names"], extra["units"])):
            vals = [v[j] if f[j] else None for v, f in zip(extra["values"], extra["free"])]
            if any(v is not None for v in vals):
                cols.append((n, u, vals, [s[j] for s in extra["std_errors"]]))
    return cols


def parameter_spread(names: list[str], results, z_threshold: float = 5.0, extra: dict | None = None
                     ) -> tuple[dict, list[dict]]:
    """Per parameter: mean, std, median, robust spread and outliers over the robots that fitted it.

    Args:
        names: robot ids; ``results``: their :class:`~torchcal.pipelines.calibrate.CalibrationResult`.
        extra: per-robot effect parameters (``names``, ``units``, ``values``, ``free``,
            ``std_errors``: lists per robot) to include.
    Returns:
        ``(spread, flags)``: ``spread[param]`` holds values in SI units (m, rad, …) and the robots
        beyond ``z_threshold``; ``flags`` lists ``{robot, parameter, value, median, z, unit}``,
        largest ``|z|`` first.
    """
    spread, flags = {}, []
    for n, u, vals, ses in _columns(results, extra):
        who = [i for i, v in enumerate(vals) if v is not None]
        x = torch.tensor([vals[i] for i in who], dtype=torch.float64)
        med = float(x.median())
        mad = float((x - med).abs().median())
        se = [ses[i] for i in who if ses[i] is not None and math.isfinite(ses[i])]
        floor = float(torch.tensor(se, dtype=torch.float64).median()) if se else 0.0
        scale = max(_MAD * mad, floor)
        entry = {"unit": u, "n": len(who), "mean": float(x.mean()), "std": float(x.std()) if len(who) > 1 else 0.0,
                 "median": med, "robust_std": _MAD * mad, "median_std_error": floor, "z_scale": scale,
                 "min": float(x.min()), "max": float(x.max()), "outliers": []}
        if len(who) >= MIN_ROBOTS and scale > 0:
            # a robot's own uncertainty widens its yardstick: a value its data barely fix is no outlier
            own = torch.tensor([ses[i] if ses[i] is not None and math.isfinite(ses[i]) else 0.0 for i in who],
                               dtype=torch.float64)
            z = (x - med) / torch.sqrt(scale ** 2 + own ** 2)
            for i, zi in zip(who, z.tolist()):
                if abs(zi) > z_threshold:
                    entry["outliers"].append(names[i])
                    flags.append({"robot": names[i], "parameter": n, "value": vals[i], "median": med, "z": zi,
                                  "unit": u})
        spread[n] = entry
    flags.sort(key=lambda f: -abs(f["z"]))
    return spread, flags


def _mean_mm(stage: dict | None, split: str) -> float | None:
    d = (stage or {}).get(split) or {}
    return d.get("mean_mm")


def fleet_report(fr) -> dict:
    """``fleet.json``: robots, parameter spread, flags, the prior and shared effect parameters."""
    robots = []
    flagged: dict[str, list[str]] = {}
    for f in fr.flags:
        flagged.setdefault(f["robot"], []).append(f["parameter"])
    for n, r in zip(fr.names, fr.results):
        robots.append({"robot": n, "n_train": r.n_train, "n_test": r.n_test, "n_params": r.stages[-1]["n_params"],
                       "train_mean_mm": {s["name"]: _mean_mm(s, "train") for s in r.stages},
                       "test_mean_mm": {s["name"]: _mean_mm(s, "test") for s in r.stages} if r.n_test else None,
                       "solver": {"n_iter": r.solver.n_iter, "converged": r.solver.converged,
                                  "message": r.solver.message},
                       "flags": flagged.get(n, [])})
    return {"model": fr.robot.name, "n_robots": len(fr.names), "identify": fr.identify,
            "z_threshold": fr.z_threshold, "min_robots_for_flags": MIN_ROBOTS, "wall_time_s": fr.wall_time_s,
            "prior": fr.prior, "effects": None if fr.effects is None else
            {k: v for k, v in fr.effects.items() if k in ("names", "units", "shared", "payload")},
            "robots": robots, "flags": fr.flags, "spread": fr.spread}


def fleet_markdown(fr) -> str:
    """``fleet.md``: flags first, then each robot's errors, then the spread of every parameter."""
    last = fr.results[0].stages[-1]["name"]
    lines = [f"# Fleet calibration: {len(fr.names)} × {fr.robot.name}", "",
             f"Identifiable parameters judged {'per robot' if fr.identify == 'per_robot' else 'on the pooled design'}; "
             f"solved together in {fr.wall_time_s:.2f} s.", ""]
    if fr.prior:
        lines += [f"Hierarchical prior: each robot's geometric errors around the fleet mean; noise σ = "
                  f"{fr.prior['sigma_m'] * 1e3:.4f} mm, {fr.prior['n_outer']} rounds of scale estimation.", ""]
    if fr.effects and fr.effects.get("shared"):
        lines += ["Shared by the fleet: " + ", ".join(f"{k} = {v:.4g}" for k, v in fr.effects["shared"].items()), ""]
    lines += [f"## Flags (robust |z| > {fr.z_threshold:g})", ""]
    if len(fr.names) < MIN_ROBOTS:
        lines.append(f"Too few robots ({len(fr.names)} < {MIN_ROBOTS}) to flag outliers.")
    elif not fr.flags:
        lines.append("No robot stands out.")
    else:
        lines += ["| robot | parameter | value | fleet median | z |", "|---|---|---|---|---|"]
        for f in fr.flags:
            sc, us = display_unit(f["unit"])
            lines.append(f"| {f['robot']} | {f['parameter']} | {f['value'] * sc:.4f} {us} | {f['median'] * sc:.4f} {us} "
                         f"| {f['z']:+.1f} |")
        lines += ["", "A joint offset far from its siblings usually means a re-mastered or damaged axis."]
        if len(fr.names) < FEW_ROBOTS:
            lines += [f"With {len(fr.names)} robots the median and the MAD are themselves uncertain, and an identified "
                      "parameter also carries what the robot's unidentifiable errors project onto it: healthy robots "
                      "of small fleets get flagged too. Confirm a flag by measuring that axis again."]
    lines += ["", "## Robots", "", f"| robot | rows | parameters | train mean: nominal → {last} (mm) | test mean (mm) | "
              "solver |", "|---|---|---|---|---|---|"]
    for n, r in zip(fr.names, fr.results):
        s0, s1 = r.stages[0], r.stages[-1]
        te = f"{_mean_mm(s0, 'test'):.4f} → {_mean_mm(s1, 'test'):.4f}" if r.n_test else "–"
        lines.append(f"| {n} | {r.n_train} | {s1['n_params']} | {_mean_mm(s0, 'train'):.4f} → "
                     f"{_mean_mm(s1, 'train'):.4f} | {te} | {r.solver.n_iter} it, {r.solver.message} |")
    lines += ["", "## Parameter spread over the fleet", "",
              "| parameter | robots | mean | std | median | robust std | min | max | unit | outliers |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for n, e in fr.spread.items():
        sc, us = display_unit(e["unit"])
        v = " | ".join(f"{e[k] * sc:.4g}" for k in ("mean", "std", "median", "robust_std", "min", "max"))
        lines.append(f"| {n} | {e['n']} | {v} | {us} | {', '.join(e['outliers']) or '–'} |")
    return "\n".join(lines) + "\n"


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
    write_json(out / "fleet.json", fr.report())
    (out / "fleet.md").write_text(fr.markdown())
    return out


def _add_effects(d: Path, eff: dict, b: int) -> None:
    """Append a robot's effect parameters (and the shared ones) to its report files."""
    rows = [(n, u, v[b] if isinstance(v, list) else v, s) for n, u, v, s in
            zip(eff["names"], eff["units"], eff["values"][b], eff["std_errors"][b])]
    rep = json.loads((d / "report.json").read_text())
    rep["effects"] = {n: {"value": v, "std_error": s, "unit": u} for n, u, v, s in rows}
    rep["effects_shared"] = eff.get("shared", {})
    write_json(d / "report.json", rep)
    md = ["", "## Effects", "", "| parameter | value | std. error | unit |", "|---|---|---|---|"]
    md += [f"| {n} | {v:.6g} | {s:.3g} | {u} |" for n, u, v, s in rows if v is not None]
    md += [f"| {n} (shared by the fleet) | {v:.6g} | – | {eff['shared_units'].get(n, '')} |"
           for n, v in eff.get("shared", {}).items()]
    with open(d / "report.md", "a") as fh:
        fh.write("\n".join(md) + "\n")
