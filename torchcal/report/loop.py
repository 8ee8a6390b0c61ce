"""Files a person reads after ``torchcal loop``: report.json, report.md, report.html and the
figures. Every quantity is shown in its display unit (:mod:`torchcal.report.units`), a finding is
stated only when significant (:mod:`torchcal.report.findings`), and each finding links to its
evidence figure."""
from __future__ import annotations

import math
import re
from pathlib import Path

from torchcal.effects.shapes import break_words
from torchcal.report.calibration import write_json
from torchcal.report.drivers import driver_figure
from torchcal.report.figures import error_figure, evidence_figure, joint_rank, leftover_figure
from torchcal.report.findings import effect_findings
from torchcal.report.html import write_html
from torchcal.report.sections import (candidates_section, flags_section, leftover_section, orientation_table,
                                      parameter_section, stage_table, suspects_table)
from torchcal.report.units import SIGNIFICANT_Z, shown, with_error, z_score

__all__ = ["write_loop_report", "loop_json", "loop_findings"]


def _histograms(res, path: Path, split: str) -> bool:
    """Errors before / geometric / full model in one figure: histograms, per axis, cumulative
    distribution with the 95th percentile and the noise floor, error against reach."""
    names = list(res.errors)
    pick = list(dict.fromkeys(n for n in (names[0], "geometric", names[-1]) if n in res.errors))
    label = {names[0]: "before (base registration only)", "geometric": "geometric calibration"}
    details = {n: res.errors[n].plotted(split) for n in pick}
    stages = [(label.get(n, "full model: " + n.lstrip("+")), d) for n, d in details.items() if d is not None]
    if not stages:
        return False
    error_figure(stages, path, title=f"{res.robot.name}: error before / geometric / full model", split=split,
                 noise_floor_mm=res.noise_floor_mm)
    return True


def loop_json(res) -> dict:
    """``report.json`` of a :class:`~torchcal.pipelines.loop.result.LoopResult`."""
    setup = None if res.setup is None else res.setup.describe(
        res.params.values[res.robot.n_params:res.robot.n_params + res.setup.n_params])
    return {"robot": res.robot.name, "n_train": res.n_train, "n_test": res.n_test,
            "noise_floor_mm": res.noise_floor_mm, "noise_floor_source": res.noise_floor_source,
            "noise_sigma_mm": res.noise_sigma_mm, "huber_threshold_mm": res.huber_mm,
            "stages": [s.to_json() for s in res.stages], "effects": [a.to_json() for a in res.accepted],
            "candidates": [c.to_json() for c in res.candidates], "geometric_set": res.geometric,
            "prior_mm": res.prior_mm, "suspect_rows": [s.to_json() for s in res.suspects], "flags": res.flags,
            "parameters": res.parameters,
            "observability": res.observability, "problems": res.problems(), "setup": setup, "rule": res.rule,
            "residual_elm": res.elm is not None, "timings_s": res.timings,
            "leftover": None if res.leftover is None else res.leftover.report(), "removed_modes": res.removed,
            "breaks_placed": res.breaks_placed,
            "heldout_check": None if getattr(res, "heldout", None) is None else res.heldout.to_json()}


def _revisions(res) -> list[str]:
    """What later rounds changed in what earlier ones found: modes removed, breaks placed again."""
    L = []
    if res.removed:
        L += ["Accepted once, then explained by later findings and removed: "
              + ", ".join(f"{g['effect']} {g['mode']} (" + ("its parameters dropped for identifiability"
                                                              if g["t"] is None else f"t = {g['t']:.1f}") + ")"
                          for g in res.removed) + ".", ""]
    moved = [b for b in res.breaks_placed if b["kept"]]
    if moved:
        L += ["Placed again once the model around them was fitted (the same parameters, the change at a neighbouring "
              "place that fits the training rows better): " + ", ".join(
                  f"the change at {break_words(b['break'])} moved to {break_words(b['to'])} (CV "
                  f"{b['cv_rmse_mm_before']:.4f} → {b['cv_rmse_mm_after']:.4f} mm)" for b in moved) + ".", ""]
    return L


def loop_findings(res) -> list[dict]:
    """Per accepted stage, what may be stated (:func:`~torchcal.report.findings.effect_findings`)."""
    by_name = {e.name: e for e in res.effects}
    out = []
    for a in res.accepted:
        eff = by_name.get(a["name"])
        if eff is None:
            continue
        f = effect_findings(eff, a["params"], a.get("standard_errors", {}))
        out.append({"stage": a.get("stage", "+" + a["name"]), **f.to_dict()})
    return out


def _safe(n: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in n)


