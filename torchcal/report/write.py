"""One door to a result's report: :func:`write_report` writes the files of any driver's result,
:func:`report_json` gives the content of its ``report.json``. Results are records
(:mod:`torchcal.pipelines`); the modules here read them and write files."""
from __future__ import annotations

from pathlib import Path

from torchcal.pipelines.calibration_result import CalibrationResult
from torchcal.pipelines.fleet.result import FleetResult
from torchcal.pipelines.loop.result import LoopResult
from torchcal.pipelines.plan.result import Plan
from torchcal.report.calibration import calibration_json, save_calibration
from torchcal.report.fleet import fleet_report, save_fleet
from torchcal.report.loop import loop_json, write_loop_report
from torchcal.report.plan import save_plan

__all__ = ["write_report", "report_json"]


def _kind(result) -> str:
    for cls, kind in ((CalibrationResult, "calibrate"), (LoopResult, "loop"), (FleetResult, "fleet"), (Plan, "plan")):
        if isinstance(result, cls):
            return kind
    raise TypeError(f"write_report takes what calibrate, run_loop, calibrate_fleet or plan_poses return, "
                    f"not {type(result).__name__}")


def write_report(result, out, **options) -> Path | list[Path]:
    """Write ``result``'s files to ``out``:

    - a :class:`~torchcal.pipelines.calibration_result.CalibrationResult`: the calibration and its
      report in the new folder ``out`` (:func:`~torchcal.report.calibration.save_calibration`;
      options ``force``, ``with_instrument``, ``with_markers``, ``extra``);
    - a :class:`~torchcal.pipelines.loop.result.LoopResult`: its report into the folder ``out``
      (:func:`~torchcal.report.loop.write_loop_report`; option ``command``);
    - a :class:`~torchcal.pipelines.fleet.result.FleetResult`: every robot's folder and the fleet's
      report (:func:`~torchcal.report.fleet.save_fleet`; options ``figures``, ``on_robot``, ``with_markers``);
    - a :class:`~torchcal.pipelines.plan.result.Plan`: the CSV ``out`` and its report beside it
      (:func:`~torchcal.report.plan.save_plan`; options ``force``, ``meta``).
    """
    writer = {"calibrate": save_calibration, "loop": write_loop_report, "fleet": save_fleet,
              "plan": save_plan}[_kind(result)]
    return writer(result, out, **options)


def report_json(result) -> dict:
    """The content of ``report.json`` (``fleet.json``, ``.plan.json``) for ``result``."""
    return {"calibrate": calibration_json, "loop": loop_json, "fleet": fleet_report,
            "plan": lambda p: p.to_dict()}[_kind(result)](result)
