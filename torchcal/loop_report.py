"""Files a person reads after ``torchcal loop``: report.json, report.md and the figures."""
from __future__ import annotations

from pathlib import Path

import torch

from .loop import SIGNATURE_AXIS, LoopResult
from .report import histogram_figure, write_json

__all__ = ["write_loop_report"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _histograms(res: LoopResult, path: Path, split: str) -> bool:
    """Error histograms before / geometric / full model in one figure, as calibration papers
    show them."""
    names = list(res.errors)
    pick = list(dict.fromkeys(n for n in (names[0], "geometric", names[-1]) if n in res.errors))
    label = {names[0]: "before (base registration only)", "geometric": "geometric calibration"}
    stages = [(label.get(n, "full model: " + n.lstrip("+")), res.errors[n][split]) for n in pick
              if res.errors[n].get(split) is not None and res.errors[n][split].numel()]
    if not stages:
        return False
    histogram_figure(stages, path, title=f"{res.robot.name}: error before / geometric / full model", split=split)
    return True


def _evidence_plot(name: str, ev: dict, path: Path) -> bool:
    """The residual of the model without the effect, projected on each joint, against the
    effect's physical signature (with the fitted effect overlaid)."""
    if not ev:
        return False
    plt = _plt()
    keys = list(ev)[:6]
    fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 3.2), dpi=110, squeeze=False)
    xl, xu = SIGNATURE_AXIS.get(name, ("signature", ""))
    for ax, k in zip(axes[0], keys):
        e = ev[k]
        x = e["x"]
        if "fitted" in e:
            ax.scatter(x, [v * 1e3 for v in e["residual"]], s=6, alpha=0.6, label="residual on joint")
            ax.scatter(x, [v * 1e3 for v in e["fitted"]], s=4, alpha=0.8, label="fitted effect")
            ax.set_ylabel("joint deflection [mrad]")
            ax.set_xlabel(f"{xl} [{xu}]")
        else:
            ax.scatter(x, e["residual"], s=6, alpha=0.6)
            ax.set_xlabel(e.get("xlabel", ""))
            ax.set_ylabel(e.get("ylabel", ""))
        ax.set_title(f"{k} (r = {e['r']:.2f})", fontsize=9)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"evidence for {name}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def _stats_cell(d: dict | None, k: str) -> str:
    return "–" if not d or k not in d else f"{d[k]:.4f}"


def write_loop_report(res: LoopResult, out_dir, command: str | None = None) -> Path:
    """Write ``report.json``, ``report.md``, ``errors_test.png`` / ``errors_train.png`` and one
    ``evidence_<effect>.png`` per accepted effect into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = res.report()
    if command:
        rep["command"] = command
    write_json(out / "report.json", rep)
    figs = {s: _histograms(res, out / f"errors_{s}.png", s) for s in ("train", "test")}
    ev_figs = {n: _evidence_plot(n, ev, out / f"evidence_{n}.png") for n, ev in res.evidence.items()}

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
        L.append(f"| {s['name']} | {s['n_params']} | {_stats_cell(tr, 'mean_mm')} | {_stats_cell(tr, 'std_mm')} | "
                 f"{_stats_cell(tr, 'max_mm')} | {_stats_cell(te, 'mean_mm')} | {_stats_cell(te, 'std_mm')} | "
                 f"{_stats_cell(te, 'max_mm')} |")
    for split in ("test", "train"):
        if figs.get(split):
            L += ["", f"![error histograms, {split}](errors_{split}.png)"]
    L += ["", "## Geometric parameter set (chosen by cross-validation)", "",
          "| set | parameters | CV RMSE (mm) | t | accepted |", "|---|---|---|---|---|"]
    for g in res.geometric["sets"]:
        t = g.get("t")
        L.append(f"| {g['name']} | {g['n_params']} | {g['cv_rmse_mm']:.4f} | {'–' if t is None else f'{t:.1f}'} | "
                 f"{'yes' if g['accepted'] else 'no'} |")
    L += ["", f"Chosen: **{res.geometric['chosen']}**. A larger set is taken only when it passes the rule below, "
              "which is what guards a small data set against over-fitting.", "",
          "## Effects", ""]
    if res.accepted:
        for a in res.accepted:
            tg = a.get("test_gain_mm")
            L += [f"### {a['name']} ({', '.join(a['joints']) or 'all links'})", "",
                  f"- cross-validated gain {a['cv_gain_mm']:+.4f} mm (RMSE); held-out gain "
                  f"{'–' if tg is None else f'{tg:+.4f} mm (mean)'}",
                  f"- evidence: {a['evidence']}"]
            if ev_figs.get(a["name"]):
                L += ["", f"![evidence for {a['name']}](evidence_{a['name']}.png)"]
            L += ["", "| parameter | value | unit |", "|---|---|---|"]
            L += [f"| {n} | {v:.6g} | {a.get('units', {}).get(n, '')} |" for n, v in a["params"].items()]
            L.append("")
    else:
        L += ["No effect passed the rule: the geometric model explains the data to within what the "
              "cross-validation can tell from noise.", ""]
    L += ["## Every candidate examined", "",
          "CV columns decided; the held-out gain (mean, mm) was measured afterwards and steered nothing.", "",
          "| round | candidate | parameters | CV RMSE (mm) | CV gain (mm) | t | held-out gain (mm) | accepted |",
          "|---|---|---|---|---|---|---|---|"]
    for c in res.candidates:
        if c.get("applicable") is False:
            L.append(f"| – | {c['name']} | – | – | – | – | – | not applicable: {c.get('reason', '')} |")
            continue
        tg = c.get("test_gain_mm")
        L.append(f"| {c.get('round', '–')} | {c['name']} | {c.get('n_params', '–')} | {c.get('cv_rmse_mm', float('nan')):.4f} | "
                 f"{c.get('cv_gain_mm', float('nan')):+.4f} | {c.get('t', float('nan')):.1f} | "
                 f"{'–' if tg is None else f'{tg:+.4f}'} | {'yes' if c.get('accepted') else 'no'} |")
    L += ["", "Rule: " + rep["rule"] + ".", "",
          "Residual ELM: " + ("kept (it passed the rule)." if res.elm is not None else
                              "not kept: it did not improve the cross-validated error significantly, so what is "
                              "left is not something a black box learns from these rows."), "",
          "## Timings (s)", "", " | ".join(f"{k} {v:.1f}" for k, v in res.timings.items()), ""]
    (out / "report.md").write_text("\n".join(L))
    return out
