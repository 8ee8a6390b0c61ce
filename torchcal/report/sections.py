"""Sections of the loop and calibration reports: Markdown lines, each
quantity in its display unit, times as ISO 8601 dates."""
from __future__ import annotations

from torchcal.report.units import covariate_value, is_time, shown

__all__ = ["stat_cell", "stage_table", "suspects_table", "parameter_section", "flags_section", "candidates_section"]

_STATS = (("mean", "mean"), ("RMSE", "rmse"), ("p95", "p95"), ("max", "max"))


def stat_cell(st, k: str) -> str:
    """One statistic ``k`` of an :class:`~torchcal.measure.records.ErrorStats` (or None) in a table cell."""
    return "–" if st is None or not st.n else f"{st.value(k):.4f}"


def _num(v, fmt: str = ".4f") -> str:
    return "–" if v is None else format(v, fmt)


def stage_table(stages: list) -> list[str]:
    """Error per stage (:class:`~torchcal.measure.records.Stage`): mean, RMSE, 95th percentile and
    max (mm) on the training and held-out rows; per kind of observation when the rows measured
    more than positions."""
    head = [f"{split} {s}" for split in ("train", "test") for s, _ in _STATS]
    L = ["| stage | parameters | " + " | ".join(head) + " |", "|---" * (2 + len(head)) + "|"]
    for s in stages:
        cells = [stat_cell(d, k) for d in (s.train, s.test) for _, k in _STATS]
        L.append(f"| {s.name} | {s.n_params} | " + " | ".join(cells) + " |")
    kinds = stages[-1].train.per_kind if stages[-1].train is not None else None
    if kinds:
        te = (stages[-1].test.per_kind if stages[-1].test is not None else None) or {}
        L += ["", "An observation's error is the Euclidean norm of what it measured: a partial position's measured "
              "axes, a plane contact's distance from its plane, a distance's difference from the measured one. "
              "Final stage, per kind of observation (mm):", "",
              "| measured | n train | train mean | train RMSE | train p95 | test mean | test RMSE | test p95 |",
              "|---|---|---|---|---|---|---|---|"]
        L += [f"| {k} | {v.n} | {stat_cell(v, 'mean')} | {stat_cell(v, 'rmse')} | {stat_cell(v, 'p95')} | "
              f"{stat_cell(te.get(k), 'mean')} | {stat_cell(te.get(k), 'rmse')} | {stat_cell(te.get(k), 'p95')} |"
              for k, v in kinds.items()]
    return L


def orientation_table(stages: list) -> list[str]:
    """Angle error per stage (mrad) of the measured orientations, when the rows measured any."""
    turned = [s for s in stages if s.train is not None and s.train.orientation is not None]
    if not turned:
        return []
    L = ["", "Measured orientations, angle error per stage (mrad):", "",
         "| stage | train mean | train RMSE | train max | test mean | test RMSE | test max |", "|---|---|---|---|---|---|---|"]
    for s in turned:
        tr, te = s.train.orientation, None if s.test is None else s.test.orientation
        L.append(f"| {s.name} | " + " | ".join(stat_cell(d, k) for d in (tr, te) for k in ("mean", "rmse", "max")) + " |")
    return L


def leftover_section(left, figure: str | None) -> list[str]:
    """What the final model still lacks (:class:`~torchcal.pipelines.loop.leftover.Leftover`): its
    cross-validated error against the noise floor, and the signals its residual still follows."""
    if left is None:
        return []
    L = ["## What is left", ""] + [f"- {w}" for w in left.words()]
    if left.associations:
        L += ["", "Strongest associations of the final training residual (the share of its variance a signal "
              "explains, fitted with an intercept to each component):", "", "| signal | kind | R² | best component |",
              "|---|---|---|---|"]
        L += [f"| {a.signal} | {a.kind} | {a.r2:.3f} | {a.axis} |" for a in left.associations]
        if figure:
            L += ["", f"![what the residual still follows]({figure})"]
    return L + [""]


def suspects_table(suspects: list, which: str, advice: str) -> list[str]:
    """The observations farther than 5·√3·σ̂ from the final model, as a table (first 50)."""
    if not suspects:
        return [f"No {which} observation lies farther than 5·√3·σ̂ from the final model."]
    L = [f"{len(suspects)} suspect observation(s) among the {which} rows, farther from the final model than 5·√3·σ̂. "
         f"{advice}", "",
         f"| row (0-based, {which} file order) | marker | measured | error (mm) |", "|---|---|---|---|"]
    L += [f"| {s.row} | {s.marker} | {s.kind or 'position'} | {s.error_mm:.3f} |" for s in suspects[:50]]
    if len(suspects) > 50:
        L.append(f"| … | {len(suspects) - 50} more in report.json | | |")
    return L


