"""Report files (JSON, Markdown) and plots for calibration results (statistics: :mod:`torchcal.measure.stats`)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchcal.report.figures import error_figure
from torchcal.report.html import write_html
from torchcal.report.plotting import pyplot
from torchcal.report.sections import stage_table
from torchcal.report.units import shown

__all__ = ["write_json", "histogram_figure", "error_figure", "error_details", "stage_problems",
           "FOREIGN_RATIO", "calibration_markdown", "write_calibration_report"]

# held-out rows this many times worse than the training rows do not come from the same robot
FOREIGN_RATIO = 20.0


def stage_problems(stages: list[dict]) -> list[str]:
    """Reasons not to trust a calibration, in words, from its stage statistics (first: nominal,
    last: final): the final model worse than the nominal one on its own training rows, or
    held-out rows that fit far worse than the training rows. Empty when none."""
    out = []
    nom, fin = stages[0], stages[-1]
    if fin["train"]["mean_mm"] > nom["train"]["mean_mm"]:
        out.append(f"the calibrated model ({fin['train']['mean_mm']:.4f} mm) is worse than the nominal one "
                   f"({nom['train']['mean_mm']:.4f} mm) on its own training rows: the fit failed (check the joint "
                   "order and units of the data, the declared markers, and the method's settings)")
    # medians: one glitch among the held-out rows is a gross error, not another robot
    test = fin.get("test") or {}
    tr, te = fin["train"].get("median_mm", fin["train"]["mean_mm"]), test.get("median_mm", test.get("mean_mm"))
    if te is not None and te > FOREIGN_RATIO * max(tr, 1e-9):
        out.append(f"the held-out rows do not belong to this robot's model: their median error ({te:.4g} mm) is "
                   f"{te / max(tr, 1e-9):.0f}× the training rows' ({tr:.4g} mm); are they from another robot, another "
                   "set-up (the instrument moved), or another marker?")
    return out


def _clean(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, Tensor):
        return _clean(o.tolist())
    return o


def write_json(path, obj) -> None:
    Path(path).write_text(json.dumps(_clean(obj), indent=2) + "\n")


def histogram_figure(stages: list[tuple[str, Tensor]], path, title: str = "Position error per observation",
                     split: str = "train") -> None:
    """One figure with overlaid error histograms (mm) for several stages, as calibration papers
    show them. ``stages``: (label, errors in m)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    data = [(lab, e.detach().double().flatten().cpu().numpy() * 1e3) for lab, e in stages if e.numel()]
    if not data:
        plt.close(fig)
        return

    hi = max(float(d.max()) for _, d in data)
    lo = min(float(np.percentile(d[d > 0], 1)) if (d > 0).any() else hi for _, d in data)
    log = hi > 30 * max(lo, 1e-12)  # stages a thousandfold apart: only a log axis shows both
    bins = np.geomspace(max(lo, 1e-6) * 0.8, hi * 1.05, 50) if log else np.linspace(0, hi * 1.02 + 1e-12, 40)
    for lab, d in data:
        ax.hist(d, bins=bins, alpha=0.55, label=f"{lab}: mean {d.mean():.3f} mm, max {d.max():.3f} mm")
    if log:
        ax.set_xscale("log")
    ax.set_xlabel("Euclidean position error [mm]" + (" (log scale)" if log else ""))
    ax.set_ylabel("observations")
    ax.set_title(f"{title} ({split})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def error_details(robot, params: Tensor, data, errors_xyz: Tensor | None = None, obs=None) -> dict:
    """Per observation of ``data``: the error vector ``xyz (n, 3)`` (model − measured, m,
    instrument frame; computed from ``params (K,)`` unless given; NaN in axes not measured), its
    norm ``e (n,)``, the marker's distance from the robot base ``dist (n,)`` (m), and where it
    came from: ``row (n,)`` (0-based row of ``data``), ``marker (n,)`` (index into
    ``robot.marker_names``), ``dims (n,)`` (how many components it measured).

    With ``obs`` (:class:`~torchcal.measure.observations.Observations`, ``errors_xyz`` its residual
    vectors) every observation counts in ``e`` and ``dist`` (a plane contact's error is its signed
    distance), and ``xyz`` holds the position observations only."""
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    base_free = robot.positions(data.q, params, check=False, base=False)[:, mk]
    robot_marker = torch.tensor(mk, device=base_free.device)
    if obs is not None:
        pos = obs.kind == 0
        xyz = errors_xyz[pos].masked_fill(~obs.mask[pos], float("nan"))
        return {"e": errors_xyz.norm(dim=-1), "xyz": xyz, "dist": base_free[obs.rows, obs.data_marker].norm(dim=-1),
                "row": obs.rows, "marker": robot_marker[obs.data_marker], "dims": obs.dims}
    seen = data.observed
    if errors_xyz is None:
        p = robot.positions(data.q, params, check=False)[:, mk][seen]
        errors_xyz = p - data.positions[seen]
    rows, cols = torch.nonzero(seen, as_tuple=True)
    return {"e": torch.nan_to_num(errors_xyz).norm(dim=-1), "xyz": errors_xyz, "dist": base_free[seen].norm(dim=-1),
            "row": rows, "marker": robot_marker[cols], "dims": torch.isfinite(errors_xyz).sum(-1)}


def calibration_markdown(res) -> str:
    """``report.md`` of a :class:`~torchcal.pipelines.calibrate.CalibrationResult`: the error per
    stage (mean, RMSE, p95, max), the figures, every fitted parameter with its standard error in
    its display unit, what could not be identified and the solver's account."""
    lines = [f"# Calibration of {res.robot.name}", "",
             f"Method `{res.method}`, loss `{res.loss}`, {res.n_train} training rows"
             + (f", {res.n_test} held-out rows." if res.n_test else ", no held-out data."), "",
             "## Position error per stage (mm)", ""]
    lines += stage_table(res.stages)
    for split, name in (("test", "errors_test.png"), ("train", "errors.png")):
        if any(e.get(f"{split}_details") is not None for e in res.errors.values()):
            lines += ["", f"![errors, {split}: histogram, per axis before and after, cumulative with p95, against "
                          f"reach]({name})"]
    if getattr(res, "prior_reason", ""):
        lines += ["", "## Prior", "", res.prior_reason + "."]
    status = res.statuses()  # one list per parameter: identified, tied to others, or fixed
    lines += ["", "## Identified parameters", "", "| parameter | value | std. error | unit |", "|---|---|---|---|"]
    for n, v, u in zip(res.params.names, res.params.values.tolist(), res.params.units):
        if status.get(n, ("",))[0] == "identified":
            (sv, us), (se, _) = shown(v, u, 6), shown(res.std_errors.get(n, float("nan")), u, 3)
            lines.append(f"| {n} | {sv} | {se} | {us} |")
    for kind, title in (("tied", "Tied to others: these measurements cannot tell them apart"),
                        ("fixed", "Fixed at nominal: not seen, or pinned down worse than a plausible error")):
        rows = sorted((n, why) for n, (k, why) in status.items() if k == kind)
        if rows:
            lines += ["", f"## {title}", ""]
            for n, why in rows:
                val = ""
                if n in res.params.free_names:  # held by a prior at its share of the tie
                    sv, us = shown(float(res.params[n]), res.params.units[res.params.index(n)], 4)
                    val = f" = {sv} {us}"
                lines.append(f"- `{n}`{val}: {why}")
    if getattr(res, "suspects", None):
        lines += ["", "## Gross errors left out of the fit (kept in the statistics)", "",
                  "| row | marker | error at the registered nominal model (mm) |", "|---|---|---|"]
        lines += [f"| {s['row']} | {s['marker']} | {s['error_mm']:.4g} |" for s in res.suspects]
    if res.problems():
        lines += ["", "**Not fit to save or deploy:** " + "; ".join(res.problems())]
    s = res.solver
    lines += ["", f"Solver: {s.method}, {s.n_iter} iterations, {s.n_evals} evaluations, "
                  f"{s.wall_time_s:.3f} s; {s.message}", ""]
    return "\n".join(lines)


def write_calibration_report(res, out_dir) -> None:
    """``report.md``, the error figures (``errors.png`` for the training rows, ``errors_test.png``
    for the held-out ones, where the result kept the details) and ``report.html`` into
    ``out_dir``."""
    out = Path(out_dir)
    for split in ("train", "test"):
        st = [(name, e[f"{split}_details"]) for name, e in res.errors.items()
              if e.get(split) is not None and e[split].numel() and e.get(f"{split}_details") is not None]
        if st:
            error_figure(st, out / ("errors.png" if split == "train" else "errors_test.png"),
                         title=f"{res.robot.name}: position error", split=split)
    (out / "report.md").write_text(calibration_markdown(res))
    write_html(out, "report.md", title=f"Calibration of {res.robot.name}")
