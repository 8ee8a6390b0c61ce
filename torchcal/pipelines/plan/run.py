"""Pose planning: which poses to measure, so that a calibration learns the most from the fewest.

:func:`plan_poses` draws candidate configurations inside the joint limits, keeps those whose
markers lie in the instrument's working volume and that are clear of self-collision
(:mod:`torchcal.pipelines.plan.feasible`), selects the subset that maximises an information criterion of
the identifiable parameters (:mod:`torchcal.pipelines.plan.design`: greedy with rank-1 updates, then an
exchange pass) and refines it by gradient ascent through the differentiable kinematics.

The information matrix is built at the nominal parameters (or ``params``): the instrument frame
(``base.*``) is always among the unknowns, the markers' positions too, as in
:func:`torchcal.pipelines.calibrate`. Effects (``effects=["joint_compliance", "backlash", …]``) add their
linear-basis columns, so that the plan also spreads the gravity torques; for backlash each pose
comes with a direction of approach per joint (+1 / -1), chosen to balance both directions.

The report gives the criterion, the observability indices and condition number of
:mod:`torchcal.problems.identifiability` for the plan, and the standard error every parameter is expected
to have for the instrument's noise: ``σ·sqrt((JᵀJ)⁻¹_ii)``, in mm and mrad.
"""
from __future__ import annotations

import csv
import io
import json
import math
import numbers
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from torchcal.effects import EFFECTS, build_effect
from torchcal.problems.identifiability import analyse_jacobian, observability_indices, resolve_free
from torchcal.outputs import atomic_write_text, check_out_file
from torchcal.params import ParamSet, display_unit
from torchcal.pipelines.plan.design import (CRITERIA, DesignColumns, column_signs, criterion_value, exchange, greedy_select,
                          information, refine_poses, tune_directions)
from torchcal.pipelines.plan.feasible import SelfCollision, in_box, parse_box
from torchcal.kinematics.robot import Robot
from torchcal.report.plan import write_plan_figure
from torchcal.sim.serial import config_bounds
from torchcal.threads import threads_by_size

__all__ = ["plan_poses", "Plan", "PLANNABLE_EFFECTS", "plan_paths", "check_plannable"]

# effects whose columns depend only on the commands (and, for backlash, on a direction the plan
# chooses); thermal drift reads a temperature or a time, which no plan can choose
PLANNABLE_EFFECTS = ("joint_compliance", "elastic_deformation", "backlash", "cyclic_joint_error", "joint_scale")
_N_RANDOM = 20  # random subsets the plan's criterion is compared with


def plan_paths(out) -> tuple[Path, Path, Path]:
    """The files a plan is written to: the CSV and its report beside it (``.plan.json``, ``.plan.md``)."""
    p = Path(out)
    return p, p.with_suffix(".plan.json"), p.with_suffix(".plan.md")


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
                 f"{_N_RANDOM} random subsets of the candidates: median {st['random_median']:.4g}).", "",
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
        a temporary name and renamed."""
        paths = plan_paths(out)
        for p in paths:
            check_out_file(p, force)
        figure = write_plan_figure(self, paths[0], force)
        atomic_write_text(paths[0], self.csv_text())
        atomic_write_text(paths[1], json.dumps({**self.to_dict(), **(meta or {})}, indent=1) + "\n")
        atomic_write_text(paths[2], self.markdown() + figure)
        return list(paths)


def check_plannable(effects: Sequence[str]) -> None:
    """Refuse effect names a plan cannot serve (unknown, or not a function of the commands),
    saying why and which can be planned."""
    bad = [e for e in effects if e not in PLANNABLE_EFFECTS]
    if bad:
        why = " (it reads a temperature or time, which a plan cannot choose)" if "thermal_drift" in bad else ""
        raise ValueError(f"cannot plan for effect(s) {bad}{why}; plannable: {list(PLANNABLE_EFFECTS)}")


def _whole(v, what: str, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not float(v).is_integer() or v < lo:
        raise ValueError(f"{what} must be a whole number ≥ {lo}, got {v!r}")
    return int(v)


def _check_candidates(robot, candidates) -> Tensor:
    """``(N, dof)`` candidate poses, refused when not joint values inside the robot's limits."""
    qc = robot.check_q(candidates, "candidates", _stacklevel=4)
    lo, hi = (x.to(qc) for x in robot.joint_limits)
    out = (qc < lo - 1e-9) | (qc > hi + 1e-9)
    if bool(out.any()):
        i, j = torch.nonzero(out)[0].tolist()
        raise ValueError(f"candidates: {int(out.any(-1).sum())} pose(s) outside the joint limits, the first row {i}: "
                         f"joint {robot.joint_names[j]!r} = {float(qc[i, j]):.4g} not in [{float(lo[j]):.4g}, "
                         f"{float(hi[j]):.4g}] (rad / m); give poses the robot can reach (robot.joint_limits), or "
                         "let plan_poses draw them (leave out candidates)")
    return qc


