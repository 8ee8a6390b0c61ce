"""Fleet reports: the files ``torchcal fleet`` writes (``<robot>/calibrated.urdf``,
``report.md/json``, ``fleet.md/json``, the spread figure), from a
:class:`~torchcal.pipelines.fleet.result.FleetResult`. The statistics they show (each robot's
distance from its siblings, the flag bound) are :mod:`torchcal.pipelines.fleet.spread`'s.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Callable

import numpy as np

from torchcal.params import display_unit
from torchcal.pipelines.fleet.spread import MIN_ROBOTS, parameter_columns, sibling_z
from torchcal.report.calibration import save_calibration, write_json
from torchcal.report.figures import fleet_figure
from torchcal.report.html import write_html
from torchcal.report.sections import stat_cell
from torchcal.report.units import shown, with_error

__all__ = ["fleet_report", "fleet_markdown", "save_fleet", "spread_rows", "SPREAD_FIGURE"]

SPREAD_FIGURE = "fleet_spread.png"


def _mean_mm(stage, split: str) -> float | None:
    """The mean error (mm) of a :class:`~torchcal.measure.records.Stage` on ``split`` (None: no such rows)."""
    st = getattr(stage, split)
    return None if st is None or not st.n else st.mean


def spread_rows(fr) -> list[dict]:
    """Per parameter judged over the fleet (at least 4 robots fitted it): every robot's distance
    from its siblings in their standard deviations
    (:func:`~torchcal.pipelines.fleet.spread.sibling_z`), the robots flagged and the flag bound,
    for :func:`~torchcal.report.figures.fleet_figure`."""
    rows = []
    for n, u, vals, ses in parameter_columns(fr.results, fr.effects):
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


def save_fleet(fr, out_dir, figures: bool = True, on_robot: Callable[[str], None] | None = None,
               with_markers: bool = False) -> Path:
    """Write every robot's calibration (``<out>/<robot>/``; ``with_markers``: a link per marker in
    its URDF) and the fleet report; ``on_robot(id)`` is called after each robot's folder is
    written (a progress bar's tick)."""
    out = Path(out_dir)
    bad = [n for n in fr.names if not _SAFE.match(n) or n in (".", "..")]
    if bad:
        raise ValueError(f"robot ids {bad[:5]} cannot name folders; use letters, digits, '_', '-' and '.'")
    out.mkdir(parents=True, exist_ok=True)
    for b, (n, r) in enumerate(zip(fr.names, fr.results)):
        d = save_calibration(r if figures else dataclasses.replace(r, errors={}), out / n, with_markers=with_markers)
        if fr.effects:
            _add_effects(d, fr.effects, b)
            write_html(d, "report.md", title=f"Calibration of {fr.robot.name}: robot {n}")
        if on_robot is not None:
            on_robot(n)
    write_json(out / "fleet.json", fleet_report(fr))
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
