"""Files a person reads after ``torchcal loop``: report.json, report.md and the figures."""
from __future__ import annotations

from pathlib import Path

from torchcal.params import display_unit
from torchcal.pipelines.loop.result import LoopResult
from torchcal.report.calibration import error_figure, write_json
from torchcal.report.plotting import pyplot

__all__ = ["write_loop_report"]


def _histograms(res: LoopResult, path: Path, split: str) -> bool:
    """Errors before / geometric / full model in one figure: histograms, per axis, cumulative
    distribution with the 95th percentile and the noise floor, error against reach."""
    names = list(res.errors)
    pick = list(dict.fromkeys(n for n in (names[0], "geometric", names[-1]) if n in res.errors))
    label = {names[0]: "before (base registration only)", "geometric": "geometric calibration"}
    stages = [(label.get(n, "full model: " + n.lstrip("+")), res.errors[n][f"{split}_details"]) for n in pick
              if res.errors[n].get(split) is not None and res.errors[n][split].numel()]
    if not stages:
        return False
    error_figure(stages, path, title=f"{res.robot.name}: error before / geometric / full model", split=split,
                 noise_floor_mm=res.noise_floor_mm)
    return True


def _unit_scale(label: str) -> tuple[str, float]:
    """Display a plot axis in a readable unit: rad -> mrad, m -> mm."""
    for u, (v, f) in {"[rad]": ("[mrad]", 1e3), "[m]": ("[mm]", 1e3)}.items():
        if label.endswith(u):
            return label[: -len(u)] + v, f
    return label, 1.0


