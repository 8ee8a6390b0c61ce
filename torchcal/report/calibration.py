"""Report files (JSON, Markdown) and plots for calibration results (statistics: :mod:`torchcal.measure.stats`)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchcal.report.plotting import pyplot

__all__ = ["write_json", "histogram_figure", "error_figure", "error_details", "stage_problems",
           "FOREIGN_RATIO"]

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
    norm ``e (n,)`` and the marker's distance from the robot base ``dist (n,)`` (m).

    With ``obs`` (:class:`~torchcal.measure.observations.Observations`, ``errors_xyz`` its residual
    vectors) every observation counts in ``e`` and ``dist`` (a plane contact's error is its signed
    distance), and ``xyz`` holds the position observations only."""
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    base_free = robot.positions(data.q, params, check=False, base=False)[:, mk]
    if obs is not None:
        pos = obs.kind == 0
        xyz = errors_xyz[pos].masked_fill(~obs.mask[pos], float("nan"))
        return {"e": errors_xyz.norm(dim=-1), "xyz": xyz, "dist": base_free[obs.rows, obs.data_marker].norm(dim=-1)}
    seen = data.observed
    if errors_xyz is None:
        p = robot.positions(data.q, params, check=False)[:, mk][seen]
        errors_xyz = p - data.positions[seen]
    return {"e": torch.nan_to_num(errors_xyz).norm(dim=-1), "xyz": errors_xyz, "dist": base_free[seen].norm(dim=-1)}


def error_figure(stages: list[tuple[str, dict]], path, title: str = "Position error", split: str = "train",
                 noise_floor_mm: float | None = None) -> None:
    """Four panels a person checks a calibration with, for several stages (``(label, details)``,
    details from :func:`error_details`): the error histogram; the per-axis errors of the last
    stage; the cumulative distribution with each stage's 95th percentile and the noise floor
    marked; the error against the marker's distance from the robot base."""
    plt = pyplot()

    data = [(lab, {k: v.detach().double().cpu().numpy() * (1e3 if k in ("e", "xyz") else 1.0)
                   for k, v in d.items()}) for lab, d in stages if d["e"].numel()]
    if not data:
        return
    fig, ax = plt.subplots(2, 2, figsize=(11, 7.5), dpi=110)
    e_all = np.concatenate([d["e"] for _, d in data])
    hi = float(e_all.max())
    lo = float(np.percentile(e_all[e_all > 0], 1)) if (e_all > 0).any() else hi
    log = hi > 30 * max(lo, 1e-12)  # stages a thousandfold apart: only a log axis shows both
    bins = np.geomspace(max(lo, 1e-6) * 0.8, hi * 1.05, 50) if log else np.linspace(0, hi * 1.02 + 1e-12, 40)
    for lab, d in data:
        ax[0, 0].hist(d["e"], bins=bins, alpha=0.55, label=f"{lab}: mean {d['e'].mean():.3f}, max {d['e'].max():.3f} mm")
        xs = np.sort(d["e"])
        ax[1, 0].plot(xs, np.arange(1, len(xs) + 1) / len(xs), label=lab)
        p95 = float(np.percentile(d["e"], 95))
        ax[1, 0].axvline(p95, ls=":", lw=1, color=ax[1, 0].lines[-1].get_color())
        ax[1, 0].annotate(f"p95 {p95:.3f}", (p95, 0.95), fontsize=7, rotation=90, va="top", ha="right")
        ax[1, 1].scatter(d["dist"], d["e"], s=5, alpha=0.5, label=lab)
    if log:
        for a in (ax[0, 0], ax[1, 0], ax[1, 1]):
            a.set_xscale("log") if a is not ax[1, 1] else a.set_yscale("log")
    if noise_floor_mm is not None:
        ax[1, 0].axvline(noise_floor_mm, color="k", lw=1.2, label=f"noise floor {noise_floor_mm:.3f} mm")
    lab, last = data[-1]
    ax[0, 1].boxplot([x[np.isfinite(x)] for x in last["xyz"].T], showfliers=True)
    ax[0, 1].set_xticks([1, 2, 3], ["x", "y", "z"])
    ax[0, 1].axhline(0, color="k", lw=0.6)
    ax[0, 0].set(xlabel="Euclidean error of each observation [mm]", ylabel="observations", title="error histogram")
    ax[0, 1].set(ylabel="error per axis, model − measured [mm]", title=f"per axis: {lab} (instrument frame)")
    ax[1, 0].set(xlabel="Euclidean position error [mm]", ylabel="fraction of observations",
                 title="cumulative distribution, 95th percentile dotted")
    ax[1, 1].set(xlabel="marker distance from the robot base [m]", ylabel="Euclidean position error [mm]",
                 title="error against reach")
    for a in (ax[0, 0], ax[1, 0], ax[1, 1]):
        a.legend(fontsize=7)
    fig.suptitle(f"{title} ({split})")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
