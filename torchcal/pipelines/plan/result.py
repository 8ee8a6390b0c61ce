"""A pose plan (:class:`Plan`, what :func:`~torchcal.pipelines.plan.run.plan_poses` returns): the
poses, their approach directions, the criterion at each stage and the expected standard errors,
and where it is written (a measurement file's joint columns, ``.plan.json``, ``.plan.md``: the files
:func:`torchcal.report.plan.save_plan` writes)."""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor


__all__ = ["Plan", "plan_paths", "RANDOM_SUBSETS"]

RANDOM_SUBSETS = 20  # random subsets the plan's criterion is compared with


def plan_paths(out) -> tuple[Path, Path, Path, Path]:
    """The files a plan is written to: the CSV and, beside it, its report (``.plan.json``,
    ``.plan.md``) and the report's figure (``.plan.png``)."""
    p = Path(out)
    return p, p.with_suffix(".plan.json"), p.with_suffix(".plan.md"), p.with_suffix(".plan.png")


@dataclass
class Plan:
    """A pose plan (see :func:`plan_poses`).

    Attributes:
        q: ``(S, dof)`` joint values to measure (rad / m), in ``robot.joint_names`` order.
        directions: ``(S, dof)`` direction (+1 / -1) in which each joint should last move before
            the pose is measured, or None when backlash is not planned; ``direction_joints``
            names the joints whose backlash the plan can see (the CSV's ``dir.<joint>`` columns).
        criterion, value: the criterion maximised and its value at the plan (``"D"``: log det
            of the scaled information matrix; ``"O1"``/``"O4"``: the index itself).
        stages: the criterion after the greedy selection, the exchange pass and the gradient
            refinement, and the median over random subsets of the candidates.
        observability: O1–O4 and the condition number of the plan's identifiable columns
            (:mod:`torchcal.problems.identifiability` convention: unit-RMS columns).
        std_errors: expected standard error of every identifiable parameter (its own unit: m,
            rad, or the effect's) for noise ``noise`` (m per axis).
        not_seen: parameters no candidate pose can identify, with the reason.
        feasibility: candidates drawn, kept by the box, kept by the collision check; what the
            collision check does and does not cover.
    """

    robot: object
    q: Tensor
    directions: Tensor | None
    direction_joints: list[str]
    criterion: str
    value: float
    stages: dict[str, float]
    observability: dict[str, float]
    std_errors: dict[str, float]
    units: dict[str, str]
    not_seen: dict[str, str]
    effects: list[str]
    noise: float
    feasibility: dict
    wall_time_s: float = 0.0
    refine_history: list[float] = field(default_factory=list)

    def __repr__(self) -> str:
        return (f"Plan({self.robot.name}: {self.q.shape[0]} poses, {self.criterion} = {self.value:.4g} (random "
                f"median {self.stages['random_median']:.4g}), condition {self.observability['condition']:.3g}, "
                f"{len(self.std_errors)} parameters identifiable, {len(self.not_seen)} not)")

    def csv_text(self) -> str:
        """The plan as a measurement file's joint columns (rad / m, full precision), then the
        ``dir.<joint>`` columns when backlash is planned."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        dj = [self.robot.joint_names.index(j) for j in self.direction_joints]
        w.writerow(list(self.robot.joint_names) + [f"dir.{j}" for j in self.direction_joints])
        for s in range(self.q.shape[0]):
            w.writerow([repr(float(v)) for v in self.q[s]] + [str(int(self.directions[s, j])) for j in dj])
        return buf.getvalue()

    def to_dict(self) -> dict:
        fin = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
        return {"robot": self.robot.name, "markers": list(self.robot.marker_names), "n_poses": int(self.q.shape[0]),
                "joints": list(self.robot.joint_names), "criterion": self.criterion, "value": fin(self.value),
                "stages": {k: fin(v) for k, v in self.stages.items()},
                "observability": {k: fin(v) for k, v in self.observability.items()},
                "noise_mm": self.noise * 1e3, "effects": list(self.effects),
                "std_errors": {n: {"value": se, "unit": self.units[n]} for n, se in self.std_errors.items()},
                "not_seen": dict(self.not_seen), "direction_joints": list(self.direction_joints),
                "feasibility": self.feasibility, "wall_time_s": self.wall_time_s,
                "q": self.q.tolist(), "directions": None if self.directions is None else self.directions.tolist()}
