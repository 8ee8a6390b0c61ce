"""The deployable model: calibrated kinematics, physical effect models and a learned residual.

:class:`CalibratedModel` predicts where the robot really goes for a command ``q``::

    q_joint = q + Σ_effects effect.joint_correction(q, covariates)      (effects, may be none)
    T_geo   = robot.fk(q_joint, params)                                  (calibrated kinematics)
    T       = T_geo ⊕ residual.predict([q, covariates])                  (learned residual, optional)

Pose errors are 6-vectors ``[dx, dy, dz, droll, dpitch, dyaw]`` with this convention (used by
:func:`pose_error`, :func:`apply_pose_error`, the ELM's training targets and the corrector):

* ``dx, dy, dz`` (m): ``p_meas - p_ref`` in the instrument frame (the frame the poses are in);
* ``droll, dpitch, dyaw`` (rad): the rotation vector ``log(R_refᵀ R_meas)``, i.e. a rotation
  about the *reference* frame's own x, y, z axes. For small errors it equals the roll, pitch and
  yaw of ``R_refᵀ R_meas`` (URDF convention ``Rz Ry Rx``) to first order, without the
  singularities of Euler differences.

So ``T_meas = T_ref ⊕ e`` means ``p = p_ref + e[:3]``, ``R = R_ref exp(e[3:])``. Position-only
errors are the first three entries.

**Effects hook** (:class:`EffectHook`). An effect is any object with

* ``name: str`` (unique within a model);
* ``joint_correction(q, covariates) -> (N, dof)``: added to the commands before FK (rad / m),
  e.g. joint compliance under gravity or a cyclic transmission error; ``q`` is ``(N, dof)``
  commands, ``covariates`` a dict ``name -> (N,)`` tensor (possibly empty);
* ``state_dict() -> dict``: tensors (saved in safetensors) and JSON-serialisable values (saved
  in ``model.json``) that describe it;
* ``from_state_dict(state, robot) -> effect``: a classmethod rebuilding it from that dict;

and optionally

* ``position_correction(p, q, covariates) -> (N, M, 3)``: a map of the marker positions in the
  *robot base* frame (m), applied after FK and before the instrument (base) frame, for effects
  that move points rather than joints (thermal expansion of the links); orientations are left
  as they are;
* ``point_correction(q, covariates) -> (N, M, 3) | None``: each row's marker points moved on their
  links along their own error translations (m; a tool that differs by row), carried by the
  kinematics exactly as the marker points themselves are;
* ``frame_correction(q, covariates) -> (N, 6) | None``: each row's offsets of the instrument frame's
  parameters (``base.x..rz``; a set-up that differs by row), composed exactly;
* ``covariates: list[str]``: the covariates it needs (they become required inputs of the model).

A class is made loadable by :func:`torchcal.effects.register_effect` (the one registry,
:mod:`torchcal.effects.registry`; the saved model names the registered type, so loading never
imports code named by a file).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from torchcal.elm import ELM
from torchcal.kinematics.transforms import homogeneous, so3_exp, so3_log
from torchcal.kinematics.slots import BASE_NAMES
from torchcal.params import ParamSet
from torchcal.measure.levels import LEVEL_SEP, code_indicator

__all__ = ["CalibratedModel", "EffectHook", "pose_error", "apply_pose_error", "ERROR_NAMES"]

ERROR_NAMES = ("dx", "dy", "dz", "droll", "dpitch", "dyaw")
"""Column names of a 6-D pose error (m, m, m, rad, rad, rad); see the module docstring."""


@runtime_checkable
class EffectHook(Protocol):
    """What :class:`CalibratedModel` needs from a physical effect model (see the module
    docstring; ``position_correction``, ``point_correction``, ``frame_correction`` and ``covariates``
    are optional)."""

    name: str

    def joint_correction(self, q: Tensor, covariates: dict[str, Tensor] | None) -> Tensor: ...

    def state_dict(self) -> dict: ...

    @classmethod
    def from_state_dict(cls, state: dict, robot) -> "EffectHook": ...


def pose_error(T_ref: Tensor, T_meas: Tensor) -> Tensor:
    """``(..., 4, 4), (..., 4, 4) -> (..., 6)`` error ``[p_meas - p_ref, log(R_refᵀ R_meas)]``
    (m, rad); ``(..., 3)`` positions give ``(..., 3)``."""
    if T_ref.shape[-2:] != (4, 4):
        return T_meas - T_ref
    dp = T_meas[..., :3, 3] - T_ref[..., :3, 3]
    dr = so3_log(T_ref[..., :3, :3].transpose(-1, -2) @ T_meas[..., :3, :3])
    return torch.cat([dp, dr], -1)


def apply_pose_error(T_ref: Tensor, e: Tensor) -> Tensor:
    """``T_ref ⊕ e``: ``p = p_ref + e[:3]``, ``R = R_ref exp(e[3:])``. ``T_ref (..., 4, 4)`` with
    ``e (..., 6)`` (or ``(..., 3)``: position only), or positions ``(..., 3)`` with ``e (..., 3)``.
    ``T_ref ⊕ (-e)`` undoes ``⊕ e`` to first order (exactly for the position)."""
    if T_ref.shape[-2:] != (4, 4):
        return T_ref + e[..., :3]
    T = T_ref.clone()
    T[..., :3, 3] = T_ref[..., :3, 3] + e[..., :3]
    if e.shape[-1] == 6:
        T[..., :3, :3] = T_ref[..., :3, :3] @ so3_exp(e[..., 3:])
    return T


class CalibratedModel:
    """Calibrated kinematics + effect models + a learned residual, ready to predict and save.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot` (built from a URDF, so that the model can be
            saved with its robot description).
        params: identified parameters (a ``ParamSet`` for this robot; ``robot.params()`` = the
            nominal model, seed 002's model-free use).
        effects: effect models (see the module docstring); their joint corrections are all
            evaluated at the commanded ``q`` and summed; default none.
        residual: an :class:`~torchcal.elm.model.ELM` predicting the pose error left after the
            kinematics and effects, from ``[q, covariates]``; ``n_outputs`` 6 (pose error) or 3
            (position error); ``None`` for none.
        marker: the marker the residual (and the corrector) is about (default the first).
        covariates: names of the extra ELM inputs, in column order after ``q`` (e.g.
            ``["temperature"]``). These and the effects' own ``covariates`` make
            :attr:`required_covariates`, which every prediction must be given.
        meta: free JSON-serialisable metadata (training data summary, metrics, units ...).
    """

    def __init__(self, robot, params: ParamSet | None = None, effects: list | None = None,
                 residual: ELM | None = None, marker: str | None = None,
                 covariates: list[str] | None = None, meta: dict | None = None):
        self.robot = robot
        if params is None:
            params = robot.params()
        if not isinstance(params, ParamSet):
            raise TypeError(f"params must be a ParamSet (robot.params() or a CalibrationResult's .params), "
                            f"got {type(params).__name__}")
        if params.names != robot.param_names:
            raise ValueError("params were made for another robot (parameter names differ); use robot.params()")
        self.params = params
        self.effects = list(effects or [])
        for e in self.effects:
            if not isinstance(e, EffectHook):
                raise TypeError(f"effect {e!r} lacks name / joint_correction / state_dict / from_state_dict "
                                "(see torchcal.deploy.model.EffectHook)")
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"effect names must be unique, got {names}")
        self.marker = marker if marker is not None else robot.marker_names[0]
        if self.marker not in robot.marker_names:
            raise ValueError(f"unknown marker {self.marker!r}; the robot measures {robot.marker_names}")
        self.marker_index = robot.marker_names.index(self.marker)
        self.covariates = list(covariates or [])
        extra = [c for e in self.effects for c in getattr(e, "covariates", None) or [] if c not in self.covariates]
        self.required_covariates = self.covariates + list(dict.fromkeys(extra))
        base = [params.index(n) for n in BASE_NAMES]
        self._base_index = torch.tensor(base, device=params.values.device)
        if residual is not None:
            if not residual.is_fitted:
                raise ValueError("the residual ELM is not fitted; call fit() first")
            want = robot.dof + len(self.covariates)
            if residual.n_features_in_ != want:
                raise ValueError(f"the residual ELM takes {residual.n_features_in_} inputs but q ({robot.dof}) "
                                 f"+ covariates {self.covariates} make {want}")
            if residual.n_outputs_ not in (3, 6):
                raise ValueError(f"the residual ELM must predict 3 (position) or 6 (pose) errors, "
                                 f"got {residual.n_outputs_}")
        self.residual = residual
        self.meta = dict(meta or {})

    def __repr__(self) -> str:
        return (f"CalibratedModel({self.robot.name!r}, marker={self.marker!r}, effects={[e.name for e in self.effects]}, "
                f"residual={self.residual!r}, covariates={self.covariates})")

    # -- inputs ---------------------------------------------------------------------------
    def _covariates(self, covariates, n: int) -> dict[str, Tensor]:
        """Normalise covariates to ``name -> (N,)`` tensors (a dict, or an ``(N, C)`` matrix in
        :attr:`required_covariates` order); checks that every required covariate is present."""
        req = self.required_covariates
        if covariates is None:
            if req:
                raise ValueError(f"this model needs covariates {req}; pass covariates={{name: (N,) values}}")
            return {}
        dt = dict(dtype=self.robot.dtype, device=self.robot.device)
        if isinstance(covariates, dict):
            out = {k: torch.as_tensor(v, **dt).reshape(-1) for k, v in covariates.items()}
        else:
            c = torch.as_tensor(covariates, **dt)
            c = c[:, None] if c.ndim == 1 else c
            if c.ndim != 2 or c.shape[1] != len(req):
                raise ValueError(f"covariates must be (N, {len(req)}) in the order {req}, or a dict; "
                                 f"got shape {tuple(c.shape)}")
            out = {k: c[:, i] for i, k in enumerate(req)}
        for k in req:  # a level of a column of codes (tool_id=2) from the numeric column itself (tool_id)
            col, _, lv = k.partition(LEVEL_SEP)
            if k not in out and lv and col in out:
                out[k] = code_indicator(out[col], lv)
        missing = [k for k in req if k not in out]
        if missing:
            raise ValueError(f"missing covariate(s) {missing}; this model needs {req}"
                             + ("; a level <column>=<code> of a numeric column may come from the column <column>"
                                if any(LEVEL_SEP in k for k in missing) else ""))
        for k, v in out.items():
            if v.shape[0] not in (1, n):
                raise ValueError(f"covariate {k!r} has {v.shape[0]} values for {n} commands")
            out[k] = v.expand(n)
        return out

    def features(self, q, covariates=None) -> Tensor:
        """``(N, dof + C)`` ELM inputs: commands (rad / m) then :attr:`covariates` in order."""
        q = self.robot.check_q(q)
        cov = self._covariates(covariates, q.shape[0])
        if not self.covariates:
            return q
        return torch.cat([q] + [cov[k][:, None] for k in self.covariates], 1)

    # -- prediction ----------------------------------------------------------------------------
    def joint_values(self, q, covariates=None) -> Tensor:
        """``(N, dof)`` commands -> joint values: ``q + Σ effect.joint_correction(q, covariates)``
        (every effect sees the commands, not another effect's output)."""
        q = self.robot.check_q(q)
        cov = self._covariates(covariates, q.shape[0])
        out = q
        for e in self.effects:
            out = out + e.joint_correction(q, cov)
        return out

    def geometric_pose(self, q, covariates=None) -> Tensor:
        """``(N, M, 4, 4)``: calibrated kinematics with the effects, without the learned residual
        (instrument frame, m)."""
        q = self.robot.check_q(q)
        qj = self.joint_values(q, covariates)
        cov = self._covariates(covariates, q.shape[0])
        moved = [d for d in (e.point_correction(q, cov) for e in self.effects if hasattr(e, "point_correction"))
                 if d is not None]
        points = sum(moved[1:], moved[0]) if moved else None
        frames = [d for d in (e.frame_correction(q, cov) for e in self.effects if hasattr(e, "frame_correction"))
                  if d is not None]
        movers = [e for e in self.effects if hasattr(e, "position_correction")]
        if not movers and points is None and not frames:
            return self.robot.fk(qj, self.params.values, check=False)
        # position effects act in the robot base frame: FK without the base, map, then the base
        v = self.params.values.clone()
        b = v[self._base_index].clone()
        v[self._base_index] = 0
        R, p = self.robot.fk_rt(qj, v, check=False, points=points)
        for e in movers:
            p = e.position_correction(p, q, cov)
        T = homogeneous(R, p)
        if frames:  # each row's instrument frame: the base parameters plus the row's offsets
            b = b + sum(frames[1:], frames[0])
            return homogeneous(so3_exp(b[:, 3:]), b[:, :3])[:, None] @ T
        return homogeneous(so3_exp(b[3:]), b[:3]) @ T

    def predict_error(self, q, covariates=None) -> Tensor:
        """The residual ELM's predicted pose error at commands ``q``: ``(N, 6)`` (or ``(N, 3)``)
        ``[dx, dy, dz, droll, dpitch, dyaw]`` (m, rad; see the module docstring); zeros when the
        model has no residual."""
        X = self.features(q, covariates)
        if self.residual is None:
            return torch.zeros(X.shape[0], 6, dtype=self.robot.dtype, device=self.robot.device)
        return self.residual.predict(X)

    def predict_pose(self, q, covariates=None) -> Tensor:
        """Where the robot goes for commands ``q (N, dof)`` (rad / m): ``(N, M, 4, 4)`` poses of
        every marker (m) in the instrument frame; the residual is added to :attr:`marker` only."""
        q = self.robot.check_q(q)
        T = self.geometric_pose(q, covariates)
        if self.residual is None:
            return T
        T = T.clone()
        m = self.marker_index
        T[:, m] = apply_pose_error(T[:, m], self.predict_error(q, covariates))
        return T
