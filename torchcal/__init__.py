"""torchcal: robot calibration on torch tensors.

Robot model -> measurement model -> problem -> solver -> result/report:
:class:`Robot` (batched, differentiable kinematics with error parameters),
:mod:`torchcal.measurement` (residual blocks), :class:`torchcal.problem.CalibrationProblem`,
:mod:`torchcal.optim` (one interface for gradient and swarm solvers), :func:`calibrate`.
"""
from .calibrate import CalibrationResult, calibrate
from .correct import Corrector
from .elm import ELM, tune_elm
from .fleet import FleetResult, calibrate_fleet
from .io import Measurements, load_measurements
from .loop import run_loop
from .model import CalibratedModel
from .params import ParamSet
from .persist import load, save
from .plan import Plan, plan_poses
from .robot import Robot
from .tree import Marker

__version__ = "0.1.0"
__all__ = ["Robot", "ParamSet", "Marker", "Measurements", "load_measurements", "calibrate",
           "CalibrationResult", "run_loop", "CalibratedModel", "ELM", "tune_elm", "Corrector", "save", "load",
           "plan_poses", "Plan", "calibrate_fleet", "FleetResult", "__version__"]
