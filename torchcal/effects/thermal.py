"""Thermal drift: the links grow with temperature (or, lacking a thermometer, with time)."""
from __future__ import annotations

import torch

from .base import Effect, Prepared

__all__ = ["ThermalDrift", "thermal_covariate"]

_NAMES = ("temperature", "temp", "t_robot", "t_start_robot", "time", "t")


def thermal_covariate(covariates: dict) -> str | None:
    """The covariate a thermal model should use: a temperature column if there is one, else a
    time column, else None."""
    keys = list(covariates)
    for k in keys:
        if "temp" in k.lower():
            return k
    for n in _NAMES:
        if n in covariates:
            return n
    return None


class ThermalDrift(Effect):
    """Uniform thermal expansion of every link length: robot-base positions scale by
    ``1 + α (T − T0)`` (``α`` in 1/unit of the covariate; ``T0`` = training mean). Exact for a
    uniform expansion: all link translations (and marker offsets) scale, rotations do not.
    """

    name = "thermal_drift"
    kind = "position"
    description = "link lengths growing with a temperature (or time) covariate"

    def __init__(self, robot, joints=None, covariate: str | None = None, t0: float | None = None):
        self.covariate, self.t0 = covariate, t0
        super().__init__(robot, joints)

    def default_joints(self):
        return []

    def config(self) -> dict:
        return {"covariate": self.covariate, "t0": self.t0}

    @property
    def covariates(self) -> list[str]:
        return [self.covariate] if self.covariate else []

    def param_info(self):
        return [("alpha", f"1/{self.covariate or 'covariate unit'}")]

    def applicable(self, data):
        c = self.covariate or thermal_covariate(data.covariates)
        if c is None:
            return False, "no temperature or time covariate in the data"
        return True, ""

    def bind(self, data) -> "ThermalDrift":
        """A copy tied to the covariate found in ``data`` and its mean as reference."""
        c = self.covariate or thermal_covariate(data.covariates)
        t0 = float(data.covariates[c].mean()) if self.t0 is None else self.t0
        return ThermalDrift(self.robot, covariate=c, t0=t0)

    def prepare(self, q, covariates):
        if self.covariate not in covariates:
            raise ValueError(f"thermal_drift needs the covariate {self.covariate!r}")
        return Prepared({"dT": (covariates[self.covariate].to(q) - (self.t0 or 0.0))})

    def row_scale(self, theta, prep):
        """``(P, N)`` factor ``1 + α ΔT`` applied to robot-base positions."""
        return 1 + theta[:, :1] * prep.features["dT"][None]

    def position_map(self, p, theta, prep):
        return p * self.row_scale(theta, prep)[..., None, None]
