"""The settings of a fleet calibration (:func:`~torchcal.pipelines.fleet.run.calibrate_fleet`), in
one typed record, and their check at the door."""
from __future__ import annotations

import numbers
from dataclasses import dataclass, replace
from typing import Any

from torchcal.advice import advice
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.pipelines.precision import check_plausible

__all__ = ["FleetOptions"]

_LM_DEFAULTS = {"reuse": 0.9}
_PRIOR_MIN_ROBOTS = 3  # a spread estimated from fewer robots is no estimate


@dataclass(frozen=True)
class FleetOptions(Options):
    """How a fleet is calibrated.

    Attributes:
        params, free: the template ParamSet and glob patterns of parameters to identify, as for
            :func:`torchcal.pipelines.calibrate`.
        prior: ``None`` (every robot alone: the result equals ``calibrate(..., method="lm")``) or
            ``"fleet"``: each robot's geometric errors are drawn around the fleet mean, with
            scales and noise estimated from the fleet (empirical Bayes) unless ``prior_scale``
            gives them (``{"m": metres, "rad": radians}``). It needs at least 3 robots (2 when
            ``prior_scale`` is given).
        effects: ``None`` or ``["joint_compliance"]``: each robot's joints twist with the gravity
            torque (its own compliances, rad/(N·m)), under a payload ``"shared"`` by the fleet or
            fitted ``"per_robot"`` (``payload``; kg, kg·m); needs URDF inertials.
        identify: ``"per_robot"`` (default without coupling) or ``"pooled"``: one identifiable
            set judged on all robots' poses together (always so with a prior or effects).
        register: register each robot's instrument frame first (batched Kabsch), its gross
            errors left out of the fit.
        prefer: parameter names (or patterns) kept first where the data cannot tell several apart.
        min_rows: robots with fewer rows are refused.
        z_threshold: the least distance from its siblings (in their standard deviations) at which a
            robot's parameter is flagged (:mod:`torchcal.report.fleet`).
        false_alarm: the chance that a fleet of healthy robots raises any flag; with few robots the
            bound it sets (Student-t, Bonferroni over robots and parameters) exceeds ``z_threshold``
            (None: the report's default, :data:`torchcal.pipelines.fleet.spread.FALSE_ALARM`, 5 %).
        plausible: the largest plausible error per unit (``{"m": metres, "rad": radians}``), as for
            :func:`torchcal.pipelines.calibrate` (a robot's parameter its data pin down worse is
            fixed; ``{}``: none is).
        options: Levenberg-Marquardt options (``max_iter``, ``tau``, ``gtol``, ``xtol``, ``ftol``,
            ``reuse``).
        ray: address of a Ray cluster (``"auto"``, ``"ray://host:10001"``, or ``"local"`` for an
            in-process one) to spread the robots over (``pip install torchcal[ray]``); ``ray_shards``
            robots are solved per task batch (default: one shard per worker CPU).
    """

    params: ParamSet | None = None
    free: Any = None
    prior: str | None = None
    prior_scale: dict | None = None
    effects: Any = None
    payload: str = "shared"
    identify: str | None = None
    register: bool = True
    prefer: Any = None
    min_rows: int = 3
    z_threshold: float = 5.0
    false_alarm: float | None = None
    plausible: dict | None = None
    options: dict | None = None
    ray: str | None = None
    ray_shards: int | None = None

    @property
    def coupled(self) -> bool:
        """A prior or fleet-wide effects tie the robots' fits together."""
        return self.prior is not None or bool(self.effects)

    def checked(self, n_robots: int) -> "FleetOptions":
        """These settings checked for a fleet of ``n_robots``, with the defaults that depend on
        others filled in (the identifiable set's judgement, the plausible sizes, the LM's
        settings), or an error that says what is wrong."""
        effects = [self.effects] if isinstance(self.effects, str) else self.effects
        if self.prior not in (None, "fleet"):
            raise ValueError(f"prior must be None or 'fleet', got {self.prior!r}")
        if self.payload not in ("shared", "per_robot"):
            raise ValueError(f"payload must be 'shared' or 'per_robot', got {self.payload!r}")
        if not (isinstance(self.z_threshold, numbers.Real) and 0 < self.z_threshold < float("inf")):
            raise ValueError("z_threshold is a robust z-score beyond which a parameter is flagged: give a positive "
                             f"number (default 5), got {self.z_threshold!r}")
        if self.false_alarm is not None and not (isinstance(self.false_alarm, numbers.Real)
                                                 and 0 < self.false_alarm < 1):
            raise ValueError("false_alarm is the chance that a fleet of healthy robots raises any flag: give a number "
                             f"between 0 and 1 (default 5 %), got {self.false_alarm!r}")
        self._check_prior(n_robots)
        if self.identify not in (None, "per_robot", "pooled"):
            raise ValueError(f"identify must be 'per_robot' or 'pooled', got {self.identify!r}")
        if self.coupled and self.identify == "per_robot":
            raise ValueError("a prior or fleet-wide effects couple the robots: their parameters are judged on the "
                             "pooled design; use identify='pooled' (or leave it out)")
        plausible = check_plausible(self.plausible)
        if self.ray is not None and self.coupled:
            raise ValueError("on Ray the robots are solved independently; a prior or a shared payload couples them. "
                             "Run those in-process (leave out ray=)")
        return replace(self, effects=effects, identify=self.identify or ("pooled" if self.coupled else "per_robot"),
                       plausible=plausible, options={**_LM_DEFAULTS, **dict(self.options or {})})

    def _check_prior(self, n_robots: int) -> None:
        need = _PRIOR_MIN_ROBOTS if self.prior_scale is None else 2
        if self.prior is not None and n_robots < need:
            estimated = self.prior_scale is None
            raise ValueError("prior='fleet' pulls each robot towards the fleet mean by how far robots spread around it"
                             + (", which is estimated from the fleet" if estimated else "")
                             + f": {n_robots} robot(s) are too few to tell. Give at least {need} robots"
                             + (advice(" (or prior_scale={'m': …, 'rad': …} with 2)", "") if estimated else "")
                             + ", or leave out the prior")
