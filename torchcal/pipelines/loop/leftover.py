"""What the final model still lacks, in numbers: how far its cross-validated error stays above the
noise a perfect model would leave, and which joint angles and covariates the residual still
follows.

**The noise a perfect model would leave.** Rows with identical commands (a pose measured again)
differ by the instrument's noise alone: their spread around their own mean, the *pure error*,
estimates it with no model at all (``σ² = Σ |r − r̄_group|² / (n_values − n_groups·dims)``).
Without repeats it comes from ``--noise-mm`` (the instrument's specification) or, failing that,
the median of a ``marker_std_mm`` column (the spread of the instrument over a static capture).

**Associations.** Each candidate signal (each joint's angle, its sine and cosine, each numeric
covariate, each direction of approach) is regressed on the residual, component by component, with
an intercept; its share of the residual's variance (R²) says how much of what is left it could
explain. Signals are ranked by R²; the strongest few are listed and plotted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchcal.measure.data import Measurements

__all__ = ["Leftover", "Association", "pure_error", "associations", "leftover", "ABOVE_FLOOR"]

ABOVE_FLOOR = 1.10  # a final CV error this far above the floor is reported as something still missing


@dataclass
class Association:
    """One signal the residual still follows: ``r2`` its share of the residual variance, ``x``
    the signal per row and ``y`` the residual component it explains best (m), for a plot."""

    signal: str
    kind: str  # "joint angle", "covariate", "direction"
    r2: float
    x: list = field(default_factory=list)
    y: list = field(default_factory=list)
    axis: str = ""

    def words(self) -> str:
        return f"{self.signal} ({self.kind}): R² = {self.r2:.3f} of the residual variance"


@dataclass
class Leftover:
    """The final model against the noise floor, and the residual's strongest associations."""

    floor_mm: float | None        # mean Euclidean error a perfect model would leave (mm)
    floor_source: str             # where that figure comes from, in words
    cv_mean_mm: float | None      # the final model's cross-validated mean error (mm)
    ratio: float | None
    associations: list[Association] = field(default_factory=list)

    @property
    def missing(self) -> bool:
        return self.ratio is not None and self.ratio > ABOVE_FLOOR

    def words(self) -> list[str]:
        if self.floor_mm is None:
            return ["no noise floor is known (no repeated commands, no --noise-mm, no marker_std_mm column): "
                    "what is left cannot be told from noise"]
        out = [f"noise floor {self.floor_mm:.4f} mm ({self.floor_source}); the final model's cross-validated mean "
               f"error is {self.cv_mean_mm:.4f} mm, {self.ratio:.2f}× the floor"]
        if self.missing:
            out.append("the model still lacks something: its error stays above what noise alone would leave")
        return out

    def report(self) -> dict:
        return {"noise_floor_mm": self.floor_mm, "noise_floor_source": self.floor_source,
                "cv_mean_mm": self.cv_mean_mm, "ratio_to_floor": self.ratio, "missing": self.missing,
                "associations": [{"signal": a.signal, "kind": a.kind, "r2": a.r2, "axis": a.axis}
                                 for a in self.associations]}


def pure_error(data: Measurements, groups: Tensor) -> tuple[float | None, int]:
    """Per-axis noise σ (m) from rows with identical commands (``groups``: a group id per row),
    and the number of repeated groups; None when no command was measured twice."""
    pos = data.positions  # (N, M, 3)
    ss, dof, reps = 0.0, 0, 0
    for g in torch.unique(groups):
        rows = torch.nonzero(groups == g).flatten()
        if rows.numel() < 2:
            continue
        x = pos[rows]
        ok = torch.isfinite(x)
        n = ok.sum(0)
        mean = torch.where(ok, x, torch.zeros_like(x)).sum(0) / n.clamp(min=1)
        d = torch.where(ok, x - mean, torch.zeros_like(x))
        ss += float((d * d).sum())
        dof += int((n - 1).clamp(min=0).sum())
        reps += 1
    if dof == 0:
        return None, 0
    return math.sqrt(ss / dof), reps


def _signals(data: Measurements) -> list[tuple[str, str, Tensor]]:
    out = []
    for j, n in enumerate(data.joint_names):
        q = data.q[:, j]
        out.append((n, "joint angle", q))
        out += [(f"sin {n}", "joint angle", torch.sin(q)), (f"cos {n}", "joint angle", torch.cos(q))]
    for k, v in data.covariates.items():
        if v.numel() and bool(torch.isfinite(v).all()) and float(v.max() - v.min()) > 0:
            out.append((k, "direction" if k.startswith("dir.") else "covariate", v))
    return out


def associations(data: Measurements, residual: Tensor, top: int = 5) -> list[Association]:
    """The ``top`` signals with the largest share (R²) of the residual ``(N, M·3)`` (m, NaN where
    not measured) they explain, each fitted with an intercept to each component."""
    R = residual
    ok = torch.isfinite(R)
    if not bool(ok.any()):
        return []
    Rz = torch.where(ok, R, torch.zeros_like(R))
    cnt = ok.sum(0).clamp(min=1)
    Rc = torch.where(ok, R - Rz.sum(0) / cnt, torch.zeros_like(R))
    total = float((Rc * Rc).sum())
    if total <= 0:
        return []
    axes = [f"{m}.{a}" for m in data.marker_names for a in "xyz"]
    out = []
    for name, kind, x in _signals(data):
        xc = x[:, None].expand_as(R)
        xm = torch.where(ok, xc, torch.zeros_like(xc)).sum(0) / cnt
        xd = torch.where(ok, xc - xm, torch.zeros_like(xc))
        sxx = (xd * xd).sum(0).clamp(min=1e-300)
        explained = (xd * Rc).sum(0) ** 2 / sxx  # per component
        best = int(explained.argmax())
        out.append(Association(name, kind, float(explained.sum()) / total, x.tolist(),
                               torch.where(ok[:, best], Rc[:, best], torch.full_like(Rc[:, best], float("nan"))).tolist(),
                               axes[best]))
    out.sort(key=lambda a: -a.r2)
    return out[:top]


def leftover(data: Measurements, residual: Tensor, groups: Tensor, cv_mean_mm: float | None,
             noise_mm: float | None = None) -> Leftover:
    """:class:`Leftover` of the final model: ``residual (N, M·3)`` its training residual (m),
    ``groups`` the duplicate-command group of each row, ``cv_mean_mm`` its cross-validated mean
    error, ``noise_mm`` the instrument's figure when given."""
    sigma, reps = pure_error(data, groups)
    if sigma is not None:
        floor, src = _mean_norm_mm(sigma), (f"pure error of {reps} repeated command(s): σ = {sigma * 1e3:.4f} mm per "
                                            "axis, the mean error a perfect model would leave")
    elif noise_mm is not None:
        floor, src = float(noise_mm), "given (--noise-mm, the instrument's specification)"
    elif "marker_std_mm" in data.covariates:
        floor = float(data.covariates["marker_std_mm"].median())
        src = "the median of the marker_std_mm column (the instrument's spread over each static capture)"
    else:
        floor, src = None, "unknown"
    ratio = None if floor is None or cv_mean_mm is None or floor <= 0 else cv_mean_mm / floor
    return Leftover(floor, src, cv_mean_mm, ratio, associations(data, residual))


def _mean_norm_mm(sigma: float) -> float:
    """Mean Euclidean norm (mm) of 3-D Gaussian noise with ``sigma`` (m) per axis: σ·2√(2/π)."""
    return sigma * 2 * math.sqrt(2 / math.pi) * 1e3
