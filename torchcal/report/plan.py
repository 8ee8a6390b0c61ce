"""A pose plan's files: the CSV of joint values, ``<stem>.plan.json``, ``<stem>.plan.md`` and the
figure of the selected poses' coverage of each joint's range and of the workspace
(``<stem>.plan.png``), from a :class:`~torchcal.pipelines.plan.result.Plan`."""
from __future__ import annotations

import json
from pathlib import Path

from torchcal.outputs import atomic_write_text, check_out_file
from torchcal.params import display_unit
from torchcal.pipelines.plan.result import RANDOM_SUBSETS, plan_paths
from torchcal.report.figures import plan_figure

__all__ = ["write_plan_figure", "plan_figure_path", "plan_markdown", "save_plan"]


def plan_figure_path(csv_path) -> Path:
    """Where a plan's figure goes: ``<stem>.plan.png`` beside its CSV (:func:`plan_paths`)."""
    return plan_paths(csv_path)[3]


def write_plan_figure(plan, csv_path, force: bool = False) -> str:
    """Draw ``plan`` (a :class:`~torchcal.pipelines.plan.run.Plan`) to ``<stem>.plan.png`` beside
    ``csv_path`` (refused when it exists, unless ``force``) and return the Markdown that shows it."""
    path = plan_figure_path(csv_path)
    check_out_file(path, force)
    robot = plan.robot
    lo, hi = (x.detach().cpu().numpy() for x in robot.joint_limits)
    pts = robot.positions(plan.q, None, check=False, base=False).detach().cpu().numpy()
    plan_figure(plan.q.detach().cpu().numpy(), (lo, hi), list(robot.joint_names), pts, path,
                box=plan.feasibility.get("box_m"), title=f"{robot.name}: {plan.q.shape[0]} poses planned "
                f"({plan.criterion}-optimal), nominal marker positions")
    return f"\n![coverage of the joint ranges and of the workspace]({path.name})\n"


def plan_markdown(plan) -> str:
    """``<stem>.plan.md``: the criterion at each stage, observability, what the feasibility checks
    covered, the expected standard errors and what no pose can identify."""
    st, ob = plan.stages, plan.observability
    lines = [f"# Pose plan for {plan.robot.name}", "",
             f"{plan.q.shape[0]} poses, markers {', '.join(plan.robot.marker_names)}; criterion {plan.criterion} "
             f"(greedy {st['greedy']:.4g} → exchange {st['exchange']:.4g} → refined {st['refined']:.4g}; "
             f"{RANDOM_SUBSETS} random subsets of the candidates: median {st['random_median']:.4g}).", "",
             f"Observability (unit-RMS columns): O1 = {ob['O1']:.4g}, O2 = {ob['O2']:.4g}, O3 = {ob['O3']:.4g}, "
             f"O4 = {ob['O4']:.4g}; condition number {ob['condition']:.4g}.", ""]
    if plan.effects:
        lines += [f"Effects planned for: {', '.join(plan.effects)}."]
        if plan.direction_joints:
            lines += ["Approach each pose so that joint j last moved in the direction `dir.<j>` (+1: increasing), "
                      "e.g. from q − 0.05 rad·dir, and keep those columns in the measurement file."]
        lines += [""]
    f = plan.feasibility
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
    lines += [f"## Expected standard errors (noise {plan.noise * 1e3:.3g} mm per axis)", "",
              "| parameter | std. error | unit |", "|---|---|---|"]
    for n, se in plan.std_errors.items():
        fac, u = display_unit(plan.units[n])
        lines.append(f"| {n} | {se * fac:.4g} | {u} |")
    if plan.not_seen:
        lines += ["", "## Not identifiable from any candidate pose", ""]
        lines += [f"- `{n}`: {why}" for n, why in plan.not_seen.items()]
    return "\n".join(lines) + "\n"


def save_plan(plan, out, *, force: bool = False, meta: dict | None = None) -> list[Path]:
    """Write the CSV, ``<stem>.plan.json`` (with ``meta`` merged in), ``<stem>.plan.md`` and its
    figure ``<stem>.plan.png`` (refused when one exists, unless ``force``); each is written under
    a temporary name and renamed."""
    paths = plan_paths(out)
    for p in paths:
        check_out_file(p, force)
    figure = write_plan_figure(plan, paths[0], force)
    atomic_write_text(paths[0], plan.csv_text())
    atomic_write_text(paths[1], json.dumps({**plan.to_dict(), **(meta or {})}, indent=1) + "\n")
    atomic_write_text(paths[2], plan_markdown(plan) + figure)
    return list(paths)
