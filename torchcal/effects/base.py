"""The effect-model interface: one physical effect the geometric model lacks, as a small,
differentiable, batched model with named parameters.

An effect acts in one or both of two places:

* :meth:`Effect.joint_delta`: a correction ``Δq (P, N, dof)`` added to the commanded joint values
  before the kinematics (compliance about a joint axis, backlash, cyclic errors, scale errors);
* :meth:`Effect.position_delta`: a displacement ``Δp (P, N, M, 3)`` of every marker in the robot
  base frame, before the instrument frame is applied (bending, a tilting base, thermal growth);
* :meth:`Effect.point_delta`: a per-row offset ``(P, N, M, 3)`` of the marker points on their own
  links (a tool that differs by row), which the kinematics carry exactly, whatever the geometry;
* :meth:`Effect.frame_delta`: a per-row offset ``(P, N, 6)`` of the instrument frame's parameters (a
  set-up that differs by row), each row's frame carried exactly.

Effects are fitted jointly with the geometry. Their features (gravity wrenches, lever arms,
harmonics of the commands, covariates) depend only on the commanded state and on the geometry
they are computed at, so :meth:`Effect.prepare` computes them once per data set and every
evaluation reuses them. The geometry is ``geometry``: the robot's parameter vector ``(K,)`` the
features are computed at (nominal when not given); the loop passes its geometric fit, because an
unknown marker 10 cm from its guess changes every lever arm by that much.

**Modes.** An effect is a sum of *modes*, each owning some of its parameters (a joint's
backlash, one link's thermal growth, one direction of bending at one joint). A *selectable*
effect is a family whose modes the loop chooses one at a time by cross-validation
(:mod:`torchcal.pipelines.crossval.scores`); the others are tried whole. :meth:`Effect.with_modes` restricts an
effect to some modes.

**Linear form.** :meth:`Effect.linear_basis` gives the effect's columns as a model linear in its
coordinates, at zero: what identifiability and mode selection judge, so that a bilinear effect
(compliance x unknown payload) is never judged at a point where half of its columns vanish.
:meth:`Effect.from_linear` maps fitted linear coordinates back to the effect's parameters.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.effects.session import SessionFindings
from torchcal.params import display_unit

__all__ = ["Effect", "Prepared", "LinearBasis", "TIME_COVARIATES", "PLANNED_COVARIATES"]

# Covariates that count time: a model reading one must never extrapolate it to another day
TIME_COVARIATES = ("t_start_robot", "t_end_robot", "time", "t", "timestamp")
# Kinds of covariate (:attr:`Effect.reads`) a pose plan can choose for every pose it proposes
PLANNED_COVARIATES = ("direction",)


@dataclass
class Prepared:
    """Per-data-set features of an effect (whatever the effect needs; tensors on the robot's device)."""

    features: dict


@dataclass
class LinearBasis:
    """An effect as a model linear in ``L`` coordinates at zero.

    Attributes:
        dq: ``(N, dof, L)`` joint deflection per unit coordinate (rad or m), or None.
        dp: ``(N, M, 3, L)`` robot-base marker displacement per unit coordinate (m), or None.
        groups: per mode (in :meth:`Effect.modes` order), the coordinate columns it owns.
        shared: for a bilinear effect, ``S > 0``: each group is ``[u, v_1 … v_S]`` and the mode's
            column is ``u + Σ s_i v_i`` for the effect's ``S`` shared parameters ``s``
            (:meth:`Effect.shared`), its coefficient the mode's own parameter; 0: linear.
    """

    dq: Tensor | None
    dp: Tensor | None
    groups: list[list[int]]
    shared: int = 0


class Effect(SessionFindings):
    """Base class. Subclasses set ``name`` and implement :meth:`param_info`, :meth:`prepare`, and
    :meth:`joint_delta` and/or :meth:`position_delta`.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot` the effect belongs to.
        joints: joints the effect acts on (default: all actuated joints it applies to).
        geometry: ``(K,)`` robot parameters the features are computed at (default nominal).
    """

    name = "effect"
    description = ""
    selectable = True             # the loop chooses its modes (joints, links, directions) one by one
    supersedes: tuple[str, ...] = ()  # accepted effects whose modes this one takes over
    # effects that say what this one says in fewer, named terms where both pass (a frame's path and
    # the drivers' drift, settling or step): this one wins a round only where it beats them by the rule
    defers_to: tuple[str, ...] = ()
    fallback = False              # a general family, tried in a round only when no physical effect passes
    # what the effect reads beyond the commanded joint values, by kind: "direction" (the approach
    # direction of a joint, ``dir.<joint>`` = ±1, which a pose plan chooses) and "measured" (a
    # temperature, a time or another column only the running robot gives, which no plan chooses)
    reads: tuple[str, ...] = ()

    def __init__(self, robot, joints: list[str] | None = None, geometry: Tensor | None = None):
        self.robot = robot
        known = list(robot.joint_names)
        if joints is not None:
            bad = [j for j in joints if j not in known]
            if bad:
                raise ValueError(f"{self.name}: unknown joint(s) {bad}; the robot's joints are {known}")
        self.joints = list(joints) if joints is not None else self.default_joints()
        g = torch.zeros(robot.n_params, dtype=robot.dtype, device=robot.device) if geometry is None else \
            torch.as_tensor(geometry, dtype=robot.dtype, device=robot.device).detach().clone()
        if g.shape != (robot.n_params,):
            raise ValueError(f"{self.name}: geometry must be the robot's ({robot.n_params},) parameter vector, "
                             f"got shape {tuple(g.shape)}")
        self.geometry = g
        self.theta = torch.zeros(len(self.param_names), dtype=robot.dtype, device=robot.device)
        self.covariate_range: dict[str, tuple[float, float]] = {}
        # a Gaussian prior on the parameters, as weights (m of residual per unit of each), when the
        # loop keeps every mode softly rather than choosing some (None: none)
        self.ridge: Tensor | None = None
        self.ridge_mm: float | None = None  # that prior's σ: the RMS displacement a mode may cause (mm)

    # -- description --------------------------------------------------------------------
    @classmethod
    def plannable(cls) -> bool:
        """Whether a pose plan can serve the effect: everything it reads is a function of the
        commands and of covariates a plan chooses (:data:`PLANNED_COVARIATES`)."""
        return set(cls.reads) <= set(PLANNED_COVARIATES)

    def direction_flips(self) -> list[int]:
        """Per parameter, the index of the joint whose approach direction flips the sign of that
        parameter's column (an offset that follows ``dir.<joint>``), else -1."""
        return [-1] * self.n_params

    def default_joints(self) -> list[str]:
        return [n for n, u in zip(self.robot.joint_names, self.robot.joint_units) if u == "rad"]

    def param_info(self) -> list[tuple[str, str]]:
        """``[(name, unit), …]`` of this effect's parameters (names without the effect prefix)."""
        raise NotImplementedError

    @property
    def param_names(self) -> list[str]:
        return [f"{self.name}.{n}" for n, _ in self.param_info()]

    @property
    def param_units(self) -> list[str]:
        return [u for _, u in self.param_info()]

    @property
    def n_params(self) -> int:
        return len(self.param_info())

    def modes(self) -> list[tuple[str, list[int]]]:
        """``[(label, parameter indices), …]``: the pieces the effect is a sum of. Default: one
        mode per joint when the parameters are named ``<joint>.…``, else one per parameter."""
        out: dict[str, list[int]] = {}
        for i, (n, _) in enumerate(self.param_info()):
            out.setdefault(n.split(".")[0] if n.split(".")[0] in self.robot.joint_names else n, []).append(i)
        return list(out.items())

    def shared(self) -> list[int]:
        """Parameters every mode needs (an unknown payload): free whenever any mode is."""
        return []

    def setup_parameters(self) -> dict[str, str]:
        """This effect's parameters that move an unknown of the set-up rather than the robot: full
        name -> ``"frame"`` (the instrument's frame) or ``"marker"`` (a marker point). Where the data
        cannot tell such a parameter from a robot error, the set-up's is the one kept, as for the
        registration itself (:data:`~torchcal.problems.identifiability.DEFAULT_PREFER`). Default: none."""
        return {}

    def with_modes(self, labels: list[str]) -> "Effect":
        """A copy holding only the modes ``labels`` (default: modes are joints)."""
        keep = [j for j in self.joints if j in set(labels)]
        return self._copy(joints=keep)

    def _copy(self, **changes) -> "Effect":
        kw = dict(self.config())
        joints = changes.pop("joints", self.joints)
        kw.update(changes)
        out = type(self)(self.robot, joints, geometry=self.geometry, **kw)
        out.covariate_range = dict(self.covariate_range)
        if self.ridge is not None and out.param_names == self.param_names:
            out.ridge, out.ridge_mm = self.ridge.clone(), self.ridge_mm
        return out

    def at_geometry(self, geometry: Tensor) -> "Effect":
        """A copy whose features are computed at ``geometry`` (``(K,)`` robot parameters)."""
        out = self._copy()
        out.geometry = torch.as_tensor(geometry, dtype=self.robot.dtype, device=self.robot.device).detach().clone()
        return out

    def proposes(self, labels: list[str]) -> tuple[bool, str]:
        """Whether the modes ``labels`` chosen for this effect say something of their own (a
        family whose chosen modes another effect already covers does not)."""
        return True, ""

    def applicable(self, data) -> tuple[bool, str]:
        """Whether this effect can be fitted on ``data`` (e.g. backlash needs direction
        covariates), with the reason in words when not."""
        return True, ""

    def bind(self, data, min_lever_m: float = 5e-3) -> "Effect":
        """A copy for ``data``: acting only on joints whose motion moves the measured markers
        (median lever over the data at least ``min_lever_m``, m per rad; prismatic joints always
        count), with each covariate's training range recorded. A joint that barely moves the
        markers cannot show an effect; fitting one there only invents values no measurement checks."""
        J = self.robot.joint_jacobian(data.q, self.geometry, check=False)[:, :, :3, :]  # (N, M, 3, dof)
        mk = [self.robot.marker_names.index(m) for m in data.marker_names]
        lever = J[:, mk].norm(dim=-2).amax(1).median(0).values  # (dof,)
        keep = [j for j in self.joints if self.robot.joint_units[self.robot.joint_names.index(j)] == "m"
                or float(lever[self.robot.joint_names.index(j)]) >= min_lever_m]
        out = self._copy(joints=keep)
        out.covariate_range = {c: (float(data.covariates[c].min()), float(data.covariates[c].max()))
                               for c in out.covariates if c in data.covariates}
        return out

    def init_theta(self, data=None) -> Tensor:
        """Start values (zeros: no effect)."""
        return torch.zeros(self.n_params, dtype=self.robot.dtype, device=self.robot.device)

    def bounds(self) -> tuple[Tensor, Tensor]:
        big = torch.full((self.n_params,), float("inf"), dtype=self.robot.dtype, device=self.robot.device)
        return -big, big

    # -- evaluation -----------------------------------------------------------------------
    def prepare(self, q: Tensor, covariates: dict[str, Tensor]) -> Prepared:
        """Features for commands ``q (N, dof)`` and covariates (name -> ``(N,)``)."""
        raise NotImplementedError

    def joint_delta(self, theta: Tensor, prep: Prepared) -> Tensor | None:
        """``theta (P, k) -> Δq (P, N, dof)`` (rad / m), or None when the effect moves no joint."""
        return None

    def position_delta(self, theta: Tensor, prep: Prepared) -> Tensor | None:
        """``theta (P, k) -> Δp (P, N, M, 3)`` robot-base displacement of every robot marker (m),
        or None when the effect moves no point directly."""
        return None

    def point_delta(self, theta: Tensor, prep: Prepared) -> Tensor | None:
        """``theta (P, k) -> (P, N, M, 3)`` offsets of the marker points along their own error
        translations (``<marker>.dx/dy/dz``, m), carried by their links as the points themselves are
        (:meth:`~torchcal.kinematics.fk.ForwardKinematics.positions`'s ``points``); None when the
        effect moves no marker point on its link."""
        return None

    def frame_delta(self, theta: Tensor, prep: Prepared) -> Tensor | None:
        """``theta (P, k) -> (P, N, 6)`` per-row offsets of the instrument frame's parameters
        (``base.x, y, z`` m, ``base.rx, ry, rz`` rad), each row's frame carried exactly
        (:mod:`torchcal.problems.row_frames`); None when the effect does not move the frame."""
        return None

    def _scatter(self, per_joint: Tensor) -> Tensor:
        """``(P, N, len(self.joints)) -> (P, N, dof)`` with zeros for the other joints."""
        idx = torch.tensor([self.robot.joint_names.index(j) for j in self.joints], device=per_joint.device)
        out = per_joint.new_zeros(*per_joint.shape[:-1], self.robot.dof)
        return out.index_copy(-1, idx, per_joint)

    # -- linear form ----------------------------------------------------------------------
    def linear_basis(self, prep: Prepared) -> LinearBasis:
        """The effect's columns at ``theta = 0``, one coordinate per parameter (exact for effects
        linear in their parameters; bilinear ones override this)."""
        k = self.n_params
        E = torch.eye(k, dtype=self.robot.dtype, device=self.robot.device)
        dq = self.joint_delta(E, prep)
        dp = self.position_delta(E, prep)
        groups = [list(cols) for _, cols in self.modes()]
        return LinearBasis(None if dq is None else dq.permute(1, 2, 0), None if dp is None else dp.permute(1, 2, 3, 0),
                           groups)

    def from_linear(self, coef: Tensor) -> Tensor:
        """Parameters ``(k,)`` from fitted linear coordinates ``(L,)`` (the identity here)."""
        return coef.clone()

    def from_bilinear(self, own: Tensor, shared: Tensor) -> Tensor:
        """Parameters ``(k,)`` from each mode's own coefficient and the shared parameters (for a
        bilinear basis, see :class:`LinearBasis`)."""
        return torch.cat([own, shared])

    def signature(self, prep: Prepared, label: str, theta: Tensor) -> dict | None:
        """What a mode's evidence plot shows (see :mod:`torchcal.pipelines.loop.evidence`): ``x (N,)`` the
        physical signature and ``xlabel``; ``fitted (N,)`` the mode's value and ``ylabel``; and
        either ``dof`` (a joint the mode deflects) or ``G (N, M, 3)`` (robot-base displacement per
        unit of the mode's value). None: nothing to plot."""
        return None

    def _joint_signature(self, prep: Prepared, label: str, theta: Tensor, x: Tensor, xlabel: str,
                         ylabel: str) -> dict:
        """A per-joint mode: ``fitted`` is the mode's own ``Δq`` on that joint."""
        j = self.robot.joint_names.index(label)
        keep = torch.zeros_like(theta)
        cols = dict(self.modes())[label]
        keep[cols] = theta[cols]
        d = self.joint_delta(keep[None], prep)[0][:, j]
        return {"x": x, "xlabel": xlabel, "fitted": d, "ylabel": ylabel, "dof": j}

    # -- words ------------------------------------------------------------------------------
    def mode_words(self, label: str) -> str:
        """What a mode is, in words (for reports)."""
        return f"{self.description} at {label}"

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        """One sentence per mode with its fitted size, for the report; ``free`` ``(k,)`` bool:
        parameters the fit identified (the others say nothing and are left out)."""
        th = self.theta if theta is None else theta
        names = [n for n, _ in self.param_info()]
        units = self.param_units
        out = []
        for label, cols in self.modes():
            cols = [i for i in cols if free is None or bool(free[i])]
            if cols:
                vals = ", ".join(f"{names[i]} = {float(th[i]) * display_unit(units[i])[0]:.4g} "
                                 f"{display_unit(units[i])[1]}" for i in cols)
                out.append(f"{self.mode_words(label)}: {vals}")
        return out

    # -- deployment -------------------------------------------------------------------------
    def clamped(self, covariates: dict[str, Tensor]) -> dict[str, Tensor]:
        """Time covariates held inside their training range: a time trend learnt on one day
        says nothing of another, so it must never extrapolate. Every evaluation of a bound
        effect (fit, cross-validation, held-out rows, deployment) reads its covariates through
        this."""
        out = dict(covariates)
        for c, (lo, hi) in self.covariate_range.items():
            if c in out and c in TIME_COVARIATES:
                out[c] = out[c].clamp(lo, hi)
        return out

    def joint_correction(self, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor:
        """``Δq (N, dof)`` for commands ``q`` with the fitted parameters (the hook
        :class:`~torchcal.deploy.model.CalibratedModel` calls before FK)."""
        d = self.joint_delta(self.theta[None], self.prepare(q, self.clamped(covariates or {})))
        return torch.zeros_like(q) if d is None else d[0]

    def position_correction(self, p: Tensor, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor:
        """``p (N, M, 3)`` robot-base marker positions (m) -> displaced, with the fitted
        parameters (the hook :class:`~torchcal.deploy.model.CalibratedModel` calls after FK)."""
        d = self.position_delta(self.theta[None], self.prepare(q, self.clamped(covariates or {})))
        return p if d is None else p + d[0]

    def point_correction(self, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor | None:
        """``(N, M, 3)`` the marker points' offsets on their links (m, :meth:`point_delta`) with the
        fitted parameters, or None (the hook :class:`~torchcal.deploy.model.CalibratedModel` passes
        to the kinematics)."""
        d = self.point_delta(self.theta[None], self.prepare(q, self.clamped(covariates or {})))
        return None if d is None else d[0]

    def frame_correction(self, q: Tensor, covariates: dict[str, Tensor] | None = None) -> Tensor | None:
        """``(N, 6)`` the instrument frame's per-row offsets (:meth:`frame_delta`) with the fitted
        parameters, or None (the hook :class:`~torchcal.deploy.model.CalibratedModel` composes)."""
        d = self.frame_delta(self.theta[None], self.prepare(q, self.clamped(covariates or {})))
        return None if d is None else d[0]

    @property
    def covariates(self) -> list[str]:
        """Covariates the effect reads (every prediction must be given them)."""
        return []

    def state_dict(self) -> dict:
        """What :func:`torchcal.deploy.persist.save` stores: tensors bit-exactly, the rest as JSON."""
        return {"name": self.name, "joints": list(self.joints), "theta": self.theta.detach().clone(),
                "geometry": self.geometry.detach().clone(), "config": self.config(),
                "covariate_range": {k: list(v) for k, v in self.covariate_range.items()}}

    @classmethod
    def from_state_dict(cls, state: dict, robot) -> "Effect":
        geo = state.get("geometry")
        eff = cls(robot, list(state["joints"]), geometry=geo, **dict(state.get("config") or {}))
        eff.theta = torch.as_tensor(state["theta"], dtype=robot.dtype, device=robot.device).clone()
        eff.covariate_range = {k: (float(v[0]), float(v[1])) for k, v in (state.get("covariate_range") or {}).items()}
        return eff

    def config(self) -> dict:
        """Constructor settings beyond ``joints`` and ``geometry`` needed to rebuild the effect."""
        return {}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(joints={self.joints}, n_params={self.n_params})"
