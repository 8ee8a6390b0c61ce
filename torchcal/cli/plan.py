"""``torchcal plan``: which poses to measure (:func:`torchcal.pipelines.plan.run.plan_poses`).

Writes the plan as a CSV of joint columns (rad / m, the joint columns of a measurement file,
in the URDF's names; ``dir.<joint>`` columns when backlash is planned) and, beside it,
``<stem>.plan.json`` and ``<stem>.plan.md``: the criterion, the condition number, the expected
standard error of every parameter, which parameters no pose can identify and why, and what the
self-collision check covers, with the figure ``<stem>.plan.png`` (the poses' coverage). Nothing is overwritten (``--force``).
"""
from __future__ import annotations

import argparse

import torch

from torchcal.cli.conventions import add_progress, progress_on
from torchcal.cli.common import (add_common, inputs_of, int_at_least, nonnegative_float, parse_markers,
                                 positive_float)
from torchcal.outputs import check_out_file, provenance
from torchcal.pipelines.plan.run import check_plannable, plan_paths, plan_poses, plannable_effects
from torchcal.report.plan import save_plan
from torchcal.pipelines.plan.design import CRITERIA
from torchcal.pipelines.plan.feasible import parse_box
from torchcal.kinematics.robot import Robot

__all__ = ["add_plan_parser", "plan_main"]


def _box(text: str):
    try:
        return parse_box(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _effect(text: str) -> str:
    try:
        check_plannable([text])
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _margin(text: str) -> float:
    v = nonnegative_float(text)
    if v >= 0.5:
        raise argparse.ArgumentTypeError(f"must be below 0.5 (a fraction of each joint range, left out at both ends), "
                                         f"got {v}")
    return v


def add_plan_parser(sub) -> argparse.ArgumentParser:
    """Add the ``plan`` sub-command to an ``argparse`` sub-parser set."""
    p = sub.add_parser("plan", help="choose the poses to measure: the most informative subset of candidate poses",
                       description="Draw candidate poses inside the joint limits, keep those inside the working "
                                   "volume and clear of self-collision, select the subset that maximises an "
                                   "information criterion of the identifiable parameters, refine it by gradient "
                                   "ascent, and write it with a report.")
    p.add_argument("--robot", required=True, help="URDF file")
    p.add_argument("--marker", action="append",
                   help="measured frame: LINK or NAME@LINK[=x,y,z] (m); repeatable. Default: every leaf link")
    p.add_argument("--candidates", type=int_at_least(1), default=5000, help="candidate poses drawn")
    p.add_argument("--select", type=int_at_least(1), default=30, help="poses in the plan")
    p.add_argument("--criterion", choices=CRITERIA, default="D",
                   help="D: log det of the information matrix; O1, O4: observability indices")
    p.add_argument("--effect", action="append", default=[], type=_effect, metavar="EFFECT",
                   help="also plan for this effect (repeatable): " + ", ".join(plannable_effects()))
    p.add_argument("--reachable", type=_box, metavar="BOX",
                   help="xmin,xmax,ymin,ymax,zmin,zmax (m, robot base frame): every marker must stay inside")
    p.add_argument("--collision-margin-mm", type=nonnegative_float,
                   help="check self-collision on the URDF's collision shapes with this clearance (mm)")
    p.add_argument("--margin", type=_margin, default=0.1,
                   help="fraction of each joint range left out at both ends")
    p.add_argument("--noise-mm", type=positive_float, default=0.02,
                   help="instrument noise: standard deviation per axis (mm), for the expected standard errors")
    p.add_argument("--refine-steps", type=int_at_least(0), default=100, help="gradient refinement steps (0: none)")
    p.add_argument("--seed", type=int, default=0, help="seeds the candidate draw and the random reference subsets")
    p.add_argument("--out", required=True,
                   help="plan CSV; the report and its figure go beside it (.plan.json, .plan.md, .plan.png)")
    add_progress(p, "the plan's stages (candidates checked, poses selected, refinement steps)")
    add_common(p, units=False)
    p.set_defaults(func=plan_main)
    return p


def plan_main(a: argparse.Namespace, argv: list[str] | None = None) -> int:
    """Run ``torchcal plan`` with parsed arguments (see :func:`add_plan_parser`)."""
    if a.select > a.candidates:
        raise ValueError(f"--select {a.select} is more than --candidates {a.candidates}: draw more candidates or select "
                         "fewer poses")
    paths = plan_paths(a.out)
    for p in paths:
        check_out_file(p, a.force, inputs=inputs_of(a))
    torch.set_num_threads(a.threads)
    robot = Robot.from_urdf(a.robot, markers=parse_markers(a.marker, None) if a.marker else None)
    margin = None if a.collision_margin_mm is None else a.collision_margin_mm * 1e-3
    plan = plan_poses(robot, a.select, n_candidates=a.candidates, criterion=a.criterion, effects=a.effect,
                      reachable=a.reachable, collision_margin=margin, urdf_path=a.robot, noise=a.noise_mm * 1e-3,
                      margin=a.margin, refine_steps=a.refine_steps, seed=a.seed, progress=progress_on(a))
    save_plan(plan, a.out, force=a.force, meta={"provenance": provenance({"urdf": a.robot}, ["torchcal", *(argv or [])])})
    f = plan.feasibility
    print(f"{robot.name}: {plan.q.shape[0]} poses from {f['clear']} feasible candidates ({f['drawn']} drawn); "
          f"{plan.criterion} = {plan.value:.4g} (random subsets: median {plan.stages['random_median']:.4g}); condition "
          f"number {plan.observability['condition']:.4g}; {len(plan.std_errors)} parameters identifiable, "
          f"{len(plan.not_seen)} not (see {paths[2]})")
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0
