"""Any parameter, any driver: a general family in which any parameter of the identified model
varies with any driver, in any of a few shapes.

Real cells hold errors no catalogue lists, and they share one form: *some parameter of the model
changes with some driver*. A joint re-mastered mid-session is a zero offset stepping with time; a
tracker that settles is the instrument frame drifting with time; a linear axis whose carriage
pitches along its travel is a joint origin following that joint's position; a tool swapped between
rows is a marker point with one value per tool; a set-up changed per session moves the instrument
frame, one rigid motion per level; a gear that stiffens under load is a zero offset
following the gravity torque piecewise. This family holds them all::

    Δθ_p(row) = Σ_t c_t f_t(driver_t(row))

* **parameters** ``p``: each joint's zero offset and origin (translations and turns), the
  instrument (base) frame, each marker point;
* **drivers** (:mod:`torchcal.effects.drivers`): each joint's position (prismatic ones in m), the
  gravity torque at each joint, time or the row order, each numeric covariate, each text column;
* **shapes** (:mod:`torchcal.effects.shapes`): linear, smooth (quadratic spline), periodic
  (harmonics of an angle), a step at an unknown time or row, a window (a change and its return:
  a tool swapped for a while), a settling from the session's start, a cycle in time,
  piecewise-linear, one value per level.

A zero offset acts as ``Δq`` on its joint, exactly; a marker point's coordinate moves the point on
its link, exactly too (:meth:`point_delta`: the kinematics carry each row's point, so a tool
centimetres longer turns with the flange at whatever geometry the fit reaches); every other
parameter acts through its column of the geometric Jacobian at the fitted geometry (a marker
displacement, first order in ``Δθ``, which is micro-radians to millimetres). Joint drivers pair
with the parameters of joints within :data:`~torchcal.effects.terms.REACH` of them along the chain;
time, row, covariates and text columns pair with every parameter.

The loop tries the family last in a round (:attr:`Effect.fallback`): it takes only what no
catalogued effect explains. Its space is large, so the loop screens each (parameter, driver) pair
with low-order shapes first (:mod:`torchcal.pipelines.loop.screen`), expands the pairs that
explain something into every shape, and selects single terms by the cross-validated rule at the
Bonferroni threshold of the whole space searched (:attr:`n_searched`).
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.base import Effect, LinearBasis, Prepared
from torchcal.effects.drivers import ROW, driver_kind, driver_values, gravity_torques, list_drivers
from torchcal.effects.gravity import body_inertials, row_payload
from torchcal.effects.anydriver_space import RIGID_BREAKS, rigid
from torchcal.effects.shapes import PERIODIC, WINDOW, cycle_label, screen_tags, shape_column
from torchcal.effects.terms import _neighbours
from torchcal.kinematics.slots import BASE_NAMES
from torchcal.effects import anydriver_evidence as evidence
from torchcal.effects import anydriver_words as words
from torchcal.measure.levels import LEVEL_SEP, factor_levels

__all__ = ["ParameterDrivers", "MAX_STEPS"]

MAX_STEPS = 8  # steps, settlings and knees offered per (parameter, driver) pair: the best by the screening


def _levels(tag: str) -> bool:
    return tag.startswith("lvl=")


class ParameterDrivers(Effect):
    """Any model parameter varying with any driver (module docstring).

    Args:
        terms: ``[(parameter, driver, shape), …]`` (default: none; :meth:`bind` lists the pairs
            and :meth:`expanded` their shapes).
        ranges: driver -> ``(mean, half range)`` of its training values (set by :meth:`bind`).
        n_searched: columns of the whole space the selection searched (for its threshold).
    """

    name = "parameter_drivers"
    description = "a model parameter that varies with a driver (a joint, torque, time, row, covariate or text column)"
    reads = ("measured",)
    selectable = True
    fallback = True
    screened = True  # the loop screens its pairs before expanding them (pipelines.loop.screen)

    def __init__(self, robot, joints=None, geometry=None, terms: list | None = None, ranges: dict | None = None,
                 n_searched: int = 0, payload: list | None = None, payload_link: str | None = None,
                 loads: dict | None = None):
        self.terms = [tuple(t) for t in terms or []]
        # a payload an accepted effect fitted (mass moments, kg and kg·m), in every gravity torque, and
        # the loads it found logged row by row (load -> mass moments per unit of it): a stiffness that
        # changes with the torque it carries sees what each row carries
        self.payload = None if payload is None else [float(v) for v in payload]
        self.payload_link = payload_link
        self.loads = {str(c): [float(v) for v in nu] for c, nu in (loads or {}).items()}
        self.ranges = {k: tuple(v) for k, v in (ranges or {}).items()}
        self.n_searched = int(n_searched)
        super().__init__(robot, joints, geometry)

    def default_joints(self) -> list[str]:
        return list(self.robot.joint_names)

    def config(self) -> dict:
        return {"terms": [list(t) for t in self.terms], "ranges": {k: list(v) for k, v in self.ranges.items()},
                "n_searched": self.n_searched, "payload": self.payload, "payload_link": self.payload_link,
                **({"loads": self.loads} if self.loads else {})}

    def torques(self, q: Tensor, covariates: dict) -> Tensor:
        """``(N, dof)`` the gravity torque drivers at ``q`` (URDF inertials, the fitted payload and the
        loads logged in ``covariates``)."""
        payload = None if self.payload is None else row_payload(self.payload, self.loads, covariates, q)
        return gravity_torques(self.robot, q, self.geometry, payload, self.payload_link)

    def with_payload(self, payload: list[float], link: str, data, loads: dict | None = None) -> "ParameterDrivers":
        """A copy whose torque drivers include a fitted payload and the ``loads`` logged row by row
        (load -> its mass moments per unit), their ranges taken again on ``data``."""
        out = self._copy(payload=list(payload), payload_link=link, loads=dict(loads or {}))
        tq = out.torques(data.q, data.covariates)
        for d in out.ranges:
            if d.startswith("torque:"):
                x = tq[:, self.robot.joint_names.index(d.split(":", 1)[1])]
                out.ranges[d] = (float(x.mean()), float((x.max() - x.min()) / 2))
        return out

    # -- the space ---------------------------------------------------------------------
    def _offset_params(self) -> dict[str, str]:
        """Zero-offset parameter name -> its joint."""
        out = {}
        for jt in self.robot.joints:
            if jt.name in self.robot.joint_names:
                out[jt.offset_name or f"{jt.name}.offset"] = jt.name
        return out

    def parameters(self, markers: list[str]) -> dict[str, str | None]:
        """Parameter -> the joint it belongs to (None: the instrument frame or a marker point):
        the effect joints' zero offsets and origins, the base frame, the points of ``markers``."""
        names = set(self.robot.param_names)
        out: dict[str, str | None] = {n: None for n in self.robot.param_names if n.startswith("base.")}
        offs = {j: p for p, j in self._offset_params().items()}
        for j in self.joints:
            if offs.get(j) in names:
                out[offs[j]] = j
            out.update({f"{j}.{a}": j for a in ("dx", "dy", "dz", "droll", "dpitch", "dyaw") if f"{j}.{a}" in names})
        for m in markers:
            out.update({f"{m}.{a}": None for a in ("dx", "dy", "dz") if f"{m}.{a}" in names})
        return out

    def pairs(self, params: dict[str, str | None], drivers: list[str]) -> list[tuple[str, str]]:
        """(parameter, driver) pairs: joint drivers with the parameters of joints near them."""
        near = _neighbours(self.robot)
        out = []
        for d in drivers:
            kind = driver_kind(d)
            for p, j in params.items():
                if kind in ("q", "torque"):
                    if j is None or j not in near.get(d.split(":", 1)[1], []):
                        continue
                out.append((p, d))
        return out

    def bind(self, data, min_lever_m: float = 5e-3) -> "ParameterDrivers":
        """A copy for ``data``: joints that move the markers, the training range of every driver,
        and as terms the screening shapes of every (parameter, driver) pair
        (:func:`~torchcal.effects.shapes.screen_tags`)."""
        moved = Effect.bind(self, data, min_lever_m)
        torques = bool(body_inertials(self.robot)) if self.robot.urdf_text else False
        drivers = list_drivers(self.robot, moved.joints, data.covariates, torques)
        out = type(self)(self.robot, moved.joints, geometry=self.geometry)
        tq = out.torques(data.q, data.covariates) if torques else None
        for d in drivers:
            if driver_kind(d) != "level":
                x = driver_values(self.robot, d, data.q, data.covariates, tq)
                x = x[torch.isfinite(x)]
                out.ranges[d] = (float(x.mean()), float((x.max() - x.min()) / 2))
        units = dict(zip(self.robot.joint_names, self.robot.joint_units))
        levels = factor_levels(data.covariates)
        terms = []
        for p, d in out.pairs(out.parameters(list(data.marker_names)), drivers):
            if driver_kind(d) == "level":
                f = d.split(":", 1)[1]
                terms += [(p, d, f"lvl={lv}") for lv in levels[f][1:]]  # the first level is the baseline
            else:
                rev = driver_kind(d) == "q" and units[d.split(":", 1)[1]] == "rad"
                terms += [(p, d, t) for t in screen_tags(driver_kind(d), rev)]
        out.terms = terms
        out.theta = torch.zeros(out.n_params, dtype=self.robot.dtype, device=self.robot.device)
        out.n_searched = len(terms)
        out.covariate_range = {c: (float(data.covariates[c].min()), float(data.covariates[c].max()))
                               for c in out.covariates if c in data.covariates}
        return out

    # -- the effect's interface --------------------------------------------------------
    @property
    def covariates(self) -> list[str]:
        out = []
        for _, d, t in self.terms:
            k = driver_kind(d)
            if k == "level":
                out.append(f"{d.split(':', 1)[1]}{LEVEL_SEP}{t[4:]}")
            elif k in ("time", "cov"):
                out.append(d.split(":", 1)[1])
            elif k == "row":
                out.append(d)
        if self.loads and any(driver_kind(d) == "torque" for _, d, _ in self.terms):
            out += [c.split("~", 1)[0] for c in self.loads]  # the load each row carries
        return list(dict.fromkeys(out))

    def param_info(self):
        units = dict(zip(self.robot.param_names, self.robot.param_units))
        return [(f"{p}~{d}~{t}", words.coef_unit(units[p], self.robot, d, t)) for p, d, t in self.terms]

    def _label(self, p: str, d: str, t: str) -> str:
        """A term's mode: one per term; a text column's levels together, and for a rigid thing all its
        coordinates together too, per level or per step: a marker point's three (a tool is a point,
        whatever frame its link turns), the instrument frame's six (a set-up moved, per level or
        mid-session, is one rigid motion, whichever of its coordinates the geometry happens to show)."""
        m = rigid(p, self.robot.marker_names)
        whole = "base.frame" if m == "base" else f"{m}.point"
        shape = cycle_label(t) if t.startswith(PERIODIC) else t  # a cycle is one finding, whatever its phase
        if not _levels(t):
            return f"{whole}~{d}~{shape}" if m is not None and t.startswith(RIGID_BREAKS) else f"{p}~{d}~{shape}"
        return f"{p}~{d}~levels" if m is None else f"{whole}~{d}~levels"

    def session_steps(self) -> list[str]:
        return list(dict.fromkeys(f"{d if d == ROW else d.split(':', 1)[1]}~{t}" for _, d, t in self.terms
                                  if driver_kind(d) in ("row", "time") and t.startswith(("step", WINDOW))))

    def with_break(self, old: str, new: str) -> "ParameterDrivers":
        col, _, tag = old.partition("~")
        moved = new.partition("~")[2]
        terms = [(p, d, moved if t == tag and driver_kind(d) in ("row", "time")
                  and (d if d == ROW else d.split(":", 1)[1]) == col else t) for p, d, t in self.terms]
        return self._carried(self._copy(terms=terms)) if terms != self.terms else self

    def setup_parameters(self) -> dict[str, str]:
        names = self.param_names
        out = {}
        for i, (p, _, _) in enumerate(self.terms):
            m = rigid(p, self.robot.marker_names)
            if m is not None:
                out[names[i]] = "frame" if m == "base" else "marker"
        return out

    def modes(self):
        out: dict[str, list[int]] = {}
        for i, (p, d, t) in enumerate(self.terms):
            out.setdefault(self._label(p, d, t), []).append(i)
        return list(out.items())

    def with_modes(self, labels: list[str]) -> "ParameterDrivers":
        keep = set(labels)
        return self._copy(terms=[(p, d, t) for p, d, t in self.terms if self._label(p, d, t) in keep])

    def _copy(self, **changes) -> "ParameterDrivers":
        if "joints" in changes and "terms" not in changes:
            changes["terms"] = list(self.terms)
        return super()._copy(**changes)

    def applicable(self, data) -> tuple[bool, str]:
        return True, ""

    def proposes(self, labels: list[str]) -> tuple[bool, str]:
        """Nothing of its own when every chosen term is a joint's zero following that joint's own
        gravity torque linearly: that is joint compliance, which the catalogue names."""
        offs = self._offset_params()
        own = [p for p, d, t in (lab.split("~") for lab in labels) if t == "lin" and d == f"torque:{offs.get(p)}"]
        if labels and len(own) == len(labels):
            return False, "its terms are joint compliance (a zero linear in its own torque): the catalogue's to name"
        return True, ""

    def clamped(self, covariates: dict[str, Tensor]) -> dict[str, Tensor]:
        """Time, and the row order, held inside their training range: a session's trend says
        nothing of rows beyond it."""
        out = super().clamped(covariates)
        if ROW in out and ROW in self.covariate_range:
            out[ROW] = out[ROW].clamp(*self.covariate_range[ROW])
        return out

    def _column(self, d: str, t: str, q: Tensor, covariates: dict, tq: Tensor | None) -> Tensor:
        if _levels(t):
            c = covariates.get(f"{d.split(':', 1)[1]}{LEVEL_SEP}{t[4:]}")
            # a level the rows never show reads 0 there; an unrecorded one (NaN) counts as the baseline
            return q.new_zeros(q.shape[0]) if c is None else torch.nan_to_num(c.to(q), nan=0.0)
        x = driver_values(self.robot, d, q, covariates, tq)
        mean, half = self.ranges.get(d, (0.0, 1.0))
        return shape_column(t, x, mean, half)

    def prepare(self, q, covariates):
        tq = self.torques(q, covariates) if any(d.startswith("torque:") for _, d, _ in self.terms) else None
        cols = [self._column(d, t, q, covariates, tq) for _, d, t in self.terms]
        F = torch.stack(cols, 1) if cols else q.new_zeros(q.shape[0], 0)
        offs = self._offset_params()
        is_q = [p in offs for p, _, _ in self.terms]
        target = torch.tensor([self.robot.joint_names.index(offs[p]) if p in offs else 0 for p, _, _ in self.terms],
                              dtype=torch.long, device=q.device)
        pos = [i for i, b in enumerate(is_q) if not b]
        # a marker point's coordinate moves the point on its link, a base coordinate the instrument
        # frame (both exact, whatever the geometry); any other parameter displaces the markers through
        # its column at the effect's geometry
        mk = {f"{m}.{a}": 3 * i + j for i, m in enumerate(self.robot.marker_names) for j, a in enumerate(("dx", "dy", "dz"))}
        pt = [i for i in pos if self.terms[i][0] in mk]
        fr = [i for i in pos if self.terms[i][0] in BASE_NAMES]  # the instrument frame per row, exactly too
        G = None
        if pos:
            k = torch.tensor([self.robot.param_names.index(self.terms[i][0]) for i in pos], device=q.device)
            J = self.robot.param_jacobian(q, self.geometry, check=False)[..., k]  # (N, M, 3, T') instrument frame
            Rb, _ = self.robot.base_transform(self.geometry)
            G = Rb.T @ J  # robot base frame, as position_delta speaks
        X = {}  # each driver's value per row (a text column: its level's index, the baseline 0), for plots
        for _, d, t in self.terms:
            if driver_kind(d) != "level":
                X.setdefault(d, driver_values(self.robot, d, q, covariates, tq))
        for (_, d, t), c in zip(self.terms, cols):
            if _levels(t):
                X.setdefault(d, torch.zeros_like(c))
                X[d] = torch.where(c > 0, c * (1 + sorted({u for _, e, u in self.terms if e == d}).index(t)), X[d])
        ix = lambda v: torch.tensor(v, dtype=torch.long, device=q.device)  # noqa: E731
        return Prepared({"F": F, "X": X, "target": target, "is_q": torch.tensor(is_q, dtype=torch.bool, device=q.device),
                         "pos": ix(pos), "G": G, "pt": ix(pt), "pt_at": ix([mk[self.terms[i][0]] for i in pt]),
                         "fr": ix(fr), "fr_at": ix([BASE_NAMES.index(self.terms[i][0]) for i in fr]),
                         "disp": ix([k for k, i in enumerate(pos) if i not in pt and i not in fr])})

    def joint_delta(self, theta, prep):
        F, target, is_q = prep.features["F"], prep.features["target"], prep.features["is_q"]
        if not bool(is_q.any()):
            return None
        out = theta.new_zeros(theta.shape[0], F.shape[0], self.robot.dof)
        th = theta * is_q.to(theta)
        return out.index_add_(2, target, th[:, None, :] * F[None])

    def position_delta(self, theta, prep):
        G, pos, disp = prep.features["G"], prep.features["pos"], prep.features["disp"]
        if G is None or not disp.numel():
            return None
        t = pos[disp]
        return torch.einsum("nmat,nt,pt->pnma", G[..., disp], prep.features["F"][:, t], theta[:, t])

    def point_delta(self, theta, prep):
        pt, at = prep.features["pt"], prep.features["pt_at"]
        if not pt.numel():
            return None
        F = prep.features["F"]
        out = theta.new_zeros(theta.shape[0], F.shape[0], 3 * len(self.robot.marker_names))
        out.index_add_(2, at, theta[:, None, pt] * F[None, :, pt])
        return out.unflatten(-1, (-1, 3))

    def frame_delta(self, theta, prep):
        fr, at = prep.features["fr"], prep.features["fr_at"]
        if not fr.numel():
            return None
        out = theta.new_zeros(theta.shape[0], prep.features["F"].shape[0], 6)
        return out.index_add_(2, at, theta[:, None, fr] * prep.features["F"][None, :, fr])

    def linear_basis(self, prep: Prepared) -> LinearBasis:
        """The terms' columns built directly (one per term, the family is linear in its
        coefficients): a zero's ``Δq`` on its joint, any other parameter's Jacobian column times
        the shape, without evaluating the effect once per term."""
        F, is_q, target, pos, G = (prep.features[k] for k in ("F", "is_q", "target", "pos", "G"))
        N, T = F.shape
        dq = dp = None
        if bool(is_q.any()):
            dq = F.new_zeros(N, self.robot.dof, T)
            cols = torch.nonzero(is_q).flatten()
            dq[:, target[cols], cols] = F[:, cols]
        if G is not None:
            dp = F.new_zeros(*G.shape[:3], T)
            dp[..., pos] = G * F[:, pos][:, None, None, :]
        return LinearBasis(dq, dp, [list(c) for _, c in self.modes()])

    def signature(self, prep: Prepared, label: str, theta: Tensor) -> dict:
        return evidence.signature(self, prep, label, theta)

    def mode_words(self, label: str) -> str:
        return words.mode_words(self, label)

    def describe(self, theta: Tensor | None = None, free: Tensor | None = None) -> list[str]:
        return words.describe(self, self.theta if theta is None else theta, free)