def _check_args(n_select, n_candidates, criterion, effects, noise, margin, candidates, refine_steps) -> int:
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    check_plannable(effects)
    n_select = _whole(n_select, "n_select (poses to select)", 1)
    _whole(refine_steps, "refine_steps", 0)
    n_cand = candidates.shape[0] if candidates is not None else _whole(n_candidates, "n_candidates", 1)
    if n_select > n_cand:
        raise ValueError(f"cannot select {n_select} poses from {n_cand} candidates: draw more candidates "
                         "(n_candidates / --candidates) or select fewer")
    if not (math.isfinite(noise) and noise > 0):
        raise ValueError(f"noise must be a positive, finite number (m per axis, e.g. 2e-5 for 0.02 mm), got {noise}")
    if not 0 <= margin < 0.5:
        raise ValueError(f"margin is the fraction of each joint range left out at both ends: give 0 ≤ margin < 0.5, "
                         f"got {margin}")
    return n_select


def _feasible_candidates(robot, qc: Tensor, p: Tensor, reachable, collision_margin, urdf_path, n_select: int):
    """The candidates inside the box and clear of self-collision, what was kept at each step,
    and the test ``q (S, dof) -> (S,) bool`` the refinement must keep passing."""
    feas = {"drawn": int(qc.shape[0])}
    box = None if reachable is None else parse_box(reachable)
    if box is not None:
        ok = in_box(robot, qc, box, p)
        if not bool(ok.any()):
            pos = robot.positions(qc, p, check=False, base=False).reshape(-1, 3)
            span = ", ".join(f"{a} {float(pos[:, i].min()):.3g}…{float(pos[:, i].max()):.3g}" for i, a in enumerate("xyz"))
            raise ValueError(f"no candidate pose keeps every marker inside the box {box.tolist()} (m, robot base "
                             f"frame); the markers reach {span} m: widen the box")
        qc = qc[ok]
        feas["box_m"] = box.tolist()
    feas["in_box"] = int(qc.shape[0])
    coll = None
    if collision_margin is not None:
        coll = SelfCollision(robot, collision_margin, urdf_path)
        if coll.checked:
            qc = qc[~coll(qc)]
            feas["collision"] = coll.describe()
        else:
            reason = "the URDF has no <collision> shapes on two movable bodies" if robot.urdf_text else \
                "the robot was not built from a URDF"
            warnings.warn(f"self-collision not checked: {reason}", stacklevel=3)
            feas["collision"] = {"checked": False, "reason": reason}
    feas["clear"] = int(qc.shape[0])
    if qc.shape[0] < n_select:
        raise ValueError(f"only {qc.shape[0]} of {feas['drawn']} candidates are inside the working volume and clear "
                         f"of self-collision, fewer than the {n_select} to select: draw more candidates, widen the "
                         "box or lower the collision margin")

    def feasible(q: Tensor) -> Tensor:
        ok = torch.ones(q.shape[0], dtype=torch.bool, device=q.device)
        if box is not None:
            ok &= in_box(robot, q.detach(), box, p)
        if coll is not None and coll.checked:
            ok &= ~coll(q)
        return ok

    return qc, feas, feasible


