"""Many robots of one type calibrated in one batched run, on one machine or several (Ray)."""
from torchcal.pipelines.fleet.result import FleetResult
from torchcal.pipelines.fleet.run import calibrate_fleet

__all__ = ["calibrate_fleet", "FleetResult"]
