"""Thermal growth: links that lengthen with temperature (or, lacking a thermometer, with time).

A link that warms by ``ΔT`` grows by ``α ΔT`` of its length: the joint origin vector it carries
(parent link frame -> joint frame, m) scales by ``1 + α ΔT``, and everything beyond moves with
it. The modes are one coefficient per link (each joint origin vector and each marker's offset on
its link) and ``uniform``: every link growing alike, which scales robot-base positions by
``1 + α ΔT``. The loop selects the modes the data supports. Growth is applied to first order
(``α ΔT`` ~ 1e-4) at the geometry the features are computed at.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import TIME_COVARIATES, Effect, Prepared
from torchcal.effects.gravity import kinematic_frames
from torchcal.effects.terms import driver_columns
from torchcal.params import display_unit

__all__ = ["ThermalDrift", "thermal_covariate"]

_NAMES = ("temperature", "temp", "t_robot") + TIME_COVARIATES


def thermal_covariate(covariates: dict) -> str | None:
    """The covariate a thermal model should use: a temperature column if there is one, else a
    time column, else None."""
    for k in covariates:
        if "temp" in k.lower():
            return k
    for n in _NAMES:
        if n in covariates:
            return n
    return None


def _unit_of(column: str) -> str:
    """The unit a driver column is read in: K for a temperature, s for a time, else its own."""
    if column in TIME_COVARIATES:
        return "s"
    return "K" if "temp" in column.lower() else "unit"


class ThermalDrift(Effect):
    """Links growing with a covariate (a temperature, a time, any numeric column), per link or all
    alike, each mode driven by one column.

    Args:
        covariate: the one column read (default: every driver column of the data, found by
            :meth:`bind`: :func:`~torchcal.effects.terms.driver_columns`).
        t0: reference value of ``covariate`` (default: the training mean).
        modes: ``"uniform"``, ``"<joint>.growth"`` (the origin vector of that joint, in its
            parent link), ``"<marker>.growth"`` (the marker's offset on its link), each followed by
            ``@<column>`` when several columns drive modes; default all.
        drivers: the columns modes may read (default ``[covariate]``); ``t0s``: their references.
    """

    name = "thermal_drift"
    description = "link lengths growing with a temperature, a time or another covariate"
    reads = ("measured",)
    selectable = True

    def __init__(self, robot, joints=None, geometry=None, covariate: str | None = None, t0: float | None = None,
                 modes: list[str] | None = None, drivers: list[str] | None = None, t0s: dict | None = None):
        self.covariate, self.t0 = covariate, t0
        self.drivers = list(drivers) if drivers is not None else ([covariate] if covariate else [])
        self.t0s = dict(t0s or ({covariate: t0} if covariate and t0 is not None else {}))
        cat = self._catalog(robot, self.drivers)
        self._mode_labels = list(cat) if modes is None else list(modes)
        bad = [m for m in self._mode_labels if m not in cat]
        if bad:
            raise ValueError(f"thermal_drift: unknown mode(s) {bad}; modes are {list(cat)}")
        super().__init__(robot, joints, geometry)

    @staticmethod
    def _catalog(robot, drivers: list[str]) -> list[str]:
        # fixed joints count: a flange or a tool holder grows like any link
        grow = [f"{jt.name}.growth" for jt in robot.joints if float(abs(jt.origin[:3, 3]).max()) > 1e-6]
        base = ["uniform"] + grow + [f"{mk.name}.growth" for mk in robot.markers]
        if len(drivers) <= 1:
            return base
        return [f"{m}@{c}" for c in drivers for m in base]

    def _split(self, label: str) -> tuple[str, str]:
        """A mode label -> (what grows, the column that drives it)."""
        if "@" in label:
            what, col = label.rsplit("@", 1)
            return what, col
        return label, self.drivers[0] if self.drivers else (self.covariate or "")

    def default_joints(self):
        return []

    def config(self) -> dict:
        return {"covariate": self.covariate, "t0": self.t0, "modes": list(self._mode_labels),
                "drivers": list(self.drivers), "t0s": dict(self.t0s)}

    @property
    def covariates(self) -> list[str]:
        return list(dict.fromkeys(self._split(m)[1] for m in self._mode_labels if self._split(m)[1]))

    @property
    def unit(self) -> str:
        return _unit_of(self.drivers[0]) if len(self.drivers) == 1 else "unit"

    def param_info(self):
        return [(m, f"1/{_unit_of(self._split(m)[1])}") for m in self._mode_labels]

    def modes(self):
        return [(m, [i]) for i, m in enumerate(self._mode_labels)]

    def with_modes(self, labels: list[str]) -> "ThermalDrift":
        keep = set(labels)
        return self._copy(modes=[m for m in self._catalog(self.robot, self.drivers) if m in keep])

    def applicable(self, data):
        if self.covariate or driver_columns(data.covariates):
            return True, ""
        return False, "no temperature, time or other numeric covariate in the data"

    def bind(self, data, min_lever_m: float = 5e-3) -> "ThermalDrift":
        """A copy driven by ``covariate``, or by every driver column of ``data``, each referred to
        its training mean, with the training ranges recorded (a time covariate is never
        extrapolated beyond its own)."""
        cols = [self.covariate] if self.covariate else driver_columns(data.covariates)
        t0s = {c: (self.t0 if c == self.covariate and self.t0 is not None else float(data.covariates[c].mean()))
               for c in cols}
        one = cols[0] if len(cols) == 1 else None
        out = type(self)(self.robot, None, geometry=self.geometry, covariate=one, t0=t0s.get(one), drivers=cols,
                         t0s=t0s)
        out.covariate_range = {c: (float(data.covariates[c].min()), float(data.covariates[c].max())) for c in cols}
        return out

    def prepare(self, q, covariates):
        missing = [c for c in self.covariates if c not in covariates]
        if missing:
            raise ValueError(f"thermal_drift needs the covariate(s) {missing}")
        fr = kinematic_frames(self.robot, q, self.geometry)
        N, M = fr.markers.shape[:2]
        mk_frame = [self.robot.link_frame[mk.link] for mk in self.robot.markers]
        jidx = {jt.name: j for j, jt in enumerate(self.robot.joints)}
        cols, dts = [], []
        for label in self._mode_labels:
            m, c = self._split(label)
            if m == "uniform":
                v = fr.markers  # all translations scale: p -> (1 + αΔT) p about the base origin
            elif m.endswith(".growth") and m[:-7] in jidx:
                j = jidx[m[:-7]]
                vec = fr.o[:, j + 1] - fr.o[:, self.robot.parent_frame[j]]  # the origin vector, base axes
                v = vec[:, None] * fr.beyond[j + 1].to(q.dtype)[None, :, None]
            else:
                k = self.robot.marker_names.index(m[:-7])
                v = torch.zeros(N, M, 3, dtype=q.dtype, device=q.device)
                v[:, k] = fr.markers[:, k] - fr.o[:, mk_frame[k]]
            cols.append(v)
            dts.append(covariates[c].to(q) - self.t0s.get(c, self.t0 or 0.0))
        V = torch.stack(cols, 2) if cols else q.new_zeros(N, M, 0, 3)
        dT = torch.stack(dts, 1) if dts else q.new_zeros(N, 0)
        return Prepared({"dT": dT, "V": V})  # (N, K), (N, M, K, 3)

    def position_delta(self, theta, prep):
        return torch.einsum("pk,nk,nmkd->pnmd", theta, prep.features["dT"], prep.features["V"])

    def signature(self, prep, label, theta):
        k = self._mode_labels.index(label)
        dT = prep.features["dT"][:, k]
        c = self._split(label)[1]
        return {"x": dT, "xlabel": f"{c} − reference [{_unit_of(c)}]", "fitted": theta[k] * dT,
                "ylabel": "relative growth [1]", "G": prep.features["V"][:, :, k]}

    def mode_words(self, label: str) -> str:
        m, cov = self._split(label)
        if m == "uniform":
            return f"every link grows alike with {cov}"
        what = m[:-7]
        if what in self.robot.marker_names:
            return f"the offset of marker {what} on its link grows with {cov}"
        return f"the link carrying {what} (its origin vector) grows with {cov}"

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        th = self.theta if theta is None else theta
        out = []
        for i, m in enumerate(self._mode_labels):
            if free is None or bool(free[i]):
                f, u = display_unit(f"1/{_unit_of(self._split(m)[1])}")  # the report's unit: µm/(m·K)
                out.append(f"{self.mode_words(m)} by {float(th[i]) * f:.3g} {u}")
        return out
