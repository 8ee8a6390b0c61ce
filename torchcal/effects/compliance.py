"""Joint compliance: each joint twists in proportion to the gravity torque about its axis, the
joint-axis special case of :class:`~torchcal.effects.deformation.GravityDeformation` (c in rad/(N m));
and the same under a load logged row by row (:class:`LoadCompliance`)."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import TIME_COVARIATES, Effect, Prepared
from torchcal.effects.deformation import GravityDeformation
from torchcal.effects.gravity import GRAVITY, body_inertials, gravity_features
from torchcal.effects.drivers import ROW
from torchcal.effects.terms import driver_columns
from torchcal.measure.levels import LEVEL_SEP, factor_levels

__all__ = ["JointCompliance", "LoadCompliance", "load_columns"]


class JointCompliance(GravityDeformation):
    """Joint deflection proportional to the gravity torque: ``Δq_j = c_j τ_j(q)`` (``c_j`` in
    rad/(N·m)), the twist modes of :class:`GravityDeformation` on every joint.

    With inertials in the URDF, ``τ`` comes from them plus an unknown payload on the tool link.
    Without usable masses (``lumped=True`` or no inertials), gravity torque is linear in the
    unknown mass moments of the links, so the products compliance × mass moment are identified
    directly (4 per joint and link, most of them dropped again by identifiability).
    """

    name = "joint_compliance"
    description = "joint deflection proportional to the gravity torque (incl. an unknown payload)"
    selectable = True  # joint by joint: a joint that shows no twist gets no compliance
    supersedes = ()

    def __init__(self, robot, joints=None, geometry=None, modes: list[str] | None = None,
                 tool_link: str | None = None, gravity=GRAVITY, lumped: bool | None = None, loads=()):
        self.lumped = (not body_inertials(robot)) if lumped is None else bool(lumped)
        super().__init__(robot, joints, geometry, modes, tool_link, gravity, loads)

    def default_joints(self) -> list[str]:
        return [n for n, u in zip(self.robot.joint_names, self.robot.joint_units) if u == "rad"]

    def _default_mode(self, c: dict) -> bool:
        return c["label"].endswith(".twist")

    def with_modes(self, labels: list[str]) -> "JointCompliance":
        return self._copy(joints=[j for j in self.joints if f"{j}.twist" in set(labels)])

    def config(self) -> dict:
        return {**super().config(), "lumped": self.lumped}

    def applicable(self, data) -> tuple[bool, str]:
        return True, ""

    def proposes(self, labels):
        return True, ""

    # -- lumped form: no inertials --------------------------------------------------------------
    def _lump_links(self) -> list[str]:
        # one lumped body per link that follows an actuated joint (fixed children move with it)
        return [jt.child for jt in self.robot.joints if jt.movable and jt.mimic is None]

    @property
    def has_payload(self) -> bool:
        return not self.lumped and super().has_payload

    def param_info(self):
        if not self.lumped:
            return super().param_info()
        # compliance rad/(N·m) times a mass (kg) or a first mass moment (kg·m): the twist per unit of
        # gravity_features' torque per kg (N·m/kg) or per kg·m (N/kg)
        return [(f"{j}.{l}.{t}", u) for j in self.joints for l in self._lump_links()
                for t, u in (("m", "rad*kg/(N*m)"), ("mx", "rad*kg/N"), ("my", "rad*kg/N"), ("mz", "rad*kg/N"))]

    def modes(self):
        if not self.lumped:
            return super().modes()
        per = 4 * len(self._lump_links())
        return [(f"{j}.twist", list(range(i * per, (i + 1) * per))) for i, j in enumerate(self.joints)]

    def prepare(self, q, covariates):
        if not self.lumped:
            return super().prepare(q, covariates)
        idx = torch.tensor([self.robot.joint_names.index(j) for j in self.joints], device=q.device)
        F = gravity_features(self.robot, q, self._lump_links(), self.gravity)  # (N, L, dof, 4)
        return Prepared({"F": F[:, :, idx, :].permute(0, 2, 1, 3).reshape(q.shape[0], len(self.joints), -1),
                         "q": q[:, idx]})

    def joint_delta(self, theta, prep):
        if not self.lumped:
            return super().joint_delta(theta, prep)
        th = theta.reshape(theta.shape[0], len(self.joints), -1)  # (P, J, 4L)
        return self._scatter(torch.einsum("njf,pjf->pnj", prep.features["F"], th))

    def position_delta(self, theta, prep):
        return None if self.lumped else super().position_delta(theta, prep)

    def linear_basis(self, prep):
        return Effect.linear_basis(self, prep) if self.lumped else super().linear_basis(prep)

    def from_linear(self, coef):
        return coef.clone() if self.lumped else super().from_linear(coef)

    def describe(self, theta=None, free=None):
        if not self.lumped:
            return super().describe(theta, free)
        modes = dict(self.modes())
        return [f"{j} deflects with the gravity torque (lumped link masses: {4 * len(self._lump_links())} "
                "products of compliance and mass moment)" for j in self.joints
                if free is None or bool(free[modes[f"{j}.twist"]].any())]

    def mode_words(self, label: str) -> str:
        return f"{label.split('.')[0]} twists about its axis (joint compliance)"

    def signature(self, prep, label, theta):
        if not self.lumped:
            return super().signature(prep, label, theta)
        j = label.split(".")[0]
        keep = torch.zeros_like(theta)
        cols = dict(self.modes())[label]
        keep[cols] = theta[cols]
        d = self.joint_delta(keep[None], prep)[0][:, self.robot.joint_names.index(j)]
        # no inertials: the gravity torque is itself fitted (lumped mass moments), so there is no
        # signature independent of the fit; plotting against the fitted deflection would make any
        # fit look perfect, so the joint angle stands on the x axis and the report says why
        return {"x": prep.features["q"][:, self.joints.index(j)], "fitted": d, "ylabel": "joint twist [rad]",
                "xlabel": f"{j} angle [rad]", "dof": self.robot.joint_names.index(j), "independent": False,
                "note": "no inertials in the URDF, so the gravity torque is itself fitted: no signature independent "
                        "of the fit; the fitted twist is shown against the joint angle"}

    def torques(self, q, covariates=None, theta: Tensor | None = None) -> Tensor:
        """Gravity torque per effect joint (N·m) at ``q`` with the identified payload, for
        evidence plots (not available in lumped form)."""
        if self.lumped:
            raise ValueError("lumped compliance has no separate torque; plot its Δq instead")
        prep = self.prepare(q, covariates or {})
        th = self.theta if theta is None else theta
        return torch.einsum("ntgb,gb->nt", prep.features["Wt"], self._load(th[None])[0])


def load_columns(covariates: dict) -> list[str]:
    """Columns that may log a load on the tool: every numeric driver column but the times (a payload's
    mass, a part held or not; :func:`~torchcal.effects.terms.driver_columns`), and each level of a text
    column but its first (a load logged by name: each its own mass and centre of mass beyond the first's;
    not the levels the loop reads from a numeric column of codes, whose number is the load's log)."""
    numeric = [c for c in driver_columns(covariates) if c not in TIME_COVARIATES]
    # a column of codes read as levels too (tool_id=2) logs its load by its number already: a load in
    # kg is a quantity, and its levels would only repeat it with four unknowns more per level
    return numeric + [f"{f}{LEVEL_SEP}{lv}" for f, lvs in factor_levels(covariates).items() if f not in covariates
                      for lv in lvs[1:]]


class LoadCompliance(JointCompliance):
    """Joint compliance under a load that changes row by row and is logged: the payload's mass moments
    are ``μ + Σ_c L_c ν_c`` for the columns ``L_c`` that may log a load (:func:`load_columns`: numeric
    columns, and a text column's levels but its first), each ``ν_c`` (mass and first moments per unit
    of the column, or for its level) unknown and shared by every joint, so ``Δq_j = c_j τ_j(q, L)``.

    A robot measured with several payloads (to see its stiffness, or because the cell works so)
    deflects by what each row carries; with one constant unknown payload the deflection of the
    other loads is left over, and a temperature-like drift or a driver family takes it in pieces.
    Offered only where the URDF has inertials and the data a column that may log a load."""

    name = "load_compliance"
    description = "joint deflection proportional to the gravity torque, with a load logged row by row"
    supersedes = ("joint_compliance",)
    reads_load_changes = True

    def applicable(self, data) -> tuple[bool, str]:
        if self.lumped:
            return False, "the URDF has no link inertials: no gravity torque to add a logged load to"
        if not (self.loads or load_columns(data.covariates) or ROW in data.covariates
                or any(c in data.covariates for c in TIME_COVARIATES)):
            return False, "the data has no column that could log a load, nor a row order a load could change along"
        return True, ""

    def waiting(self) -> str | None:
        return None if self.loads else "no column logs a load, and no set-up change has been found yet"

    def given(self, found: list, data, changes: list[str] = ()) -> "LoadCompliance":
        """Also loaded by a step at every step in time or the row order an accepted effect found (a
        set-up changed there: a payload swapped with nothing logged changes the deflection too), and
        at every change of the load the residual shows (``changes``: a payload swapped beside another
        set-up change, whose step the loop found first)."""
        kept = [c for e in found if e.name == self.name for c in e.loads]  # what it carried when accepted
        steps = [s for e in found for s in e.session_steps()]
        new = [c for c in dict.fromkeys([*kept, *steps, *changes]) if c not in self.loads]
        if not new or self.lumped:
            return self
        return JointCompliance.bind(self._copy(loads=self.loads + new), data)

    def bind(self, data, min_lever_m: float = 5e-3) -> "LoadCompliance":
        """A copy loaded by every column of ``data`` that may log a load (unless ``loads`` were given),
        acting on the joints that move the markers."""
        eff = self if self.loads else self._copy(loads=load_columns(data.covariates))
        return JointCompliance.bind(eff, data, min_lever_m)
