"""The pose plan's figure: the selected poses' coverage of each joint's range and of the
workspace (``<stem>.plan.png`` beside the plan)."""
from __future__ import annotations

from pathlib import Path

from torchcal.outputs import check_out_file
from torchcal.report.figures import plan_figure

__all__ = ["write_plan_figure", "plan_figure_path"]


def plan_figure_path(csv_path) -> Path:
    """Where a plan's figure goes: ``<stem>.plan.png`` beside its CSV."""
    return Path(csv_path).with_suffix(".plan.png")


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