def _evidence_figures(name: str, ev: dict, out: Path, order: list[str]) -> dict[str, str]:
    """One evidence figure per mode (``evidence_<effect>_<mode>.png``), so that each finding links to
    its own: mode label -> file name, in joint order."""
    figs = {}
    for k in sorted(ev, key=lambda k: joint_rank(k, order)):
        f = f"evidence_{_safe(name)}_{_safe(k)}.png"
        if evidence_figure(name, {k: ev[k]}, out / f, order) is not None:
            figs[k] = f
    return figs


def _own_figure(sentence: str, figs: dict[str, str]) -> str | None:
    """The figure of the mode a stated finding speaks of: the mode, or its joint, named earliest in
    the sentence (the only one where the effect has one)."""
    hits = []
    for k, f in figs.items():
        for word in (k, k.split(".")[0]):
            m = re.search(r"(?<![\w.])" + re.escape(word) + r"(?![\w])", sentence)
            if m:
                hits.append((m.start(), -len(word), f))
                break
    if hits:
        return min(hits)[2]
    return next(iter(figs.values())) if len(figs) == 1 else None


def _effect_section(res, findings: list[dict], ev_figs: dict) -> list[str]:
    L = ["## What was found", ""]
    if not res.accepted:
        return L + ["No effect passed the rule: the geometric model explains the data to within what the "
                    "cross-validation can tell from noise.", ""]
    L += [f"An effect is accepted on its cross-validated gain; each of its modes is then stated only when its value "
          f"lies more than {SIGNIFICANT_Z:g} standard errors from zero (a group of values: the chi-square bound of the "
          "same chance).", ""]
    by_stage = {f["stage"]: f for f in findings}
    for a in res.accepted:
        tg = a.get("test_gain_mm")
        stage = a.get("stage", "+" + a["name"])
        key = stage.lstrip("+")
        figs = ev_figs.get(key) or {}
        L += [f"### {stage}", ""]
        if a.get("extends"):
            L += [f"Extends the accepted {', '.join(a['extends'])}: its modes are kept and these are added: "
                  f"{', '.join(a.get('added_modes') or [])}.", ""]
        f = by_stage.get(stage, {})
        for x in f.get("stated", []):
            own = _own_figure(x, figs)
            L.append(f"- {x}" + (f" ([evidence]({own}))" if own else ""))
        if not f.get("stated"):
            L.append("- no mode of it is significant on its own: the gain comes from the modes together")
        if f.get("not_significant"):
            L += ["- measured but not significant, so not stated as findings: " + "; ".join(f["not_significant"])]
        L += [f"- cross-validated gain {a['cv_gain_mm']:+.4f} mm (RMSE); held-out gain "
              f"{'–' if tg is None else f'{tg:+.4f} mm (mean)'}", f"- evidence: {a['evidence']}"]
        if figs:
            L.append("")
            L += [f"![evidence for {key}: {k}]({fig})" for k, fig in figs.items()]
        se = a.get("standard_errors", {})
        units = a.get("units", {})
        L += ["", "| parameter | value ± standard error | z = value / s.e. |", "|---|---|---|"]
        for n, v in a["params"].items():
            z = z_score(v, se.get(n))
            L.append(f"| {n} | {with_error(v, se.get(n), units.get(n, ''))} | {'–' if math.isnan(z) else f'{z:.1f}'} |")
        L.append("")
    return L


