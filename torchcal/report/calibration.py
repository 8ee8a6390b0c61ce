"""Report files (JSON, Markdown) and plots for calibration results (statistics: :mod:`torchcal.measure.stats`)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from torch import Tensor

from torchcal.report.figures import error_figure
from torchcal.report.html import write_html
from torchcal.report.plotting import save, subplots
from torchcal.report.sections import stage_table
from torchcal.report.units import shown

__all__ = ["write_json", "histogram_figure", "error_figure", "calibration_json", "calibration_markdown",
           "write_calibration_report", "save_calibration"]


def _clean(o):
    if hasattr(o, "to_json"):  # a typed record becomes JSON here, at the edge
        return _clean(o.to_json())
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
    data = [(lab, e.detach().double().flatten().cpu().numpy() * 1e3) for lab, e in stages if e.numel()]
    if not data:
        return
    fig, ax = subplots(figsize=(7, 4), dpi=120)

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
    save(fig, path)


def calibration_json(res) -> dict:
    """``report.json`` of a :class:`~torchcal.pipelines.calibration_result.CalibrationResult`
    (its shape shared with ``torchcal loop``)."""
    ident = res.params.free_names
    s = res.solver
    return {
        "robot": res.robot.name, "method": res.method, "loss": res.loss, "n_train": res.n_train, "n_test": res.n_test,
        "stages": [st.to_json() for st in res.stages],
        "unidentifiable": sorted(res.unidentifiable), "unidentifiable_reasons": res.unidentifiable,
        "parameters": {n: {"value": v, "std_error": res.std_errors.get(n), "unit": u}
                       for n, v, u in zip(res.params.names, res.params.values.tolist(), res.params.units) if n in ident},
        "solver": {"method": s.method, "fun": s.fun, "n_iter": s.n_iter, "n_evals": s.n_evals,
                   "wall_time_s": s.wall_time_s, "converged": s.converged, "message": s.message},
        "wall_time_s": res.wall_time_s, "problems": res.problems(),
        "suspects": [s.to_json() for s in res.suspects],
        "prior_mm": res.prior_mm, "prior_reason": res.prior_reason, "prior_tried": res.prior_tried,
        "status": {n: st for n, (st, _) in res.statuses().items()},
    }


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
        if any(getattr(e, f"{split}_details") is not None for e in res.errors.values()):
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
        lines += [f"| {s.row} | {s.marker} | {s.error_mm:.4g} |" for s in res.suspects]
    if res.problems():
        lines += ["", "**Not fit to save or deploy:** " + "; ".join(res.problems())]
    s = res.solver
    lines += ["", f"Solver: {s.method}, {s.n_iter} iterations, {s.n_evals} evaluations, "
                  f"{s.wall_time_s:.3f} s; {s.message}", ""]
    return "\n".join(lines)


def write_calibration_report(res, out_dir) -> None:
    """``report.json``, ``report.md``, the error figures (``errors.png`` for the training rows, ``errors_test.png``
    for the held-out ones, where the result kept the details) and ``report.html`` into
    ``out_dir``."""
    out = Path(out_dir)
    write_json(out / "report.json", calibration_json(res))
    for split in ("train", "test"):
        st = [(name, e.plotted(split)) for name, e in res.errors.items() if e.plotted(split) is not None]
        if st:
            error_figure(st, out / ("errors.png" if split == "train" else "errors_test.png"),
                         title=f"{res.robot.name}: position error", split=split)
    (out / "report.md").write_text(calibration_markdown(res))
    write_html(out, "report.md", title=f"Calibration of {res.robot.name}")


def save_calibration(res, out_dir, *, force: bool = False, with_instrument: bool = False, with_markers: bool = False,
                     extra=None) -> Path:
    """The calibration files (:meth:`~torchcal.pipelines.calibration_result.CalibrationResult.save`)
    and its report (:func:`write_calibration_report`) in ``out_dir``, written together under a
    temporary name; ``extra(tmp_dir)`` may add files before the rename."""

    def reports(d: Path) -> None:
        write_calibration_report(res, d)
        if extra is not None:
            extra(d)

    return res.save(out_dir, force=force, with_instrument=with_instrument, with_markers=with_markers, extra=reports)
