"""A pose plan (:class:`Plan`, what :func:`~torchcal.pipelines.plan.run.plan_poses` returns): the
poses, their approach directions, the criterion at each stage and the expected standard errors,
and the files it is written to (a measurement file's joint columns, ``.plan.json``, ``.plan.md``)."""
from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from torchcal.outputs import atomic_write_text, check_out_file
from torchcal.params import display_unit
from torchcal.report.plan import plan_figure_path, write_plan_figure

__all__ = ["Plan", "plan_paths", "RANDOM_SUBSETS"]

RANDOM_SUBSETS = 20  # random subsets the plan's criterion is compared with


def plan_paths(out) -> tuple[Path, Path, Path, Path]:
    """The files a plan is written to: the CSV and, beside it, its report (``.plan.json``,
    ``.plan.md``) and the report's figure (``.plan.png``)."""
    p = Path(out)
    return p, p.with_suffix(".plan.json"), p.with_suffix(".plan.md"), plan_figure_path(p)


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

    def markdown(self) -> str:
        st, ob = self.stages, self.observability
        lines = [f"# Pose plan for {self.robot.name}", "",
                 f"{self.q.shape[0]} poses, markers {', '.join(self.robot.marker_names)}; criterion {self.criterion} "
                 f"(greedy {st['greedy']:.4g} → exchange {st['exchange']:.4g} → refined {st['refined']:.4g}; "
                 f"{RANDOM_SUBSETS} random subsets of the candidates: median {st['random_median']:.4g}).", "",
                 f"Observability (unit-RMS columns): O1 = {ob['O1']:.4g}, O2 = {ob['O2']:.4g}, O3 = {ob['O3']:.4g}, "
                 f"O4 = {ob['O4']:.4g}; condition number {ob['condition']:.4g}.", ""]
        if self.effects:
            lines += [f"Effects planned for: {', '.join(self.effects)}."]
            if self.direction_joints:
                lines += ["Approach each pose so that joint j last moved in the direction `dir.<j>` (+1: increasing), "
                          "e.g. from q − 0.05 rad·dir, and keep those columns in the measurement file."]
            lines += [""]
        f = self.feasibility
        lines += [f"Candidates: {f['drawn']} drawn, {f['in_box']} inside the working volume, {f['clear']} clear of "
                  "self-collision.", ""]
        col = f.get("collision") or {}
        if col.get("checked"):
            lines += [f"Self-collision: {col['method']}; margin {col['margin_m'] * 1e3:.3g} mm; "
                      f"{len(col['pairs_checked'])} link pairs checked."]
            if col["not_checked_touching_at_zero"]:
                lines += ["Not checked (overlapping at the zero configuration): "
                          + ", ".join(f"{a}–{b}" for a, b in col["not_checked_touching_at_zero"]) + "."]
            if col["not_checked_missing_meshes"]:
                lines += ["Not checked (mesh file not found): " + "; ".join(col["not_checked_missing_meshes"]) + "."]
            lines += [""]
        elif col:
            lines += [f"Self-collision: not checked ({col.get('reason', 'no collision shapes')}).", ""]
        lines += [f"## Expected standard errors (noise {self.noise * 1e3:.3g} mm per axis)", "",
                  "| parameter | std. error | unit |", "|---|---|---|"]
        for n, se in self.std_errors.items():
            fac, u = display_unit(self.units[n])
            lines.append(f"| {n} | {se * fac:.4g} | {u} |")
        if self.not_seen:
            lines += ["", "## Not identifiable from any candidate pose", ""]
            lines += [f"- `{n}`: {why}" for n, why in self.not_seen.items()]
        return "\n".join(lines) + "\n"

    def save(self, out, *, force: bool = False, meta: dict | None = None) -> list[Path]:
        """Write the CSV, ``<stem>.plan.json`` (with ``meta`` merged in), ``<stem>.plan.md`` and its
        figure ``<stem>.plan.png`` (refused when one exists, unless ``force``); each is written under
        a temporary name and renamed. Returns the four paths (:func:`plan_paths`)."""
        paths = plan_paths(out)
        for p in paths:
            check_out_file(p, force)
        figure = write_plan_figure(self, paths[0], force)
        atomic_write_text(paths[0], self.csv_text())
        atomic_write_text(paths[1], json.dumps({**self.to_dict(), **(meta or {})}, indent=1) + "\n")
        atomic_write_text(paths[2], self.markdown() + figure)
        return list(paths)
