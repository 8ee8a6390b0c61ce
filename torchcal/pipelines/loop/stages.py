"""A model's stage in the loop measured on data: error statistics (mm) overall, per marker and per
observation kind, the residual matrix (m), and the inputs the residual ELM reads."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from torchcal.measure.data import Measurements
from torchcal.measure.details import error_details
from torchcal.measure.observations import KIND_NAMES
from torchcal.measure.records import ErrorDetails, ErrorStats, Stage, StageErrors
from torchcal.measure.setup import Setup
from torchcal.measure.stats import angle_stats, error_stats, errors_by_marker
from torchcal.params import ParamSet
from torchcal.pipelines.crossval.models import Context, observation_model

__all__ = ["StageBook", "elm_covariates", "elm_inputs", "residual_matrix", "stage_details", "stage_stats"]


@dataclass
class StageBook:
    """The stages of one loop run as they are added, each measured on the training and held-out
    rows (:class:`~torchcal.measure.records.Stage`), with the errors its figures plot."""
    robot: object
    train: Measurements
    test: Measurements | None
    setup: Setup | None = None
    rot_weight: float | None = None
    stages: list[Stage] = field(default_factory=list)
    errors: dict[str, StageErrors] = field(default_factory=dict)

    def add(self, name: str, k: float, params: ParamSet, effects: list, elm=None, cv: float | None = None,
            **extra) -> Stage:
        """Measure a model (``k`` parameters, ``cv``: its cross-validated RMSE, mm) and add its stage."""
        st_tr, e_tr = stage_details(self.robot, params, effects, self.train, elm, self.setup, self.rot_weight)
        st_te, e_te = stage_details(self.robot, params, effects, self.test, elm, self.setup, self.rot_weight)
        s = Stage(name, int(round(k)), st_tr, st_te, cv_rmse_mm=cv, **extra)
        self.stages.append(s)
        self.errors[name] = StageErrors(e_tr, e_te)
        return s


# ----------------------------------------------------------------------------- statistics
def stage_stats(robot, params: ParamSet, effects: list, data: Measurements | None, elm=None,
                setup: Setup | None = None, rot_weight: float | None = None) -> tuple[ErrorStats | None, Tensor]:
    """Error statistics (mm), overall and per marker, and the per-observation errors (m) of a
    model on ``data`` (``setup``: the planes and fixed points, ``LoopResult.setup``). An
    observation's error is the Euclidean norm of what it measured: a plane contact's signed
    distance, a partial position's measured axes. With ``rot_weight`` (m/rad) the measured
    orientations' angle errors (mrad) are in ``orientation``, apart from the positions'."""
    st, d = stage_details(robot, params, effects, data, elm, setup, rot_weight)
    return st, d.e


def stage_details(robot, params: ParamSet, effects: list, data: Measurements | None, elm=None,
                  setup: Setup | None = None, rot_weight: float | None = None) -> tuple[ErrorStats | None, ErrorDetails]:
    """:func:`stage_stats` and the error details a figure needs (:func:`~torchcal.measure.details.error_details`)."""
    if data is None or len(data) == 0:
        z = torch.zeros(0)
        return None, ErrorDetails(e=z, xyz=z.reshape(0, 3), dist=z)
    prob = observation_model(Context(robot, data, [], None, 1.0, setup, rot_weight), params, effects, data)
    r = prob.residual_vectors(params.values[None])[0]
    where = prob.obs.is_position
    e3 = r[where]
    if elm is not None:  # the ELM is only fitted on full positions, whose order is data.seen's
        left = (residual_matrix(robot, params, effects, data, setup) - elm.predict(elm_inputs(data)))
        e3 = -left.reshape(len(data), -1, 3)[data.seen]
    obs = prob.obs.view(where)
    d = error_details(robot, params.values[: robot.n_params], data, e3, obs)
    e = d.e
    out = errors_by_marker(e, obs.data_marker, data.marker_names)
    kinds = torch.unique(obs.kind).tolist()
    if len(kinds) > 1 or kinds != [0] or not bool(obs.mask.all()):
        out = replace(out, per_kind={KIND_NAMES[k]: error_stats(e[obs.kind == k]) for k in kinds})
    if prob.obs.has_orientation:
        out = replace(out, orientation=angle_stats(prob.obs.angle_errors(r)))
    return out, d


def residual_matrix(robot, params: ParamSet, effects: list, data: Measurements, setup: Setup | None = None) -> Tensor:
    """``(N, 3M)`` measured − model position per row (NaN where a marker's full position was not
    measured)."""
    prob = observation_model(Context(robot, data, [], None, 1.0, setup), params, effects, data)
    e3 = prob.residual_vectors(params.values[None])[0]
    full = prob.obs.full_positions
    out = torch.full((len(data), len(data.marker_names), 3), float("nan"), dtype=e3.dtype, device=e3.device)
    out[prob.obs.rows[full], prob.obs.data_marker[full]] = -e3[full]
    return out.reshape(len(data), -1)


def elm_covariates(data: Measurements) -> list[str]:
    """Covariates the residual ELM reads after the commands: temperatures and directions."""
    return [k for k in sorted(data.covariates) if k.startswith(("temp", "dir."))]


def elm_inputs(data: Measurements) -> Tensor:
    return torch.cat([data.q] + [data.covariates[k][:, None] for k in elm_covariates(data)], 1)
