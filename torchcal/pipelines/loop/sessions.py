"""Held-out rows from another session: what describes the session and what the robot, and why a
model that fits its own session may miss another one.

A session is one set-up of robot and instrument, measured in one sitting. An effect driven by
time or by the order of the rows (a drift, a warm-up) describes that sitting, not the robot: on
another session's rows it is held at a stated value (the training rows' median), never
extrapolated. The instrument is often set up anew between sessions: its frame is then registered
anew on the held-out rows when asked (``reregister``), and both figures are reported.

When the held-out rows fit badly, :func:`check_heldout_rows` says which of the two usual causes it
is, from the held-out rows themselves:

* **the instrument moved**: registering its frame anew on the held-out rows (6 values, the robot's
  model untouched) takes most of the error away;
* **an effect extrapolates**: the held-out error falls when that effect is left out, and the rows
  drive it (a joint, a temperature) outside the range it was fitted on.

Rows that neither explains do not belong to this robot's model, and the refusal stays.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.effects.base import TIME_COVARIATES
from torchcal.measure.data import Measurements
from torchcal.measure.trust import FOREIGN_RATIO
from torchcal.pipelines.loop.covariates import extrapolation
from torchcal.pipelines.crossval.evaluate import fit_params
from torchcal.pipelines.crossval.models import Context
from torchcal.pipelines.loop.parts import assemble, split_params
from torchcal.pipelines.loop.stages import stage_stats

__all__ = ["is_session_driver", "other_session", "hold_session_terms", "HeldOutCheck", "check_heldout_rows",
           "EXPLAINS"]

ROW_ORDER = ("row", "row_order", "row_index")
EXPLAINS = 0.5  # a cause explains the held-out error when it takes at least half of it away
_TOL = 0.01     # a driver leaves its training range by more than 1 % of that range


def is_session_driver(column: str) -> bool:
    """A covariate that describes the sitting, not the robot: a time or the row order."""
    return column in TIME_COVARIATES or column.lower() in ROW_ORDER


def other_session(train: Measurements, test: Measurements) -> str | None:
    """Why the held-out rows come from another session (in words), or None when they are rows of
    the training session. A time column both have decides (ranges that do not overlap: another
    session; interleaved times: the same one, even from two files); without one, rows from another
    file are another session."""
    for c in TIME_COVARIATES:
        if c in train.covariates and c in test.covariates:
            a, b = train.covariates[c], test.covariates[c]
            if float(b.min()) > float(a.max()) or float(b.max()) < float(a.min()):
                return f"their {c} ({float(b.min()):.6g}–{float(b.max()):.6g}) does not overlap the training rows' " \
                       f"({float(a.min()):.6g}–{float(a.max()):.6g})"
            return None
    if train.source and test.source and Path(train.source).resolve() != Path(test.source).resolve():
        return f"they come from another file ({test.source}) than the training rows ({train.source})"
    return None


def hold_session_terms(train: Measurements, test: Measurements) -> tuple[Measurements, dict[str, float]]:
    """The held-out rows with every session driver (time, row order) held at the training rows'
    median, and the values held."""
    held = {c: float(train.covariates[c].double().median()) for c in test.covariates
            if is_session_driver(c) and c in train.covariates}
    if not held:
        return test, {}
    cov = {k: (torch.full_like(v, held[k]) if k in held else v) for k, v in test.covariates.items()}
    return test._with(test.q, test.positions, list(test.marker_names), test.quaternions, cov, test.planes,
                      dict(test.distances)), held


@dataclass
class HeldOutCheck:
    """Why held-out rows fit as they do (errors: mean / median Euclidean position error, mm).

    Attributes:
        session: why the rows come from another session (None: the training session).
        held_at: session drivers held on the held-out rows, and their value.
        final_mm, final_median_mm: the final model; ``geometric_mm``: the geometry alone.
        without: held-out mean without each accepted effect (and without the residual ELM).
        out_of_range: the drivers the held-out rows take outside their training range.
        reregistered_mm, reregistered_median_mm: the final model with the instrument frame
            registered anew on the held-out rows (None: not tried); ``frame_shift_mm``,
            ``frame_turn_mrad``: how far that frame moved.
        reregister: whether the user asked for it (then it is the figure reported beside the
            first, and a move it explains is no reason to refuse the model).
        train_median_mm: the final model's median on its training rows.
    """
    session: str | None
    held_at: dict[str, float]
    final_mm: float
    final_median_mm: float
    geometric_mm: float
    train_median_mm: float
    without: dict[str, float] = field(default_factory=dict)
    out_of_range: list[dict] = field(default_factory=list)
    reregistered_mm: float | None = None
    reregistered_median_mm: float | None = None
    frame_shift_mm: float | None = None
    frame_turn_mrad: float | None = None
    reregister: bool = False

    @property
    def foreign(self) -> bool:
        """The final model's held-out median is beyond the refusal's ratio to its training median."""
        return self.final_median_mm > FOREIGN_RATIO * max(self.train_median_mm, 1e-9)

    @property
    def instrument_moved(self) -> bool:
        return self.reregistered_mm is not None and self.reregistered_mm < EXPLAINS * self.final_mm

    @property
    def explained_by_reregistration(self) -> bool:
        """Registering the frame anew brings the held-out rows within the refusal's ratio."""
        return self.reregistered_median_mm is not None and \
            self.reregistered_median_mm <= FOREIGN_RATIO * max(self.train_median_mm, 1e-9)

    def extrapolating(self) -> list[str]:
        """Effects whose removal takes at least half of the held-out error away."""
        return [k for k, v in self.without.items() if v < EXPLAINS * self.final_mm]

    def words(self) -> list[str]:
        out = []
        if self.session:
            out.append(f"the held-out rows come from another session: {self.session}")
        if self.held_at:
            out.append("effects driven by time or row order describe a session, not the robot: on the held-out rows "
                       "they are held at the training rows' median (" +
                       ", ".join(f"{k} = {v:.6g}" for k, v in self.held_at.items()) + ")")
        if self.reregistered_mm is not None:
            out.append(f"held-out mean error {self.final_mm:.4f} mm as measured; {self.reregistered_mm:.4f} mm with "
                       "the instrument frame registered anew on the held-out rows (moved "
                       f"{self.frame_shift_mm:.3f} mm, turned {self.frame_turn_mrad:.3f} mrad; 6 values fitted on "
                       "those rows)")
        causes = self.causes()
        if causes:
            out.append("why the held-out rows fit worse: " + "; ".join(causes))
        elif self.foreign:
            out.append("neither a moved instrument nor an effect outside its fitted range explains the held-out rows")
        return out

    def causes(self) -> list[str]:
        out = []
        if self.instrument_moved:
            out.append(f"the instrument moved between the sessions (registered anew, the error falls from "
                       f"{self.final_mm:.4f} to {self.reregistered_mm:.4f} mm)")
        for name in self.extrapolating():
            drv = [r for r in self.out_of_range if r["effect"] == name]
            where = "; ".join(f"{r['covariate']} spans {r['test_range'][0]:.4g}–{r['test_range'][1]:.4g} held out "
                              f"against {r['train_range'][0]:.4g}–{r['train_range'][1]:.4g} in training" for r in drv)
            out.append(f"{name} does not carry over: without it the held-out error is {self.without[name]:.4f} mm "
                       f"(with it {self.final_mm:.4f} mm)" + (f", extrapolating outside its fitted range ({where})"
                                                              if where else ""))
        return out

    def to_json(self) -> dict:
        return {"session": self.session, "held_at": self.held_at, "final_mean_mm": self.final_mm,
                "final_median_mm": self.final_median_mm, "geometric_mean_mm": self.geometric_mm,
                "without_mm": self.without, "out_of_range": self.out_of_range,
                "reregistered_mean_mm": self.reregistered_mm, "reregistered_median_mm": self.reregistered_median_mm,
                "frame_shift_mm": self.frame_shift_mm, "frame_turn_mrad": self.frame_turn_mrad,
                "reregister": self.reregister, "causes": self.causes()}


