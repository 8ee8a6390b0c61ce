"""Pose planning: which poses to measure, so that a calibration learns the most from the fewest.

:func:`plan_poses` draws candidate configurations inside the joint limits, keeps those whose
markers lie in the instrument's working volume and that are clear of self-collision
(:mod:`torchcal.pipelines.plan.feasible`), selects the subset that maximises an information criterion of
the identifiable parameters (:mod:`torchcal.pipelines.plan.design`: greedy with rank-1 updates, then an
exchange pass) and refines it by gradient ascent through the differentiable kinematics.

The information matrix is built at the nominal parameters (or ``params``): the instrument frame
(``base.*``) is always among the unknowns, the markers' positions too, as in
:func:`torchcal.pipelines.calibrate`. Effects (``effects=["joint_compliance", "backlash", …]``) add their
linear-basis columns, so that the plan also spreads the gravity torques; for an effect that reads
approach directions (backlash) each pose comes with a direction of approach per joint (+1 / -1),
chosen to balance both directions.

The report (:class:`~torchcal.pipelines.plan.result.Plan`) gives the criterion, the observability
indices and condition number of :mod:`torchcal.problems.identifiability` for the plan, and the
standard error every parameter is expected to have for the instrument's noise:
``σ·sqrt((JᵀJ)⁻¹_ii)``, in mm and mrad.
"""
from __future__ import annotations

import math
import numbers
import time
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

from torchcal.effects import EFFECTS, build_effect
from torchcal.kinematics.bounds import config_bounds
from torchcal.kinematics.robot import Robot
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.pipelines.plan.design import (CRITERIA, DesignColumns, column_signs, criterion_value, exchange,
                                            greedy_select, information, refine_poses, tune_directions)
from torchcal.pipelines.plan.feasible import SelfCollision, in_box, parse_box
from torchcal.pipelines.plan.result import RANDOM_SUBSETS, Plan, plan_paths
from torchcal.problems.identifiability import analyse_jacobian, observability_indices, resolve_free
from torchcal.threads import threads_by_size

__all__ = ["plan_poses", "PlanOptions", "Plan", "PLANNABLE_EFFECTS", "plannable_effects", "plan_paths",
           "check_plannable"]


def plannable_effects() -> tuple[str, ...]:
    """The registered effects a plan can serve (:meth:`~torchcal.effects.base.Effect.plannable`:
    they read only the commands and the approach directions a plan chooses)."""
    return tuple(n for n, cls in EFFECTS.items() if cls.plannable())


PLANNABLE_EFFECTS = plannable_effects()  # those registered when torchcal is imported


@dataclass(frozen=True)
class PlanOptions(Options):
    """How :func:`plan_poses` plans.

    Attributes:
        criterion: ``"D"`` (log det), ``"O1"`` or ``"O4"`` (:mod:`torchcal.pipelines.plan.design`).
        effects: effect names to plan for (:func:`plannable_effects`); one name may be a string.
        reachable: ``(xmin, xmax, ymin, ymax, zmin, zmax)`` m, robot base frame: every marker
            must lie inside (None: anywhere).
        collision_margin: check self-collision with this clearance (m) on the URDF's collision
            shapes (:class:`~torchcal.pipelines.plan.feasible.SelfCollision`); None: not checked.
            ``urdf_path`` lets mesh files be found beside the URDF.
        noise: the instrument's noise, m per axis, for the expected standard errors.
        margin: the fraction of each joint range left out at both ends when candidates are drawn.
        refine_steps: gradient steps of the refinement (0: none); ``exchange_passes``: sweeps of
            the exchange pass.
        seed: seeds the candidate draw and the random reference subsets.
        progress: a progress bar (tqdm) over the plan's stages, with the time left.
    """

    criterion: str = "D"
    effects: Sequence[str] = ()
    reachable: Any = None
    collision_margin: float | None = None
    urdf_path: Any = None
    noise: float = 2e-5
    margin: float = 0.1
    refine_steps: int = 100
    exchange_passes: int = 3
    seed: int = 0
    progress: bool = False


