"""The instrument frame along a path: a frame that wanders through the session in no shape anyone
wrote down.

A tracker's tripod creeps as the floor and the stand warm and settle, a camera rig sags, a robot's
base slides on its mount: the frame the measurements are taken in moves a little through the
session, a random walk more than a line or a cycle. :class:`~torchcal.effects.anydriver.ParameterDrivers`
has shapes for a frame that drifts, settles, cycles or steps; a path that wanders is none of them,
and a few such shapes leave most of it. This family follows it as a continuous piecewise-linear path
of the frame's six coordinates in time (or in the row order, without a time column)::

    Δframe(t) = Σ_k c_k r_k(t),    r_k(t) = clip((t − t_{k−1}) / (t_k − t_{k−1}), 0, 1)

with knots ``t_0 < … < t_K`` at quantiles of the training times (:data:`ROWS_PER_INTERVAL` rows per
interval, at most :data:`MAX_INTERVALS` intervals). Each mode ``c_k`` is the frame's rigid motion over
one interval (three shifts, three turns): the increments of the walk. A mode alone is a set-up that
moved gradually over one stretch of the session; all of them are the whole path, and the loop
selects the increments cross-validation supports. The frame at ``t_0`` is the geometric stage's.

Each row's markers move as the frame's six columns of the geometric Jacobian at the fitted geometry
say (:meth:`position_delta`): first order in the path, which a wander of 1 mrad at 1.5 m from the
frame's origin misses by about a micrometre. The drivers' frame terms carry each row's frame exactly
(a tracker carried metres away needs that); a path fitted exactly row by row crept for its whole
iteration budget along the geometry's near-alias of the frame's turns and the first joint's origin,
where the first-order columns converge in a few steps to the same held-out error. The end knots are
the first and last training values, so a time or row beyond them reads the path's end (:func:`ramps`
clamps; no extrapolation), and held-out rows from another session read the training rows' median
time (:mod:`torchcal.pipelines.loop.sessions`).

It is a general family (:attr:`~torchcal.effects.base.Effect.fallback`): the loop tries it beside
the drivers, only in a round where no catalogued effect passes, and it defers to them
(:attr:`~torchcal.effects.base.Effect.defers_to`): a path of a few intervals stands in for a drift,
a settling or a step the drivers name in one term, so where both pass it wins only by the rule
against theirs.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import TIME_COVARIATES, Effect, LinearBasis, Prepared
from torchcal.effects.drivers import ROW
from torchcal.kinematics.slots import BASE_NAMES
from torchcal.params import display_unit

__all__ = ["FramePath", "ramps", "ROWS_PER_INTERVAL", "MAX_INTERVALS"]

# Training rows per interval of the path: each increment is six coordinates, seen by this many rows'
# 3 coordinates each (15 per parameter); with fewer, an interval's motion is the noise's. More
# intervals than MAX_INTERVALS cost more than a wander seen by a few hundred rows shows
ROWS_PER_INTERVAL = 30
MAX_INTERVALS = 16


def ramps(x: Tensor, knots: list[float]) -> Tensor:
    """``(N, K)`` the path's columns at driver values ``x (N,)``: ``r_k`` rises from 0 at knot
    ``k − 1`` to 1 at knot ``k`` and stays (values outside the knots read the end knots)."""
    k = torch.tensor(knots, dtype=x.dtype, device=x.device)
    return ((x[:, None] - k[None, :-1]) / (k[1:] - k[:-1])[None]).clamp(0.0, 1.0)


def path_driver(covariates: dict) -> str | None:
    """The column a path follows: a time column, else the row order, else None."""
    for c in TIME_COVARIATES:
        if c in covariates:
            return c
    return ROW if ROW in covariates else None


class FramePath(Effect):
    """The instrument frame along a piecewise-linear path in time or the row order (module docstring).

    Args:
        driver: the column the path follows (:func:`path_driver`; set by :meth:`bind`).
        knots: ``K + 1`` increasing driver values (s, or rows); mode ``k`` is the motion between
            knots ``k − 1`` and ``k``.
        intervals: the modes kept (1-based interval numbers; default all ``K``).
    """

    name = "frame_path"
    description = "the instrument frame wandering along a path through the session"
    reads = ("measured",)
    selectable = True
    fallback = True
    defers_to = ("parameter_drivers",)  # a path stands in for any drift, settling or step they name

    def __init__(self, robot, joints=None, geometry=None, driver: str | None = None, knots: list | None = None,
                 intervals: list | None = None):
        self.driver = driver
        self.knots = [float(k) for k in knots or []]
        every = list(range(1, len(self.knots)))
        self.intervals = every if intervals is None else [int(s) for s in intervals]
        bad = [s for s in self.intervals if s not in every]
        if bad:
            raise ValueError(f"frame_path: interval(s) {bad} outside the path's 1..{len(every)}")
        super().__init__(robot, joints, geometry)

    def default_joints(self) -> list[str]:
        return []

    def config(self) -> dict:
        return {"driver": self.driver, "knots": list(self.knots), "intervals": list(self.intervals)}

    @property
    def covariates(self) -> list[str]:
        return [self.driver] if self.driver else []

    def _label(self, s: int) -> str:
        return f"base.frame~interval{s}"

    def param_info(self):
        units = dict(zip(self.robot.param_names, self.robot.param_units))
        return [(f"interval{s}.{b.split('.', 1)[1]}", units[b]) for s in self.intervals for b in BASE_NAMES]

    def modes(self):
        return [(self._label(s), list(range(6 * i, 6 * i + 6))) for i, s in enumerate(self.intervals)]

    def with_modes(self, labels: list[str]) -> "FramePath":
        keep = set(labels)
        return self._copy(intervals=[s for s in self.intervals if self._label(s) in keep])

    def setup_parameters(self) -> dict[str, str]:
        return {n: "frame" for n in self.param_names}

    def applicable(self, data) -> tuple[bool, str]:
        if not all(b in self.robot.param_names for b in BASE_NAMES):
            return False, "the model has no instrument frame to move"
        d = path_driver(data.covariates)
        if d is None:
            return False, "no time column and no row order"
        if len(data) < 2 * ROWS_PER_INTERVAL:
            return False, f"fewer than {2 * ROWS_PER_INTERVAL} training rows: no path of two intervals can be seen"
        return True, ""

    def bind(self, data, min_lever_m: float = 5e-3) -> "FramePath":
        """A copy following ``data``'s time (or row order), its knots at quantiles of the training
        values: about :data:`ROWS_PER_INTERVAL` rows per interval, at most :data:`MAX_INTERVALS`."""
        d = path_driver(data.covariates)
        x = data.covariates[d].double()
        x = x[torch.isfinite(x)]
        n = int(torch.unique(x).numel())
        K = max(2, min(MAX_INTERVALS, n // ROWS_PER_INTERVAL))
        knots = sorted(set(torch.quantile(x, torch.linspace(0, 1, K + 1, dtype=x.dtype)).tolist()))
        out = type(self)(self.robot, None, geometry=self.geometry, driver=d, knots=knots)
        out.covariate_range = {d: (float(x.min()), float(x.max()))}
        return out

    def prepare(self, q, covariates):
        if self.driver not in covariates:
            raise ValueError(f"frame_path needs the covariate {self.driver!r}")
        x = covariates[self.driver].to(q)
        R = ramps(x, self.knots)[:, [s - 1 for s in self.intervals]]
        k = torch.tensor([self.robot.param_names.index(b) for b in BASE_NAMES], device=q.device)
        J = self.robot.param_jacobian(q, self.geometry, check=False)[..., k]  # (N, M, 3, 6) instrument frame
        Rb, _ = self.robot.base_transform(self.geometry)
        return Prepared({"R": R, "x": x, "G": Rb.T @ J})  # G: robot base axes, as position_delta speaks

    def position_delta(self, theta, prep):
        """The markers' displacement (robot base frame) by the frame's offsets at each row, to first order."""
        R, G = prep.features["R"], prep.features["G"]
        d = torch.einsum("nk,pkc->pnc", R, theta.reshape(theta.shape[0], -1, 6))
        return torch.einsum("nmac,pnc->pnma", G, d)

    def linear_basis(self, prep: Prepared) -> LinearBasis:
        """Each coordinate's column of the geometric Jacobian times its interval's ramp."""
        R, G = prep.features["R"], prep.features["G"]
        dp = (G[..., None, :] * R[:, None, None, :, None]).flatten(-2)  # (N, M, 3, 6 K)
        return LinearBasis(None, dp, [list(c) for _, c in self.modes()])

    def _span(self, s: int) -> str:
        """Interval ``s`` in words: from where to where along the driver."""
        a, b = self.knots[s - 1], self.knots[s]
        if self.driver == ROW:
            return f"from row {int(a + 0.5)} to row {int(b + 0.5)}"
        return f"from {self.driver} = {a:.6g} s to {b:.6g} s ({(b - a) / 60:.3g} min)"

    def mode_words(self, label: str) -> str:
        return f"the instrument frame moves as one rigid body {self._span(int(label.rsplit('interval', 1)[1]))}"

    def signature(self, prep: Prepared, label: str, theta: Tensor) -> dict:
        """The markers' displacement per row from this interval's motion (its ramp) against the
        driver; ``G`` its direction."""
        i = self.intervals.index(int(label.rsplit("interval", 1)[1]))
        move = torch.einsum("nmac,c->nma", prep.features["G"], theta[6 * i: 6 * i + 6])
        disp = move * prep.features["R"][:, i, None, None]
        size = disp.norm(dim=-1).amax(-1)
        unit = "rows" if self.driver == ROW else "s"
        return {"x": prep.features["x"], "xlabel": f"{self.driver} [{unit}]", "fitted": size,
                "ylabel": "instrument frame offset [m]", "G": disp / size.clamp(min=1e-300)[:, None, None]}

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        th = self.theta if theta is None else theta
        (fm, um), (fr, ur) = display_unit("m"), display_unit("rad")
        out = []
        for i, s in enumerate(self.intervals):
            idx = range(6 * i, 6 * i + 6)
            if free is not None and not any(bool(free[j]) for j in idx):
                continue
            v = th[6 * i: 6 * i + 6].tolist()
            shift = ", ".join(f"{c * fm:.3g}" for c in v[:3])
            turn = ", ".join(f"{c * fr:.3g}" for c in v[3:])
            out.append(f"the instrument frame moves by ({shift}) {um} and turns by ({turn}) {ur} about x, y, z "
                       f"{self._span(s)}")
        return out