def parameter_section(res) -> list[str]:
    """Every identified parameter of the final model with its standard error, and how well its
    set is conditioned."""
    if not res.parameters:
        return []
    L = ["## Identified parameters of the final model", "",
         "Standard errors from the robust noise estimate and the Jacobian at the solution (a prior's pull "
         "included).", "", "| parameter | value | standard error | unit |", "|---|---|---|---|"]
    for p in res.parameters:
        v, u = shown(p["value"], p["unit"], 6)
        e, _ = shown(p.get("std_error"), p["unit"], 3)
        L.append(f"| {p['name']} | {v} | {e} | {u} |")
    o = res.observability or {}
    if o:
        seen = o.get("not_seen_by_data") or []
        held = (f"; held by the prior alone: {', '.join(seen[:8])}" + (" …" if len(seen) > 8 else "")) if seen else ""
        L += ["", f"Condition number of the identified set (unit-norm columns): {_num(o.get('condition'), '.4g')}; "
                  f"observability indices O1 = {_num(o.get('O1'), '.4g')}, O2 = {_num(o.get('O2'), '.4g')}, "
                  f"O3 = {_num(o.get('O3'), '.4g')}, O4 = {_num(o.get('O4'), '.4g')} (rank {o.get('rank')} of "
                  f"{o.get('n_params')} free parameters{held})."]
    if res.setup is not None:
        K = res.robot.n_params
        d = res.setup.describe(res.params.values[K:K + res.setup.n_params])
        L += ["", "### The set-up (identified with the robot, instrument frame)", ""]
        L += [f"- plane {k}: unit normal ({', '.join(f'{x:.6f}' for x in v['normal'])}), offset "
              f"{1e3 * v['offset_m']:.4f} mm (the plane is normalᵀp = offset)" for k, v in d["planes"].items()]
        L += [f"- fixed point {k}: ({', '.join(f'{1e3 * x:.4f}' for x in v)}) mm" for k, v in d["fixed_points"].items()]
    if o.get("not_seen"):
        L += ["", "### What these measurements cannot see", ""]
        L += [f"- **{n}**: {why}" for n, why in o["not_seen"].items()]
    if res.problems():
        L += ["", "**Not fit to deploy:** " + "; ".join(res.problems())]
    return L + [""]


def flags_section(flags: list[dict]) -> list[str]:
    """Warnings about candidates: a covariate whose held-out values leave the training range
    (times as ISO 8601 dates)."""
    if not flags:
        return []
    L = ["## Flags", ""]
    for f in flags:
        c = f["covariate"]
        rng = lambda r: f"{covariate_value(c, r[0])} … {covariate_value(c, r[1])}"  # noqa: E731
        what = "time" if is_time(c) else "covariate"
        L.append(f"- {f['effect']} reads the {what} `{c}`: training range {rng(f['train_range'])}, held-out "
                 f"{rng(f['test_range'])} ({100 * f['fraction_outside']:.0f} % of held-out rows outside): {f['note']}.")
    return L + [""]


def candidates_section(candidates: list) -> list[str]:
    """Every candidate examined (:class:`~torchcal.pipelines.loop.records.Candidate`), with the
    numbers that decided."""
    L = ["## Every candidate examined", "",
         "CV columns decided; the held-out gain (mean, mm) was measured afterwards and steered nothing. A family "
         "(per joint, link or direction) lists the modes its selection kept.", "",
         "| round | candidate | parameters | CV RMSE (mm) | CV gain (mm) | t | held-out gain (mm) | accepted | modes / reason |",
         "|---|---|---|---|---|---|---|---|---|"]
    for c in candidates:
        rnd = "–" if c.round is None else c.round
        if not c.applicable:
            L.append(f"| – | {c.name} | – | – | – | – | – | no | not applicable: {c.reason} |")
        elif c.t is None:
            L.append(f"| {rnd} | {c.name} | – | – | – | – | – | no | {c.reason} |")
        else:
            L.append(f"| {rnd} | {c.name} | {c.n_params} | {_num(c.cv_rmse_mm)} | {_num(c.cv_gain_mm, '+.4f')} | "
                     f"{_num(c.t, '.1f')} | {_num(c.test_gain_mm, '+.4f')} | {'yes' if c.accepted else 'no'} | "
                     f"{', '.join(c.added_modes or c.modes)} |")
    return L

