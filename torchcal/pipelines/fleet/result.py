"""What a fleet calibration returns: every robot's result, the fleet's values and free flags, the
spread of each parameter across the fleet and the robots flagged, in m and rad. A record:
:mod:`torchcal.report.fleet` writes its files (``torchcal.report.write_report(fleet, out)``)."""
from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.pipelines.calibration_result import CalibrationResult
from torchcal.pipelines.fleet.spread import FALSE_ALARM

__all__ = ["FleetResult"]


@dataclass
class FleetResult:
    """What :func:`calibrate_fleet` found.

    Attributes:
        names: robot ids, in order.
        results: per robot, a :class:`~torchcal.pipelines.calibrate.CalibrationResult` (what
            ``calibrate(robot, data, method="lm")`` returns: parameters, standard errors, reasons,
            error statistics per stage); index the result by robot id or position.
        values: ``(R, K)`` identified parameters; ``free``: ``(R, K)`` which were fitted.
        spread: per parameter, its distribution over the fleet and the robots flagged as outliers
            (:func:`~torchcal.pipelines.fleet.spread.parameter_spread`); ``flags``: those robots, worst first.
        z_threshold, false_alarm: the flag rule (a robot's ``|z|`` beyond ``z_threshold`` and beyond
            the bound at which healthy fleets raise any flag with probability ``false_alarm``).
        prior: the hierarchical prior (fleet mean, scales, noise) when one was used.
        effects: per robot, the fitted effect parameters (name -> value), and the shared ones.
        wall_time_s: the whole fleet solve (every robot's result is part of it).
    """

    robot: Robot
    names: list[str]
    results: list[CalibrationResult]
    values: Tensor
    free: Tensor
    spread: dict
    flags: list[dict]
    identify: str
    z_threshold: float
    prior: dict | None = None
    effects: dict | None = None
    wall_time_s: float = 0.0
    false_alarm: float = FALSE_ALARM

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, key: int | str) -> CalibrationResult:
        if isinstance(key, str):
            if key not in self.names:
                raise KeyError(f"no robot {key!r} in this fleet; robots: {self.names[:5]}…")
            key = self.names.index(key)
        return self.results[key]