def check_plannable(effects: Sequence[str]) -> None:
    """Refuse effect names a plan cannot serve (unknown, or not a function of the commands),
    saying why and which can be planned."""
    ok = plannable_effects()
    bad = [e for e in effects if e not in ok]
    if bad:
        measured = [e for e in bad if e in EFFECTS and "measured" in EFFECTS[e].reads]
        why = " (it reads a temperature or time, which a plan cannot choose)" if measured else ""
        raise ValueError(f"cannot plan for effect(s) {bad}{why}; plannable: {list(ok)}")


def _whole(v, what: str, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not float(v).is_integer() or v < lo:
        raise ValueError(f"{what} must be a whole number ≥ {lo}, got {v!r}")
    return int(v)


def _check_candidates(robot, candidates) -> Tensor:
    """``(N, dof)`` candidate poses, refused when not joint values inside the robot's limits."""
    qc = robot.check_q(candidates, "candidates", _stacklevel=5)  # the caller of plan_poses
    lo, hi = (x.to(qc) for x in robot.joint_limits)
    out = (qc < lo - 1e-9) | (qc > hi + 1e-9)
    if bool(out.any()):
        i, j = torch.nonzero(out)[0].tolist()
        raise ValueError(f"candidates: {int(out.any(-1).sum())} pose(s) outside the joint limits, the first row {i}: "
                         f"joint {robot.joint_names[j]!r} = {float(qc[i, j]):.4g} not in [{float(lo[j]):.4g}, "
                         f"{float(hi[j]):.4g}] (rad / m); give poses the robot can reach (robot.joint_limits), or "
                         "let plan_poses draw them (leave out candidates)")
    return qc


def _check_args(n_select, n_candidates, opt: PlanOptions, effects: list[str], candidates) -> int:
    criterion, noise, margin = opt.criterion, opt.noise, opt.margin
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    check_plannable(effects)
    n_select = _whole(n_select, "n_select (poses to select)", 1)
    _whole(opt.refine_steps, "refine_steps", 0)
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


def _feasible_candidates(robot, qc: Tensor, p: Tensor, opt: PlanOptions, n_select: int):
    """The candidates inside the box and clear of self-collision, what was kept at each step,
    and the test ``q (S, dof) -> (S,) bool`` the refinement must keep passing."""
    feas = {"drawn": int(qc.shape[0])}
    box = None if opt.reachable is None else parse_box(opt.reachable)
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
    if opt.collision_margin is not None:
        coll = SelfCollision(robot, opt.collision_margin, opt.urdf_path)
        if coll.checked:
            qc = qc[~coll(qc)]
            feas["collision"] = coll.describe()
        else:
            reason = "the URDF has no <collision> shapes on two movable bodies" if robot.urdf_text else \
                "the robot was not built from a URDF"
            warnings.warn(f"self-collision not checked: {reason}", stacklevel=4)
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


def _linearised_at(robot, params, free) -> tuple[Tensor, list[int]]:
    """``(K,)`` parameters the model is linearised at and the geometric parameters planned for
    (default as :func:`torchcal.pipelines.calibrate`: everything but the markers' orientations)."""
    dt = dict(dtype=robot.dtype, device=robot.device)
    p = torch.zeros(robot.n_params, **dt) if params is None else \
        (params.values if isinstance(params, ParamSet) else torch.as_tensor(params, **dt)).detach().clone()
    if free is None:
        free = robot.params()
        for m in robot.marker_names:
            free.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
    return p, resolve_free(robot, free)


def _draw_candidates(robot, n: int, margin: float, candidates, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """``(N, dof)`` candidates (drawn, or those given) and the ``(dof,)`` bounds the refinement
    keeps to (widened to the candidates given)."""
    lo, hi = config_bounds(robot, margin)
    if candidates is None:
        u = torch.rand(n, robot.dof, generator=g, dtype=torch.float64)
        return (lo + (hi - lo) * u).to(dtype=robot.dtype, device=robot.device), lo, hi
    lo, hi = torch.minimum(lo, candidates.min(0).values.cpu()), torch.maximum(hi, candidates.max(0).values.cpu())
    return candidates, lo, hi


def _scaled_columns(robot, cols: DesignColumns, qc: Tensor, g: torch.Generator, n_select: int):
    """What any pose can identify, judged on all candidates with backlash approached both ways:
    the candidates' blocks of the identifiable columns, scaled to unit RMS (``A (N, r, k)``), the
    scales, the columns kept, their direction flips and the identifiability report."""
    A_plus = cols(qc)
    signs = torch.where(torch.rand(qc.shape, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    signs = signs.to(dtype=robot.dtype, device=robot.device)
    mixed = cols(qc, signs) if bool((cols.flip >= 0).any()) else A_plus
    rep = analyse_jacobian(mixed.reshape(-1, mixed.shape[-1]), cols.names, cols.units, markers=robot.marker_names)
    keep = [cols.names.index(n) for n in rep.identifiable]
    r, k = A_plus.shape[1], len(keep)
    if n_select * r <= k:
        raise ValueError(f"{n_select} poses give {n_select * r} measured coordinates ({r} per pose), not more than the "
                         f"{k} parameters they must identify: select at least {k // r + 1} poses")
    A_all = A_plus[:, :, keep]
    scale = A_all.reshape(-1, k).norm(dim=0) / math.sqrt(A_all.shape[0] * r)
    return A_all / scale, scale, keep, cols.flip[keep], rep


def _select(A: Tensor, n_select: int, opt: PlanOptions, flip: Tensor, dof: int) -> tuple[list[int], Tensor, dict]:
    """Greedy selection, the exchange pass and the approach directions: the chosen candidates,
    their directions ``D (S, dof)`` and the criterion after the first two stages."""
    m, crit = n_select * A.shape[1], opt.criterion
    sel, D = greedy_select(A, n_select, crit, flip, dof)
    v_greedy = float(criterion_value(information(A[sel] * column_signs(D, flip)[:, None]), m, crit))
    sel, D, _ = exchange(A, sel, D, crit, flip, passes=opt.exchange_passes)
    D = tune_directions(A[sel], D, crit, flip)
    v_exchange = float(criterion_value(information(A[sel] * column_signs(D, flip)[:, None]), m, crit))
    return sel, D, {"greedy": v_greedy, "exchange": v_exchange}


class _Stages:
    """A tqdm bar over the plan's stages, each weighted by its work (a selected pose, a refinement
    step, a pass over the candidates), so that the time left is an estimate."""

    def __init__(self, on: bool, n_select: int, refine_steps: int):
        self.bar = None
        if on:
            from tqdm.auto import tqdm
            self.bar = tqdm(total=2 + n_select + refine_steps, desc="plan: drawing candidates", unit="step")

    def done(self, what: str, n: int) -> None:
        if self.bar is not None:
            self.bar.set_description(f"plan: {what}")
            self.bar.update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _random_median(A: Tensor, n_select: int, crit: str, flip: Tensor, dof: int, g: torch.Generator) -> float:
    """Median criterion of :data:`RANDOM_SUBSETS` random subsets of the candidates ``A (N, r, k)``,
    each pose approached in random directions."""
    m, rnd = n_select * A.shape[1], []
    for _ in range(RANDOM_SUBSETS):
        idx = torch.randperm(A.shape[0], generator=g)[:n_select]
        s = torch.where(torch.rand(n_select, dof, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0).to(A)
        rnd.append(float(criterion_value(information(A[idx] * column_signs(s, flip)[:, None]), m, crit)))
    return sorted(rnd)[len(rnd) // 2]


def _expected_errors(robot, A_plan: Tensor, names: list[str], units: list[str], scale: Tensor, noise: float,
                     rep) -> tuple[dict, dict, dict, dict]:
    """Identifiability of the plan itself: observability indices, the expected standard error of
    each identifiable parameter for ``noise`` (m per axis), units, and what is not seen and why."""
    k = len(names)
    J = A_plan.reshape(-1, k)
    prep = analyse_jacobian(J, names, units, markers=robot.marker_names)
    not_seen = {n: rep.reasons[n] for n in rep.dropped}
    if prep.rank < k:
        warnings.warn(f"the plan identifies only {prep.rank} of the {k} parameters the candidates can; dropped: "
                      f"{prep.dropped[:5]}: select more poses", RuntimeWarning, stacklevel=4)
        not_seen.update({n: "not from this plan: " + prep.reasons[n] for n in prep.dropped})
    ok = [names.index(n) for n in prep.identifiable]
    J, names, units, sc = J[:, ok], [names[i] for i in ok], [units[i] for i in ok], scale[ok]
    Js = J / sc
    se = noise * (torch.linalg.inv(Js.T @ Js).diagonal().clamp(min=0).sqrt() / sc)
    obs = observability_indices(torch.linalg.svdvals(J / (J.norm(dim=0) / math.sqrt(J.shape[0]))).cpu().numpy(),
                                 J.shape[0])
    return obs, dict(zip(names, se.tolist())), dict(zip(names, units)), not_seen


@threads_by_size("n_candidates", "candidates")
def plan_poses(robot, n_select: int = 30, *, n_candidates: int = 5000, candidates: Tensor | None = None,
               params=None, free=None, settings: PlanOptions | None = None, **kw) -> Plan:
    """Plan ``n_select`` calibration poses for ``robot`` (module docstring).

    Args:
        robot: a :class:`~torchcal.kinematics.robot.Robot` with its markers declared.
        n_candidates: candidates drawn uniformly inside the joint limits (±π where a joint has
            none), ``margin`` of each range left out at both ends; or give ``candidates (N, dof)``
            (rad / m).
        params: ``(K,)`` or a ParamSet: where the model is linearised (default nominal).
        free: the geometric parameters to plan for (names or globs; default as
            :func:`torchcal.pipelines.calibrate`: everything but the markers' orientations).
        settings, kw: a :class:`PlanOptions` and/or its fields as keywords (``criterion="O4"``,
            ``effects=["backlash"]``, ``noise=2e-5``, …).

    Returns:
        A :class:`~torchcal.pipelines.plan.result.Plan`.
    """
    t0 = time.perf_counter()
    opt = PlanOptions.build(settings, **kw)
    if not isinstance(robot, Robot):
        raise TypeError(f"robot must be a torchcal.Robot with its markers (Robot.from_urdf(path, markers=[...])), got "
                        f"{type(robot).__name__}")
    effects = [opt.effects] if isinstance(opt.effects, str) else list(opt.effects)
    candidates = None if candidates is None else _check_candidates(robot, candidates)
    n_select = _check_args(n_select, n_candidates, opt, effects, candidates)
    dt = dict(dtype=robot.dtype, device=robot.device)
    p, geo = _linearised_at(robot, params, free)
    cols = DesignColumns(robot, p, geo, [build_effect(e, robot, geometry=p) for e in effects])
    g = torch.Generator().manual_seed(int(opt.seed))
    bar = _Stages(opt.progress, n_select, opt.refine_steps)
    qc, lo, hi = _draw_candidates(robot, n_candidates, opt.margin, candidates, g)
    qc, feas, feasible = _feasible_candidates(robot, qc, p, opt, n_select)
    bar.done("candidates checked", 1)
    A, scale, keep, flip, rep = _scaled_columns(robot, cols, qc, g, n_select)
    bar.done("information of each candidate", 1)

    sel, D, stages = _select(A, n_select, opt, flip, robot.dof)
    bar.done(f"{n_select} poses selected", n_select)
    planned = bool((flip >= 0).any())
    q, hist = qc[sel], []
    if opt.refine_steps > 0:
        q, hist = refine_poses(cols, q, D if planned else None, keep, scale, (lo.to(**dt), hi.to(**dt)),
                               opt.criterion, feasible, steps=opt.refine_steps)
    bar.done("poses refined", opt.refine_steps)
    bar.close()
    with torch.no_grad():
        A_plan = cols(q, D if planned else None)[:, :, keep]
    stages["refined"] = float(criterion_value(information(A_plan / scale), n_select * A.shape[1], opt.criterion))
    stages["random_median"] = _random_median(A, n_select, opt.criterion, flip, robot.dof, g)

    obs, se, units, not_seen = _expected_errors(robot, A_plan, [cols.names[i] for i in keep],
                                                [cols.units[i] for i in keep], scale, opt.noise, rep)
    nat = lambda v: math.exp(v) if opt.criterion != "D" else v  # noqa: E731
    return Plan(robot=robot, q=q.detach(), directions=D.to(**dt) if planned else None,
                direction_joints=[robot.joint_names[j] for j in sorted(set(flip[flip >= 0].tolist()))],
                criterion=opt.criterion, value=nat(stages["refined"]), stages={k: nat(v) for k, v in stages.items()},
                observability=obs, std_errors=se, units=units, not_seen=not_seen, effects=effects,
                noise=float(opt.noise), feasibility=feas, wall_time_s=time.perf_counter() - t0, refine_history=hist)
