"""Which poses to measure: candidate generation, feasibility and optimal design."""
from torchcal.pipelines.plan.run import Plan, plan_poses

__all__ = ["plan_poses", "Plan"]