def write_loop_report(res, out_dir, command: str | None = None) -> Path:
    """Write ``report.json``, ``report.md``, ``report.html``, ``errors_test.png`` /
    ``errors_train.png`` and one ``evidence_<stage>.png`` per accepted effect into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = loop_json(res)
    findings = loop_findings(res)
    held = res.heldout_suspects()
    rep.update({"findings": findings, "suspect_rows_test": held, "significance_z": SIGNIFICANT_Z})
    by_stage = {f["stage"]: f for f in findings}
    for a in rep["effects"]:  # "found" keeps its place but says only what is significant
        f = by_stage.get(a.get("stage", "+" + a["name"]))
        if f is not None:
            a["found"], a["not_significant"] = f["stated"], f["not_significant"]
    if command:
        rep["command"] = command
    write_json(out / "report.json", rep)
    figs = {s: _histograms(res, out / f"errors_{s}.png", s) for s in ("train", "test")}
    order = [jt.name for jt in res.robot.joints]
    ev_figs = {n: _evidence_figures(n, ev, out, order) for n, ev in res.evidence.items()}
    for n, ev in res.evidence.items():  # a parameter that follows a driver: drawn against that driver
        if n.startswith("+parameter_drivers") or n == "parameter_drivers":
            driver_figure(ev, out / f"drivers_{_safe(n)}.png")

    floor = "no noise floor known" if res.noise_floor_mm is None else (
        f"noise floor {res.noise_floor_mm:.4f} mm, {res.noise_floor_source or 'source not recorded'}")
    L = [f"# Calibration loop: {res.robot.name}", ""]
    if command:
        L += ["Made with:", "", "```", command, "```", ""]
    L += [f"{res.n_train} training rows, {res.n_test} held-out rows; {floor}.",
          "Every decision below was made by cross-validation on the training rows; the held-out rows were "
          "only measured.", "", "## Error per stage (mm)", ""]
    L += stage_table(res.stages) + orientation_table(res.stages)
    for split in ("test", "train"):
        if figs.get(split):
            L += ["", f"![errors, {split}: histogram, per axis before and after, cumulative with p95, against reach]"
                      f"(errors_{split}.png)"]
    sig = "–" if res.noise_sigma_mm is None else f"{res.noise_sigma_mm:.4f}"
    L += ["", "## Noise and outliers", "",
          f"Robust noise estimate of the final model: σ̂ = {sig} mm per axis (1.4826 × the median absolute deviation "
          f"of the residual components). Every fit uses the Huber loss; the last threshold was "
          f"{'–' if res.huber_mm is None else f'{res.huber_mm:.4f}'} mm on the Euclidean error of an observation.", ""]
    L += suspects_table(res.suspects, "training", "They stay in the data: the Huber loss limits their pull, and the "
                        "comparisons score them as a constant. Check them (a bumped reflector, a mislabelled marker, "
                        "a row out of sync).")
    if res.n_test:
        L += [""] + suspects_table(held, "held-out", "They are only measured, never fitted; they raise the held-out "
                                   "mean. Check them as the training ones.")
    L += ["", "## Geometric parameter set (chosen by cross-validation)", "",
          "| set | parameters (effective) | CV RMSE (mm) | t | accepted |", "|---|---|---|---|---|"]
    for g in res.geometric["sets"]:
        k = g.get("k_eff", g["n_params"])
        acc = "yes" if g.get("accepted") else ("no" if "accepted" in g else "– (scale not chosen)")
        t = g.get("t")
        L.append(f"| {g['name']} | {k:.1f} | {g['cv_rmse_mm']:.4f} | {'–' if t is None else f'{t:.1f}'} | {acc} |")
    L += ["", f"Chosen: **{res.geometric['chosen']}**. A larger set is taken only when it passes the rule below, "
              "which is what guards a small data set against over-fitting."]
    for a in res.geometric.get("again", []):
        L += ["", f"Judged again after {a['after']} was accepted: it left {a['sigma_now_mm']:.4f} mm of noise per "
                  f"axis, against the {a['sigma_chosen_mm']:.4f} mm the set was chosen under. "
              + "; ".join(f"{t['name']}: {t['k_eff']:.1f} parameters, CV {t['cv_rmse_mm']:.4f} mm, t = {t['t']:.1f}, "
                          f"{'accepted' if t['accepted'] else 'rejected'}" for t in a["tried"])
              + f". Kept: **{a['chosen']}**."]
    o = res.geometric.get("orientation") or {}
    if o.get("tried"):
        L += ["", f"Orientation weight: **{o['chosen']:.4g} mm/mrad** (0: orientations left out), the "
                  f"{o['rule']} among " + ", ".join(f"{t['weight_mm_per_mrad']:.4g} ({t['cv_mean_mm']:.4f} mm)"
                                                    for t in o["tried"]) + "."]
    h = getattr(res, "heldout", None)
    if h is not None and h.words():
        L += ["", "## The held-out rows", ""] + [f"- {w}" for w in h.words()]
    if res.prior_mm is not None:
        mm, _ = shown(res.prior_mm * 1e-3, "m")
        L += ["", f"The full set carries a Gaussian prior on every geometric error (not the instrument frame nor the "
                  f"marker points) of σ = {mm} mm for lengths and {mm} mrad for angles, its scale chosen among the "
                  "tried ones by the penalised CV error. The parameter count is the effective one, "
                  "tr((JᵀJ + W²)⁻¹ JᵀJ)."]
    L += [""] + _effect_section(res, findings, ev_figs)
    L += _revisions(res)
    left = res.leftover
    fig = leftover_figure(left.associations, out / "leftover.png") if left is not None else None
    L += leftover_section(left, "leftover.png" if fig is not None else None)
    L += parameter_section(res)
    L += flags_section(res.flags)
    L += candidates_section(res.candidates)
    L += ["", "Rule: " + rep["rule"] + ".", "",
          "Residual ELM: " + ("kept (it passed the rule)." if res.elm is not None else
                              "not kept: it did not improve the cross-validated error significantly, so what is "
                              "left is not something a black box learns from these rows."), "",
          "## Timings (s)", "", " | ".join(f"{k} {v:.1f}" for k, v in res.timings.items()), ""]
    (out / "report.md").write_text("\n".join(L))
    write_html(out, "report.md", title=f"Calibration loop: {res.robot.name}")
    return out