def check_heldout_rows(ctx: Context, params, effects: list, elm, test: Measurements, geometric_params, *,
                       session: str | None, held_at: dict, reregister: bool) -> HeldOutCheck:
    """The held-out rows measured against the final model (``params``, ``effects``, ``elm``), the
    geometry alone, the model without each effect, and (when asked, or when the rows fit too badly
    to keep) with the instrument frame registered anew on them."""
    robot, setup, w = ctx.robot, ctx.setup, ctx.rot_weight
    stats = lambda p, e, m=None, d=test: stage_stats(robot, p, e, d, m, setup, w)[0]  # noqa: E731
    final, train = stats(params, effects, elm), stats(params, effects, elm, ctx.data)
    out = HeldOutCheck(session, held_at, final.mean, final.median, stats(geometric_params, []).mean, train.median,
                       reregister=reregister)
    geo, parts = split_params(params, robot, effects)
    for i, e in enumerate(effects):
        rest = [x for j, x in enumerate(effects) if j != i]
        out.without[e.name] = stats(assemble(geo, [p for j, p in enumerate(parts) if j != i]), rest).mean
        out.out_of_range += extrapolation(e, test) + _joints_outside(e, ctx.data, test)
    if elm is not None:
        out.without["residual ELM"] = stats(params, effects).mean
    if reregister or out.foreign:
        p = _reregistered(ctx, params, effects, test)
        rr = stats(p, effects, elm)
        out.reregistered_mm, out.reregistered_median_mm = rr.mean, rr.median
        out.frame_shift_mm, out.frame_turn_mrad = _frame_change(params, p)
    return out


def _reregistered(ctx: Context, params, effects: list, test: Measurements):
    """``params`` with only the instrument frame (``base.*``) fitted anew on ``test``."""
    p = params.clone()
    p.free[:] = False
    p.unfix("base.*")
    at = Context(ctx.robot, test, [], ctx.c, ctx.sigma, ctx.setup, ctx.rot_weight, ctx.soft, ctx.plausible)
    return fit_params(at, p, effects, test, None, reduce=False)


def _frame_change(before, after) -> tuple[float, float]:
    """How far the instrument frame moved (mm) and turned (mrad) between two fits."""
    idx = [before.names.index(f"base.{a}") for a in ("x", "y", "z", "rx", "ry", "rz")]
    d = (after.values[idx] - before.values[idx]).double()
    return 1e3 * float(d[:3].norm()), 1e3 * float(d[3:].norm())


def _joints_outside(eff, train: Measurements, test: Measurements) -> list[dict]:
    """The joints an effect acts on whose held-out values leave their training range."""
    out = []
    for j in getattr(eff, "joints", []):
        k = list(train.joint_names).index(j)
        lo, hi = float(train.q[:, k].min()), float(train.q[:, k].max())
        v = test.q[:, k]
        tol = _TOL * (hi - lo)
        outside = float(((v < lo - tol) | (v > hi + tol)).double().mean())
        if outside > 0:
            out.append({"effect": eff.name, "covariate": j, "train_range": [lo, hi],
                        "test_range": [float(v.min()), float(v.max())], "fraction_outside": outside})
    return out
