"""What :func:`~torchcal.pipelines.calibrate.calibrate` found (:class:`CalibrationResult`): the
identified parameters with their standard errors, one status per candidate parameter, the stages'
error statistics, and the calibration files that save it (the report files are
:mod:`torchcal.report.calibration`'s: ``torchcal.report.write_report(result, out)`` writes both)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from torchcal.kinematics.transforms import matrix_to_quat, so3_exp
from torchcal.measure.records import Stage, StageErrors, Suspect
from torchcal.measure.trust import stage_problems
from torchcal.optim import Result
from torchcal.outputs import staged_dir
from torchcal.params import ParamSet
from torchcal.pipelines.precision import PLAUSIBLE, implausible_reason

__all__ = ["CalibrationResult", "write_instrument"]


def _write_json(path, obj: dict) -> None:
    Path(path).write_text(json.dumps(obj, indent=2) + "\n")


def write_instrument(robot, params: ParamSet, path) -> None:
    """The instrument registration (instrument frame <- robot base) as JSON: translation in
    metres and rotation as a unit quaternion (w, x, y, z)."""
    b = params.values[:6]
    R = so3_exp(b[3:])
    _write_json(path, {"frame": "instrument <- robot base: p_instrument = R p_base + t",
                       "translation_m": b[:3].tolist(), "quaternion_wxyz": matrix_to_quat(R).tolist(),
                       "rotation_vector_rad": b[3:].tolist(),
                       "note": "the calibrated URDF is in the robot's own base frame; this is where the instrument "
                               "saw it"})


@dataclass
class CalibrationResult:
    """What :func:`calibrate` found.

    Attributes:
        params: identified values (full ParamSet; its free flags mark what was fitted).
        std_errors: standard error of every fitted parameter (m or rad), from
            ``σ² (JᵀJ)⁻¹`` with ``σ² = SSR / (m − k)``.
        unidentifiable: parameters that were free but could not be identified, with reasons.
        stages: the :class:`~torchcal.measure.records.Stage` records: "nominal" (base registration only)
            and "geometric".
        solver: the optimiser's :class:`~torchcal.optim.Result`.
    """

    robot: object
    params: ParamSet
    std_errors: dict[str, float]
    unidentifiable: dict[str, str]
    stages: list[Stage]
    solver: Result
    method: str
    n_train: int
    n_test: int
    start: ParamSet
    identifiability: object = None
    loss: str = "l2"
    wall_time_s: float = 0.0
    errors: dict[str, StageErrors] = field(default_factory=dict)  # stage name -> its errors (m)
    prior_mm: float | None = None  # Gaussian prior on the geometric errors (mm and mrad), None: none
    prior_reason: str = ""         # why that prior (or none), in words
    prior_tried: list = field(default_factory=list)
    implausible: dict = field(default_factory=dict)  # joint errors beyond their plausible size: name -> value
    plausible: dict = field(default_factory=dict)
    held_by_prior: dict = field(default_factory=dict)  # fitted, but tied: the prior's share, and why
    suspects: list[Suspect] = field(default_factory=list)  # gross errors left out of the fit
    not_converged: str | None = None  # a population method's best short of the optimum beside it: why

    def __repr__(self) -> str:
        last = self.stages[-1]
        te = f", held-out mean {last.test.mean:.4f} mm" if last.test is not None else ""
        return (f"CalibrationResult({self.robot.name}, {self.method}: {len(self.std_errors)} parameters fitted, "
                f"{len(self.unidentifiable)} not identifiable; training mean {last.train.mean:.4f} mm{te})")

    def problems(self) -> list[str]:
        """Reasons not to trust this calibration, in words (empty when none): worse than the
        nominal model on its own training rows, held-out rows that do not fit this robot, or joints
        moved or turned by more than a plausible error, or a population method that stopped short
        of the optimum."""
        out = stage_problems(self.stages)
        if self.not_converged:  # implausible values then say nothing about the data: the search stopped short
            out.append(self.not_converged)
        elif self.implausible:
            out.append(implausible_reason(self.implausible, dict(zip(self.params.names, self.params.units)),
                                          self.plausible or PLAUSIBLE))
        return out

    def statuses(self) -> dict[str, tuple[str, str]]:
        """Every candidate parameter's one status: ``"identified"``, ``"tied"`` (the data cannot
        tell it from others) or ``"fixed"`` (not seen, or pinned down worse than a plausible
        error), with the reason for the latter two."""
        imp = set(getattr(self.identifiability, "imprecise", []) or [])
        out = {n: ("identified", "") for n in self.params.free_names if n not in self.held_by_prior}
        out.update({n: ("tied", why) for n, why in self.held_by_prior.items()})
        for n, why in self.unidentifiable.items():
            fixed = n in imp or "does not move" in why or "not fitted" in why
            out[n] = ("fixed" if fixed else "tied", why)
        return out

    def save(self, out_dir, *, force: bool = False, with_instrument: bool = False, with_markers: bool = False,
             extra=None) -> Path:
        """Write the calibration: ``calibrated.urdf`` (in the robot's own base frame;
        ``with_instrument``: the instrument frame as its root; ``with_markers``: a link per marker; only
        the joints whose change exceeds its standard error), ``calibration.yaml``,
        ``instrument.json`` and ``params.json`` into ``out_dir``, built under a temporary name.
        Refused when ``out_dir`` holds anything (unless ``force``) and when :meth:`problems`
        says the result cannot be trusted. ``extra(tmp_dir)`` may add files before the rename
        (:func:`torchcal.report.write_report` adds the report files so)."""
        if self.problems():
            raise ValueError("not saved, this calibration is not fit to use: " + "; ".join(self.problems()))
        with staged_dir(out_dir, force) as out:
            self.robot.export_calibration(self.params, out, with_instrument=with_instrument, with_markers=with_markers,
                                          std_errors=self.std_errors)
            write_instrument(self.robot, self.params, out / "instrument.json")
            fin = [None if s is None or not math.isfinite(s) else s for s in self.std_errors.values()]
            _write_json(out / "params.json", {"names": self.params.names, "units": self.params.units,
                                              "values": self.params.values.tolist(),
                                              "free": self.params.free.tolist(),
                                              "std_errors": dict(zip(self.std_errors, fin))})
            if extra is not None:
                extra(out)
        return Path(out_dir)