def _evidence_plot(name: str, ev: dict, path: Path) -> bool:
    """Per mode: the partial residual projected on the mode's displacement against the mode's
    physical signature, with the fitted mode overlaid."""
    if not ev:
        return False
    plt = pyplot()
    keys = list(ev)
    cols = min(3, len(keys))
    rows = (len(keys) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.3 * rows), dpi=110, squeeze=False)
    for ax, k in zip(axes.flat, keys):
        e = ev[k]
        ylabel, f = _unit_scale(e["ylabel"])
        ax.scatter(e["x"], [v * f for v in e["residual"]], s=6, alpha=0.5, label="partial residual")
        ax.scatter(e["x"], [v * f for v in e["fitted"]], s=4, alpha=0.9, label="fitted")
        ax.set_xlabel(e["xlabel"], fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.set_title(f"{k} (r = {e['r']:.2f})", fontsize=9)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"evidence for {name}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def _shown(v: float | None, unit: str) -> tuple[str, str]:
    """A value in a readable unit: m -> mm, rad -> mrad, rad/(N*m) -> µrad/(N·m)."""
    f, u = display_unit(unit)
    return ("–" if v is None else f"{v * f:.6g}"), u


def _parameter_section(res: LoopResult) -> list[str]:
    """Every identified parameter of the final model with its standard error, and how well its
    set is conditioned."""
    if not res.parameters:
        return []
    L = ["## Identified parameters of the final model", "",
         "Standard errors from the robust noise estimate and the Jacobian at the solution (a prior's pull "
         "included).", "", "| parameter | value | standard error | unit |", "|---|---|---|---|"]
    for p in res.parameters:
        v, u = _shown(p["value"], p["unit"])
        e, _ = _shown(p.get("std_error"), p["unit"])
        L.append(f"| {p['name']} | {v} | {e} | {u} |")
    o = res.observability or {}
    if o:
        L += ["", f"Condition number of the identified set (unit-norm columns): {_num(o.get('condition'), '.4g')}; "
                  f"observability indices O1 = {_num(o.get('O1'), '.4g')}, O2 = {_num(o.get('O2'), '.4g')}, "
                  f"O3 = {_num(o.get('O3'), '.4g')}, O4 = {_num(o.get('O4'), '.4g')} (rank {o.get('rank')} of "
                  f"{o.get('n_params')} free parameters"
                  + (f"; held by the prior alone: {', '.join(o['not_seen_by_data'][:8])}"
                     + (" …" if len(o['not_seen_by_data']) > 8 else "") if o.get("not_seen_by_data") else "") + ")."]
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


def _cell(d: dict | None, k: str) -> str:
    return "–" if not d or k not in d else f"{d[k]:.4f}"


def _num(v, fmt: str = ".4f") -> str:
    return "–" if v is None else format(v, fmt)


def _leftover_plot(left, path: Path) -> bool:
    """The residual component each of the strongest remaining signals explains best, against it."""
    if left is None or not left.associations:
        return False
    plt = pyplot()
    ass = left.associations
    fig, axes = plt.subplots(1, len(ass), figsize=(3.4 * len(ass), 3.2), dpi=110, squeeze=False)
    for ax, a in zip(axes[0], ass):
        ax.scatter(a.x, [v * 1e3 for v in a.y], s=6, alpha=0.6)
        ax.set_xlabel(a.signal, fontsize=8)
        ax.set_ylabel(f"residual {a.axis} [mm]", fontsize=8)
        ax.set_title(f"R² = {a.r2:.3f}", fontsize=9)
    fig.suptitle("what the residual still follows", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def _leftover_section(res: LoopResult, out: Path) -> list[str]:
    left = res.leftover
    if left is None:
        return []
    L = ["## What is left", ""] + [f"- {w}" for w in left.words()]
    if left.associations:
        L += ["", "Strongest associations of the final training residual (share of its variance a signal explains, "
              "fitted with an intercept to each component):", "", "| signal | kind | R² | best component |",
              "|---|---|---|---|"]
        L += [f"| {a.signal} | {a.kind} | {a.r2:.3f} | {a.axis} |" for a in left.associations]
        if _leftover_plot(left, out / "leftover.png"):
            L += ["", "![what the residual still follows](leftover.png)"]
    return L + [""]


def write_loop_report(res: LoopResult, out_dir, command: str | None = None) -> Path:
    """Write ``report.json``, ``report.md``, ``errors_test.png`` / ``errors_train.png`` and one
    ``evidence_<stage>.png`` per accepted effect into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = res.report()
    if command:
        rep["command"] = command
    write_json(out / "report.json", rep)
    figs = {s: _histograms(res, out / f"errors_{s}.png", s) for s in ("train", "test")}
    safe = lambda n: "".join(c if c.isalnum() or c in "_-" else "_" for c in n)  # noqa: E731
    ev_figs = {n: _evidence_plot(n, ev, out / f"evidence_{safe(n)}.png") for n, ev in res.evidence.items()}

    L = [f"# Calibration loop: {res.robot.name}", ""]
    if command:
        L += ["Made with:", "", "```", command, "```", ""]
    L += [f"{res.n_train} training rows, {res.n_test} held-out rows"
          + ("" if res.noise_floor_mm is None else f"; noise floor {res.noise_floor_mm:.4f} mm") + ".",
          "Every decision below was made by cross-validation on the training rows; the held-out rows were "
          "only measured.", "", "## Error per stage (mm)", "",
          "| stage | parameters | train mean | train std | train max | test mean | test std | test max |",
          "|---|---|---|---|---|---|---|---|"]
    for s in res.stages:
        tr, te = s.get("train"), s.get("test")
        L.append(f"| {s['name']} | {s['n_params']} | {_cell(tr, 'mean_mm')} | {_cell(tr, 'std_mm')} | "
                 f"{_cell(tr, 'max_mm')} | {_cell(te, 'mean_mm')} | {_cell(te, 'std_mm')} | {_cell(te, 'max_mm')} |")
    turned = [s for s in res.stages if (s.get("train") or {}).get("orientation")]
    if turned:
        L += ["", "Measured orientations, angle error per stage (mrad):", "",
              "| stage | train mean | train max | test mean | test max |", "|---|---|---|---|---|"]
        for s in turned:
            tr, te = s["train"]["orientation"], (s.get("test") or {}).get("orientation")
            L.append(f"| {s['name']} | {_cell(tr, 'mean_mrad')} | {_cell(tr, 'max_mrad')} | {_cell(te, 'mean_mrad')} | "
                     f"{_cell(te, 'max_mrad')} |")
    kinds = (res.stages[-1].get("train") or {}).get("per_kind")
    if kinds:
        L += ["", "An observation's error is the Euclidean norm of what it measured: a partial position's measured "
              "axes, a plane contact's distance from its plane, a distance's difference from the measured one. "
              "Final stage, per kind of observation (mm):", "", "| measured | n train | train mean | test mean |",
              "|---|---|---|---|"]
        te = (res.stages[-1].get("test") or {}).get("per_kind", {})
        L += [f"| {k} | {v['n']} | {v['mean_mm']:.4f} | {_cell(te.get(k), 'mean_mm')} |" for k, v in kinds.items()]
    for split in ("test", "train"):
        if figs.get(split):
            L += ["", f"![errors, {split}: histogram, per axis, cumulative with p95, against reach](errors_{split}.png)"]
    L += ["", "## Noise and outliers", "",
          f"Robust noise estimate of the final model: σ̂ = {_num(res.noise_sigma_mm)} mm per axis (1.4826 × the median "
          f"absolute deviation of the residual components). Every fit uses the Huber loss; the last threshold was "
          f"{_num(res.huber_mm)} mm on the Euclidean error of an observation.", ""]
    if res.suspects:
        L += [f"{len(res.suspects)} suspect observation(s), farther from the final model than 5·√3·σ̂. They stay in "
              "the data: the Huber loss limits their pull, and the comparisons score them as a constant. Check them "
              "(a bumped reflector, a mislabelled marker, a row out of sync).", "",
              "| row (0-based, training file order) | marker | measured | error (mm) |", "|---|---|---|---|"]
        L += [f"| {s['row']} | {s['marker']} | {s.get('kind', 'position')} | {s['error_mm']:.3f} |"
              for s in res.suspects[:50]]
        if len(res.suspects) > 50:
            L.append(f"| … | {len(res.suspects) - 50} more in report.json | | |")
    else:
        L.append("No observation lies farther than 5·√3·σ̂ from the final model.")
    L += ["", "## Geometric parameter set (chosen by cross-validation)", "",
          "| set | parameters (effective) | CV RMSE (mm) | t | accepted |", "|---|---|---|---|---|"]
    for g in res.geometric["sets"]:
        k = g.get("k_eff", g["n_params"])
        acc = "yes" if g.get("accepted") else ("no" if "accepted" in g else "– (scale not chosen)")
        L.append(f"| {g['name']} | {k:.1f} | {g['cv_rmse_mm']:.4f} | {_num(g.get('t'), '.1f')} | {acc} |")
    L += ["", f"Chosen: **{res.geometric['chosen']}**. A larger set is taken only when it passes the rule below, "
              "which is what guards a small data set against over-fitting."]
    if res.prior_mm is not None:
        L += ["", f"The full set carries a Gaussian prior on every geometric error (not the instrument frame nor the "
                  f"marker points) of σ = {res.prior_mm:g} mm for lengths and {res.prior_mm:g} mrad for angles, its "
                  "scale chosen among the tried ones by the penalised CV error. The parameter count is the "
                  "effective one, tr((JᵀJ + W²)⁻¹ JᵀJ)."]
    L += ["", "## What was found", ""]
    if res.accepted:
        for a in res.accepted:
            tg = a.get("test_gain_mm")
            stage = a.get("stage", "+" + a["name"])
            L += [f"### {stage}", ""]
            if a.get("extends"):
                L += [f"Extends the accepted {', '.join(a['extends'])}: its modes are kept and these are added: "
                      f"{', '.join(a.get('added_modes') or [])}.", ""]
            L += [f"- {x}" for x in a.get("found", [])]
            L += [f"- cross-validated gain {a['cv_gain_mm']:+.4f} mm (RMSE); held-out gain "
                  f"{'–' if tg is None else f'{tg:+.4f} mm (mean)'}",
                  f"- evidence: {a['evidence']}"]
            key = stage.lstrip("+")
            if ev_figs.get(key):
                L += ["", f"![evidence for {key}](evidence_{safe(key)}.png)"]
            se = a.get("standard_errors", {})
            L += ["", "| parameter | value | standard error | unit |", "|---|---|---|---|"]
            L += [f"| {n} | {v:.6g} | {_num(se.get(n), '.3g')} | {a.get('units', {}).get(n, '')} |"
                  for n, v in a["params"].items()]
            L.append("")
    else:
        L += ["No effect passed the rule: the geometric model explains the data to within what the "
              "cross-validation can tell from noise.", ""]
    L += _leftover_section(res, out)
    L += _parameter_section(res)
    if res.flags:
        L += ["## Flags", ""]
        for f in res.flags:
            L.append(f"- {f['effect']} reads `{f['covariate']}`: training range {f['train_range'][0]:.6g} … "
                     f"{f['train_range'][1]:.6g}, held-out {f['test_range'][0]:.6g} … {f['test_range'][1]:.6g} "
                     f"({100 * f['fraction_outside']:.0f} % of held-out rows outside): {f['note']}.")
        L.append("")
    L += ["## Every candidate examined", "",
          "CV columns decided; the held-out gain (mean, mm) was measured afterwards and steered nothing. A family "
          "(per joint, link or direction) lists the modes its selection kept.", "",
          "| round | candidate | parameters | CV RMSE (mm) | CV gain (mm) | t | held-out gain (mm) | accepted | modes / reason |",
          "|---|---|---|---|---|---|---|---|---|"]
    for c in res.candidates:
        if c.get("applicable") is False:
            L.append(f"| – | {c['name']} | – | – | – | – | – | no | not applicable: {c.get('reason', '')} |")
            continue
        if "t" not in c:
            L.append(f"| {c.get('round', '–')} | {c['name']} | – | – | – | – | – | no | {c.get('reason', '')} |")
            continue
        modes = ", ".join(c.get("added_modes") or c.get("modes") or [])
        L.append(f"| {c.get('round', '–')} | {c['name']} | {c.get('n_params', '–')} | {c.get('cv_rmse_mm', float('nan')):.4f} | "
                 f"{c.get('cv_gain_mm', float('nan')):+.4f} | {c.get('t', float('nan')):.1f} | "
                 f"{_num(c.get('test_gain_mm'), '+.4f')} | {'yes' if c.get('accepted') else 'no'} | {modes} |")
    L += ["", "Rule: " + rep["rule"] + ".", "",
          "Residual ELM: " + ("kept (it passed the rule)." if res.elm is not None else
                              "not kept: it did not improve the cross-validated error significantly, so what is "
                              "left is not something a black box learns from these rows."), "",
          "## Timings (s)", "", " | ".join(f"{k} {v:.1f}" for k, v in res.timings.items()), ""]
    (out / "report.md").write_text("\n".join(L))
    return out
