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


class ThermalDrift(Effect):
    """Links growing with a temperature (or time) covariate, per link or all alike.

    Args:
        covariate: the column read (default: found in the data by :meth:`bind`).
        t0: reference value of the covariate (default: the training mean).
        modes: ``"uniform"``, ``"<joint>.growth"`` (the origin vector of that joint, in its
            parent link), ``"<marker>.growth"`` (the marker's offset on its link); default all.
    """

    name = "thermal_drift"
    description = "link lengths growing with a temperature (or time) covariate"
    selectable = True

    def __init__(self, robot, joints=None, geometry=None, covariate: str | None = None, t0: float | None = None,
                 modes: list[str] | None = None):
        self.covariate, self.t0 = covariate, t0
        cat = self._catalog(robot)
        self._mode_labels = list(cat) if modes is None else list(modes)
        bad = [m for m in self._mode_labels if m not in cat]
        if bad:
            raise ValueError(f"thermal_drift: unknown mode(s) {bad}; modes are {list(cat)}")
        super().__init__(robot, joints, geometry)

    @staticmethod
    def _catalog(robot) -> list[str]:
        # fixed joints count: a flange or a tool holder grows like any link
        grow = [f"{jt.name}.growth" for jt in robot.joints if float(abs(jt.origin[:3, 3]).max()) > 1e-6]
        return ["uniform"] + grow + [f"{mk.name}.growth" for mk in robot.markers]

    def default_joints(self):
        return []

    def config(self) -> dict:
        return {"covariate": self.covariate, "t0": self.t0, "modes": list(self._mode_labels)}

    @property
    def covariates(self) -> list[str]:
        return [self.covariate] if self.covariate else []

    @property
    def unit(self) -> str:
        return "s" if self.covariate in TIME_COVARIATES else "K"

    def param_info(self):
        return [(m, f"1/{self.unit}") for m in self._mode_labels]

    def modes(self):
        return [(m, [i]) for i, m in enumerate(self._mode_labels)]

    def with_modes(self, labels: list[str]) -> "ThermalDrift":
        keep = set(labels)
        return self._copy(modes=[m for m in self._catalog(self.robot) if m in keep])

    def applicable(self, data):
        c = self.covariate or thermal_covariate(data.covariates)
        if c is None:
            return False, "no temperature or time covariate in the data"
        return True, ""

    def bind(self, data, min_lever_m: float = 5e-3) -> "ThermalDrift":
        """A copy tied to the covariate found in ``data``, its training mean as reference, and
        its training range recorded (a time covariate is never extrapolated beyond it)."""
        c = self.covariate or thermal_covariate(data.covariates)
        t0 = float(data.covariates[c].mean()) if self.t0 is None else self.t0
        out = self._copy(covariate=c, t0=t0)
        out.covariate_range = {c: (float(data.covariates[c].min()), float(data.covariates[c].max()))}
        return out

    def prepare(self, q, covariates):
        if self.covariate not in covariates:
            raise ValueError(f"thermal_drift needs the covariate {self.covariate!r}")
        fr = kinematic_frames(self.robot, q, self.geometry)
        N, M = fr.markers.shape[:2]
        mk_frame = [self.robot.link_frame[mk.link] for mk in self.robot.markers]
        jidx = {jt.name: j for j, jt in enumerate(self.robot.joints)}
        cols = []
        for m in self._mode_labels:
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
        dT = covariates[self.covariate].to(q) - (self.t0 or 0.0)
        return Prepared({"dT": dT, "V": torch.stack(cols, 2)})  # (N,), (N, M, K, 3)

    def position_delta(self, theta, prep):
        return torch.einsum("pk,n,nmkd->pnmd", theta, prep.features["dT"], prep.features["V"])

    def signature(self, prep, label, theta):
        k = self._mode_labels.index(label)
        dT = prep.features["dT"]
        return {"x": dT, "xlabel": f"{self.covariate} − reference [{self.unit}]", "fitted": theta[k] * dT,
                "ylabel": "relative growth [1]", "G": prep.features["V"][:, :, k]}

    def mode_words(self, label: str) -> str:
        cov = self.covariate or "the covariate"
        if label == "uniform":
            return f"every link grows alike with {cov}"
        what = label[:-7]
        if what in self.robot.marker_names:
            return f"the offset of marker {what} on its link grows with {cov}"
        return f"the link carrying {what} (its origin vector) grows with {cov}"

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        th = self.theta if theta is None else theta
        f, u = display_unit(f"1/{self.unit}")  # the report's unit: µm/(m·K), or µm/(m·h) for a time
        return [f"{self.mode_words(m)} by {float(th[i]) * f:.3g} {u}"
                for i, m in enumerate(self._mode_labels) if free is None or bool(free[i])]
