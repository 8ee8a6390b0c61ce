"""What the final model still lacks, in numbers: how far its cross-validated error stays above the
noise a perfect model would leave, and which joint angles and covariates the residual still
follows.

**The noise a perfect model would leave** (:func:`~torchcal.measure.stats.noise_floor`): rows with
identical commands (a pose measured again) differ by the noise alone, and their spread, the *pure
error*, estimates it with no model at all. Without repeats it comes from ``--noise-floor-mm`` (the
instrument's specification) or, failing that, from a ``marker_std_mm`` column.

**Associations.** Each candidate signal (each joint's angle, its sine and cosine, each numeric
covariate, each direction of approach) is regressed on the residual, component by component, with
an intercept; its share of the residual's variance (R²) says how much of what is left it could
explain. Signals are ranked by R²; the strongest few are listed and plotted.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchcal.measure.data import Measurements

__all__ = ["Leftover", "Association", "associations", "leftover", "ABOVE_FLOOR"]

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
            return ["no noise floor is known (no repeated commands, no --noise-floor-mm, no marker_std_mm column): "
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


def leftover(data: Measurements, residual: Tensor, cv_mean_mm: float | None, floor_mm: float | None,
             floor_source: str | None) -> Leftover:
    """:class:`Leftover` of the final model: ``residual (N, M·3)`` its training residual (m),
    ``cv_mean_mm`` its cross-validated mean error, the noise floor and its source
    (:func:`~torchcal.measure.stats.noise_floor`)."""
    ratio = None if floor_mm is None or cv_mean_mm is None or floor_mm <= 0 else cv_mean_mm / floor_mm
    return Leftover(floor_mm, floor_source or "unknown", cv_mean_mm, ratio, associations(data, residual))