@threads_by_size("n_candidates", "candidates")
def plan_poses(robot, n_select: int = 30, *, n_candidates: int = 5000, criterion: str = "D",
               effects: Sequence[str] = (), reachable=None, collision_margin: float | None = None,
               urdf_path=None, noise: float = 2e-5, margin: float = 0.1, refine_steps: int = 100,
               exchange_passes: int = 3, params=None, free=None, candidates: Tensor | None = None,
               seed: int = 0) -> Plan:
    """Plan ``n_select`` calibration poses for ``robot`` (module docstring).

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot` with its markers declared.
        n_candidates: candidates drawn uniformly inside the joint limits (±π where a joint has
            none), ``margin`` of each range left out at both ends; or give ``candidates (N, dof)``.
        criterion: ``"D"`` (log det), ``"O1"`` or ``"O4"`` (:mod:`torchcal.pipelines.plan.design`).
        effects: effects to plan for (:data:`PLANNABLE_EFFECTS`).
        reachable: ``(xmin, xmax, ymin, ymax, zmin, zmax)`` m, robot base frame: every marker
            must lie inside.
        collision_margin: check self-collision with this clearance (m) on the URDF's collision
            shapes (:class:`~torchcal.pipelines.plan.feasible.SelfCollision`); None: not checked.
            ``urdf_path`` lets mesh files be found beside the URDF.
        noise: the instrument's noise, m per axis, for the expected standard errors.
        refine_steps: gradient steps of the refinement (0: none).
        params: ``(K,)`` or a ParamSet: where the model is linearised (default nominal).
        free: the geometric parameters to plan for (names or globs; default as
            :func:`torchcal.pipelines.calibrate`: everything but the markers' orientations).
        seed: seeds the candidate draw and the random reference subsets.

    Returns:
        A :class:`Plan`.
    """
    t0 = time.perf_counter()
    if not isinstance(robot, Robot):
        raise TypeError(f"robot must be a torchcal.Robot with its markers (Robot.from_urdf(path, markers=[...])), got "
                        f"{type(robot).__name__}")
    effects = [effects] if isinstance(effects, str) else list(effects)
    candidates = None if candidates is None else _check_candidates(robot, candidates)
    n_select = _check_args(n_select, n_candidates, criterion, effects, noise, margin, candidates, refine_steps)
    dt = dict(dtype=robot.dtype, device=robot.device)
    p = torch.zeros(robot.n_params, **dt) if params is None else \
        (params.values if isinstance(params, ParamSet) else torch.as_tensor(params, **dt)).detach().clone()
    if free is None:
        ps = robot.params()
        for m in robot.marker_names:
            ps.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
        free = ps
    cols = DesignColumns(robot, p, resolve_free(robot, free), [build_effect(e, robot, geometry=p) for e in effects])
    g = torch.Generator().manual_seed(int(seed))
    lo, hi = config_bounds(robot, margin)
    if candidates is None:
        qc = (lo + (hi - lo) * torch.rand(n_candidates, robot.dof, generator=g, dtype=torch.float64)).to(**dt)
    else:
        qc = candidates
        lo, hi = torch.minimum(lo, qc.min(0).values.cpu()), torch.maximum(hi, qc.max(0).values.cpu())

    qc, feas, feasible = _feasible_candidates(robot, qc, p, reachable, collision_margin, urdf_path, n_select)

    # --- what any pose can identify: judged on all candidates, backlash approached both ways
    A_plus = cols(qc)
    signs = torch.where(torch.rand(qc.shape, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0).to(**dt)
    mixed = cols(qc, signs) if bool((cols.flip >= 0).any()) else A_plus
    rep = analyse_jacobian(mixed.reshape(-1, mixed.shape[-1]), cols.names, cols.units, markers=robot.marker_names)
    keep = [cols.names.index(n) for n in rep.identifiable]
    r = A_plus.shape[1]
    k = len(keep)
    if n_select * r <= k:
        raise ValueError(f"{n_select} poses give {n_select * r} measured coordinates ({r} per pose), not more than the "
                         f"{k} parameters they must identify: select at least {k // r + 1} poses")
    A_all = A_plus[:, :, keep]
    scale = A_all.reshape(-1, k).norm(dim=0) / math.sqrt(A_all.shape[0] * r)
    A = A_all / scale
    flip = cols.flip[keep]

    # --- greedy, exchange, directions, refinement
    sel, D = greedy_select(A, n_select, criterion, flip, robot.dof)
    m = n_select * r
    v_greedy = float(criterion_value(information(A[sel] * column_signs(D, flip)[:, None]), m, criterion))
    sel, D, _ = exchange(A, sel, D, criterion, flip, passes=exchange_passes)
    D = tune_directions(A[sel], D, criterion, flip)
    v_exchange = float(criterion_value(information(A[sel] * column_signs(D, flip)[:, None]), m, criterion))
    planned = bool((flip >= 0).any())
    q = qc[sel]
    hist: list[float] = []
    if refine_steps > 0:
        q, hist = refine_poses(cols, q, D if planned else None, keep, scale, lo.to(**dt), hi.to(**dt), criterion,
                               feasible, steps=refine_steps)
    with torch.no_grad():
        A_plan = cols(q, D if planned else None)[:, :, keep]
    v_refined = float(criterion_value(information(A_plan / scale), m, criterion))
    rnd = []
    for _ in range(_N_RANDOM):
        idx = torch.randperm(qc.shape[0], generator=g)[:n_select]
        s = torch.where(torch.rand(n_select, robot.dof, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0).to(**dt)
        rnd.append(float(criterion_value(information(A[idx] * column_signs(s, flip)[:, None]), m, criterion)))

    # --- report: identifiability of the plan itself, expected standard errors
    J = A_plan.reshape(-1, k)
    names, units = [cols.names[i] for i in keep], [cols.units[i] for i in keep]
    prep = analyse_jacobian(J, names, units, markers=robot.marker_names)
    not_seen = {n: rep.reasons[n] for n in rep.dropped}
    if prep.rank < k:
        warnings.warn(f"the plan identifies only {prep.rank} of the {k} parameters the candidates can; dropped: "
                      f"{prep.dropped[:5]}: select more poses", RuntimeWarning, stacklevel=2)
        not_seen.update({n: "not from this plan: " + prep.reasons[n] for n in prep.dropped})
    ok = [names.index(n) for n in prep.identifiable]
    J, names, units, sc = J[:, ok], [names[i] for i in ok], [units[i] for i in ok], scale[ok]
    Js = J / sc
    se = noise * (torch.linalg.inv(Js.T @ Js).diagonal().clamp(min=0).sqrt() / sc)
    obs = observability_indices(torch.linalg.svdvals(J / (J.norm(dim=0) / math.sqrt(J.shape[0]))).cpu().numpy(),
                                 J.shape[0])
    nat = lambda v: math.exp(v) if criterion != "D" else v  # noqa: E731
    dirs = D.to(**dt) if planned else None
    return Plan(robot=robot, q=q.detach(), directions=dirs,
                direction_joints=[robot.joint_names[j] for j in sorted(set(flip[flip >= 0].tolist()))],
                criterion=criterion, value=nat(v_refined),
                stages={"greedy": nat(v_greedy), "exchange": nat(v_exchange), "refined": nat(v_refined),
                        "random_median": nat(sorted(rnd)[len(rnd) // 2])},
                observability=obs, std_errors=dict(zip(names, se.tolist())), units=dict(zip(names, units)),
                not_seen=not_seen, effects=effects, noise=float(noise),
                feasibility=feas, wall_time_s=time.perf_counter() - t0, refine_history=hist)
