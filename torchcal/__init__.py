"""torchcal: robot calibration on torch tensors.

Robot model -> measurement model -> problem -> solver -> result/report:
:class:`Robot` (batched, differentiable kinematics with error parameters),
:class:`torchcal.measure.observations.Observations` (what was measured, as residuals),
:class:`torchcal.problems.calibration.CalibrationProblem`,
:mod:`torchcal.optim` (one interface for gradient and swarm solvers), :func:`calibrate`.
"""
from torchcal import environment as _environment  # first: it checks MPLBACKEND before matplotlib is imported
from torchcal.deploy.correct import Corrector
from torchcal.elm import ELM, tune_elm
from torchcal.deploy.model import CalibratedModel
from torchcal.deploy.persist import load, save
from torchcal.kinematics import robots  # the shipped robots: torchcal.robots.shipped('ur5e')
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.tree import Marker
from torchcal.measure.data import Measurements
from torchcal.measure.io import load_measurements
from torchcal.params import ParamSet
from torchcal.pipelines.calibrate import calibrate
from torchcal.pipelines.calibration_result import CalibrationResult
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.pipelines.fleet.result import FleetResult
from torchcal.pipelines.loop.run import run_loop
from torchcal.pipelines.plan.run import Plan, plan_poses
from torchcal.threads import get_threads, set_threads
from torchcal.version import __version__
__all__ = ["Robot", "ParamSet", "Marker", "Measurements", "load_measurements", "calibrate",
           "CalibrationResult", "run_loop", "CalibratedModel", "ELM", "tune_elm", "Corrector", "save", "load",
           "plan_poses", "Plan", "calibrate_fleet", "FleetResult", "robots", "set_threads", "get_threads",
           "__version__"]
