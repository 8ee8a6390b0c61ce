"""What an instrument measured, as residuals of the model's marker positions: full or partial
positions, contacts with planes, distances between markers or to fixed points; and the unknowns
of the set-up that planes and fixed points bring (:class:`Setup`), identified with the robot.

Every observation gives a residual vector of three components (model − measured, m). The
components an observation does not measure are zero and so are their Jacobian rows, so every
fit, score and cross-validation works on ``(n_obs, 3)`` arrays whatever was measured:

* position: the measured axes of ``p − p_measured`` (a marker seen in one axis has one);
* plane contact: ``(nᵀp − d, 0, 0)``, the signed distance of the marker from the plane ``(n, d)``;
* distance between markers ``a`` and ``b`` of one row: ``(|p_a − p_b| − d_measured, 0, 0)``;
* distance to a fixed point ``c``: ``(|p_a − c| − d_measured, 0, 0)``;
* orientation of a marker frame: ``w · log(R R_measuredᵀ)``, its rotation vector (rad) times the
  weight ``w`` (m/rad) that makes a rotation error count like a position error of the same
  noise (``w = σ_position / σ_rotation``).

**What a plane cannot see.** A contact measures only the marker's displacement along the
plane's normal: whatever moves every contact within its plane is invisible, and the plane's own
pose absorbs a rigid motion of the whole robot along and about its normal. With planes and
distances alone nothing fixes where the robot stands, so the instrument frame is fixed (planes and
fixed points are then expressed in the robot's base frame); :func:`blind_reasons` says in words
why a parameter is not seen.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.kinematics.transforms import quat_to_matrix, so3_left_jacobian_inv, so3_log
from torchcal.measure.data import Measurements
from torchcal.params import ParamSet

__all__ = ["Setup", "Observations", "POSITION", "PLANE", "DISTANCE", "PIVOT", "ORIENTATION", "KIND_NAMES",
           "SETUP_PREFIXES",
           "needs_setup", "setup_refs", "check_heldout"]

POSITION, PLANE, DISTANCE, PIVOT, ORIENTATION = 0, 1, 2, 3, 4
KIND_NAMES = ("position", "plane contact", "distance between markers", "distance to a fixed point", "orientation")
SETUP_PREFIXES = ("plane.", "pivot.")


def needs_setup(data: Measurements) -> bool:
    """The rows touch planes or measure distances to fixed points: their poses are unknowns."""
    return bool(data.pivots) or (data.planes is not None and bool((data.planes >= 0).any()))


def setup_refs(data: Measurements) -> tuple[list[str], list[str]]:
    """The planes these rows touch (labels with at least one contact, sorted) and the fixed points
    they measure distances to."""
    planes = sorted({data.plane_names[int(i)] for i in torch.unique(data.planes[data.planes >= 0]).tolist()}
                    if data.planes is not None else set())
    return planes, list(data.pivots)


def check_heldout(train: Measurements, test: Measurements) -> None:
    """Refuse held-out rows that touch a plane or measure to a fixed point the training rows never
    do: its pose would be unknown, since the set-up is identified from the training rows only. And
    held-out rows without a covariate column of the training rows: a model that reads it could not
    be measured on them."""
    lack = [c for c in train.covariates if c not in test.covariates]
    if lack:
        raise ValueError(f"the held-out rows ({test.source or 'test'}) have no column for covariate(s) {lack[:5]}, "
                         f"which the training rows ({train.source or 'data'}) have; effects and the residual ELM may "
                         "read them: add the column(s) to the held-out file, or drop them from the training file")
    (tp, tb), (hp, hb) = setup_refs(train), setup_refs(test)
    unknown = [p for p in hp if p not in tp] + [b for b in hb if b not in tb]
    if unknown:
        raise ValueError(f"the held-out rows measure against {unknown}, which the training rows never touch (they "
                         f"touch planes {tp}, fixed points {tb}); planes and fixed points are located from the "
                         "training rows only: move some rows that touch them into the training data, or drop them "
                         "from the held-out data")


def _marker_index(robot, data: Measurements) -> Tensor:
    missing = [m for m in data.marker_names if m not in robot.marker_names]
    if missing:
        raise ValueError(f"the data has markers {missing} that the robot does not have ({robot.marker_names})")
    return torch.tensor([robot.marker_names.index(m) for m in data.marker_names], device=robot.device)


class Setup:
    """The unknowns of the measuring set-up besides the instrument frame: every touched plane's
    pose and every fixed point's position (instrument frame, m).

    A plane is ``nᵀp = d``. Its normal is parameterised around a reference ``n0`` fixed for the
    run, ``n = (n0 + rx t1 + ry t2) / |n0 + rx t1 + ry t2|`` with ``t1, t2`` perpendicular to ``n0``:
    parameters ``plane.<name>.rx``, ``.ry`` (rad, near 0: no singular direction) and ``.d`` (m).
    A fixed point is ``pivot.<name>.x/.y/.z`` (m).

    Build it with :meth:`from_data`: the references and start values come from the model's marker
    positions at a start geometry (a plane fitted to the contacts, a sphere to the distances),
    never from anything but what was measured.

    **Scale.** Plane contacts alone cannot tell the robot's size: a robot scaled by ``s`` about its
    base touches planes whose offsets are scaled by ``s`` at exactly the same commands, and since
    the residuals shrink with ``s`` a free fit would shrink the robot towards a point. When the
    data hold nothing but contacts (no position, no distance), ``scale_gauge (K,)`` holds the
    robot's size at the ``reference (K,)`` geometry: ``gᵀ(θ − θ_ref)`` is the relative change of
    size, and the fit keeps it at zero (:class:`~torchcal.problems.calibration.EffectCalibrationProblem`).
    One known length (a distance, a position) removes the need.
    """

    def __init__(self, planes: list[str], normals: Tensor, offsets: Tensor, pivots: list[str], centres: Tensor,
                 scale_gauge: Tensor | None = None, reference: Tensor | None = None):
        self.planes, self.pivots = list(planes), list(pivots)
        self.scale_gauge, self.reference = scale_gauge, reference
        dt = normals.dtype if len(planes) else centres.dtype
        dev = normals.device
        n0 = normals.reshape(-1, 3).to(dt)
        self.n0 = n0 / n0.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        # t1: the coordinate axis least aligned with n0, made perpendicular; t2 = n0 × t1
        eye = torch.eye(3, dtype=dt, device=dev)
        a = eye[(self.n0.abs()).argmin(-1)] if len(planes) else torch.zeros(0, 3, dtype=dt, device=dev)
        t1 = a - (a * self.n0).sum(-1, keepdim=True) * self.n0
        self.t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp(min=1e-300)
        self.t2 = torch.linalg.cross(self.n0, self.t1)
        self.names = ([f"plane.{p}.{s}" for p in self.planes for s in ("rx", "ry", "d")]
                      + [f"pivot.{p}.{s}" for p in self.pivots for s in ("x", "y", "z")])
        self.units = ["rad", "rad", "m"] * len(self.planes) + ["m"] * (3 * len(self.pivots))
        start = torch.zeros(3 * len(self.planes), dtype=dt, device=dev)
        if len(planes):
            start[2::3] = offsets.to(dt)
        self.start = torch.cat([start, centres.reshape(-1).to(dt)])

    @property
    def n_params(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        return f"Setup(planes {self.planes}, fixed points {self.pivots}; {self.n_params} unknowns)"

    @classmethod
    def from_data(cls, robot, data: Measurements, geometry: Tensor) -> "Setup":
        """Planes and fixed points of ``data``, started from the model's marker positions at
        ``geometry (K,)`` (instrument frame): a least-squares plane through each plane's contacts
        (at least 3, not on one line), a least-squares sphere centre for each fixed point (at
        least 4 distances, not on one plane)."""
        mk = _marker_index(robot, data)
        p = robot.positions(data.q, geometry, check=False)[:, mk]  # (N, M, 3)
        dt, dev = p.dtype, p.device
        normals, offsets, names = [], [], []
        for k, name in enumerate(data.plane_names):
            pts = p[data.planes == k] if data.planes is not None else p.new_zeros(0, 3)
            if pts.shape[0] == 0:  # a label of other rows (a subset): not a plane of these
                continue
            names.append(name)
            if pts.shape[0] < 3:
                raise ValueError(f"plane {name!r} has {pts.shape[0]} contact(s) in these rows; a plane needs at least "
                                 "3 (not on one line) to be located, and many more to calibrate anything with it: "
                                 f"touch it more often, or drop the rows labelled {name!r}")
            c = pts.mean(0)
            _, s, vh = torch.linalg.svd(pts - c, full_matrices=False)
            if float(s[1]) <= 1e-6 * max(float(s[0]), 1e-300):
                raise ValueError(f"the contacts with plane {name!r} lie on one line; a plane's pose needs contacts "
                                 "spread over its surface")
            n = vh[-1]
            normals.append(n)
            offsets.append((n * c).sum())
        centres = []
        for b in data.pivots:
            rows_p, d_all = [], []
            for (a, bb), v in data.distances.items():
                if bb != b:
                    continue
                ok = torch.isfinite(v)
                rows_p.append(p[ok, data.marker_names.index(a)])
                d_all.append(v[ok])
            P_, d = torch.cat(rows_p), torch.cat(d_all)
            if P_.shape[0] < 4:
                raise ValueError(f"fixed point {b!r} has {P_.shape[0]} distance(s) in these rows; locating it needs at "
                                 "least 4 from positions not on one plane: measure more, or drop the '<marker>.dist."
                                 f"{b}' column")
            # |p_i − c|² = d_i²: subtracting the mean equation leaves 2 (p_i − p̄)ᵀ c = |p_i|² − mean − (d_i² − mean)
            sq = (P_ * P_).sum(-1) - d * d
            A = 2 * (P_ - P_.mean(0))
            rhs = (sq - sq.mean())[:, None]
            sol = torch.linalg.lstsq(A, rhs).solution[:, 0]
            if torch.linalg.matrix_rank(A) < 3:
                raise ValueError(f"the distances to fixed point {b!r} were measured from positions on one plane; "
                                 "the point's side of that plane is then unknown: measure from a spread of heights")
            centres.append(sol)
        gauge = _scale_direction(robot, data, geometry) if not data.distances and not bool(data.observed.any()) else None
        return cls(names, torch.stack(normals) if normals else torch.zeros(0, 3, dtype=dt, device=dev),
                   torch.stack(offsets) if offsets else torch.zeros(0, dtype=dt, device=dev), data.pivots,
                   torch.stack(centres) if centres else torch.zeros(0, 3, dtype=dt, device=dev), gauge,
                   geometry.detach().clone() if gauge is not None else None)

    def params(self) -> ParamSet:
        """The set-up unknowns at their start values, free and unbounded."""
        n = self.n_params
        inf = torch.full((n,), math.inf, dtype=self.start.dtype, device=self.start.device)
        return ParamSet(list(self.names), list(self.units), self.start.clone(),
                        torch.ones(n, dtype=torch.bool, device=self.start.device), -inf, inf)

    def planes_of(self, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``s (P, S)`` -> unit normals ``(P, n_planes, 3)``, offsets ``(P, n_planes)`` (m) and the
        unnormalised normal's length ``(P, n_planes)``."""
        k = len(self.planes)
        x = s[:, : 3 * k].reshape(s.shape[0], k, 3)
        v = self.n0 + x[..., :1] * self.t1 + x[..., 1:2] * self.t2
        ln = v.norm(dim=-1)
        return v / ln[..., None], x[..., 2], ln

    def centres_of(self, s: Tensor) -> Tensor:
        """``s (P, S)`` -> fixed points ``(P, n_pivots, 3)`` (m)."""
        return s[:, 3 * len(self.planes):].reshape(s.shape[0], -1, 3)

    def describe(self, s: Tensor) -> dict:
        """Readable values at ``s (S,)``: each plane's unit normal and offset (m), each fixed point."""
        n, d, _ = self.planes_of(s[None])
        c = self.centres_of(s[None])
        return {"planes": {p: {"normal": n[0, i].tolist(), "offset_m": float(d[0, i])} for i, p in enumerate(self.planes)},
                "fixed_points": {p: c[0, i].tolist() for i, p in enumerate(self.pivots)}}


def _scale_direction(robot, data: Measurements, geometry: Tensor) -> Tensor | None:
    """``g (K,)`` with ``gᵀ δ`` the relative change of the robot's size caused by a parameter
    change ``δ``: the least-squares combination of the robot's length parameters that moves
    every marker by its own position from the base origin (a pure scaling), normalised; None when
    no combination scales the robot (prismatic joints, too few parameters)."""
    J, p = robot.param_jacobian(data.q, geometry, kind="position", check=False, return_positions=True)
    _, tb = robot.base_transform(geometry[None])
    target = (p - tb.reshape(1, 1, 3)).reshape(-1)
    cols = [i for i, (n, u) in enumerate(zip(robot.param_names, robot.param_units))
            if u == "m" and not n.startswith("base.")]
    A = J.reshape(-1, J.shape[-1])[:, cols]
    a = torch.linalg.pinv(A) @ target  # minimum norm: the lengths' own scaling, whatever duplicates them
    if float((A @ a - target).norm()) > 1e-6 * float(target.norm()):
        return None
    g = torch.zeros(robot.n_params, dtype=a.dtype, device=a.device)
    g[cols] = a / (a * a).sum()
    return g


class Observations:
    """Every observation of ``data`` as a residual vector of the model's marker positions.

    Order: positions (a marker seen in at least one axis, row-major), plane contacts, distances
    between markers, distances to fixed points. Attributes: ``rows (n,)`` the row, ``marker
    (n,)`` the robot's marker index (for distances the marker measured from), ``data_marker (n,)``
    the index into ``data.marker_names``, ``kind (n,)``, ``mask (n, 3)`` the components measured.

    Args:
        setup: the plane poses and fixed points; required when the data touches planes or
            measures distances to fixed points, and must know every one of them.
        rot_weight: m/rad; with it, every measured marker orientation (finite quaternion) is an
            observation too, after the positions' and set-up's (None: orientations unused).
    """

    def __init__(self, robot, data: Measurements, setup: Setup | None = None, rot_weight: float | None = None):
        mk = _marker_index(robot, data)
        dev, dt = robot.device, robot.dtype
        if needs_setup(data):
            if setup is None:
                raise ValueError("these rows touch planes or measure distances to fixed points, whose poses are "
                                 "unknowns: pass setup=Setup.from_data(robot, data, geometry)")
            used, pivots = setup_refs(data)
            unknown = [p for p in used if p not in setup.planes] + [b for b in pivots if b not in setup.pivots]
            if unknown:
                raise ValueError(f"these rows measure against {unknown}, which the set-up does not know (it has planes "
                                 f"{setup.planes}, fixed points {setup.pivots}): the training rows must touch every "
                                 "plane and fixed point the held-out rows use")
        self.setup = setup
        parts = []  # (rows, data marker, kind, other, target (n, 3), mask (n, 3))
        obs = data.observed
        idx = torch.nonzero(obs)
        mask = data.axes_seen[obs]
        parts.append((idx[:, 0], idx[:, 1], POSITION, torch.full_like(idx[:, 0], -1),
                      torch.nan_to_num(data.positions[obs]), mask))
        one = torch.tensor([True, False, False], device=dev)
        if data.planes is not None and bool((data.planes >= 0).any()):
            idx = torch.nonzero(data.planes >= 0)
            remap = torch.tensor([setup.planes.index(p) if p in setup.planes else -1 for p in data.plane_names],
                                 device=dev)
            other = remap[data.planes[idx[:, 0], idx[:, 1]]]
            parts.append((idx[:, 0], idx[:, 1], PLANE, other, torch.zeros(idx.shape[0], 3, dtype=dt, device=dev),
                          one.expand(idx.shape[0], 3)))
        for kind in (DISTANCE, PIVOT):
            for (a, b), v in data.distances.items():
                is_pair = b in data.marker_names
                if is_pair != (kind == DISTANCE):
                    continue
                r = torch.nonzero(torch.isfinite(v)).flatten()
                o = int(mk[data.marker_names.index(b)]) if is_pair else setup.pivots.index(b)
                tgt = torch.zeros(r.numel(), 3, dtype=dt, device=dev)
                tgt[:, 0] = v[r]
                parts.append((r, torch.full_like(r, data.marker_names.index(a)), kind, torch.full_like(r, o), tgt,
                              one.expand(r.numel(), 3)))
        self.rot_weight = None if rot_weight is None else float(rot_weight)
        self._meas_R = torch.zeros(0, 3, 3, dtype=dt, device=dev)
        if self.rot_weight is not None and data.quaternions is not None:
            idx = torch.nonzero(torch.isfinite(data.quaternions).all(-1))
            self._meas_R = quat_to_matrix(data.quaternions[idx[:, 0], idx[:, 1]]).to(dt)
            parts.append((idx[:, 0], idx[:, 1], ORIENTATION, torch.full_like(idx[:, 0], -1),
                          torch.zeros(idx.shape[0], 3, dtype=dt, device=dev),
                          torch.ones(idx.shape[0], 3, dtype=torch.bool, device=dev)))
        self.rows = torch.cat([p[0] for p in parts])
        self.data_marker = torch.cat([p[1] for p in parts])
        self.marker = mk[self.data_marker]
        self.kind = torch.cat([torch.full_like(p[0], p[2]) for p in parts])
        self.other = torch.cat([p[3] for p in parts])
        self.target = torch.cat([p[4] for p in parts]).to(dt)
        self.mask = torch.cat([p[5] for p in parts])
        self._sel = {k: torch.nonzero(self.kind == k).flatten() for k in range(len(KIND_NAMES))}
        self.n = int(self.rows.numel())

    def view(self, where: Tensor) -> "Observations":
        """The observations ``where (n,) bool`` as a light copy (rows, markers, kinds, masks)."""
        out = object.__new__(Observations)
        for a in ("rows", "data_marker", "marker", "kind", "other", "target", "mask"):
            setattr(out, a, getattr(self, a)[where])
        out.setup, out.rot_weight, out.n = self.setup, self.rot_weight, int(where.sum())
        out._sel = {k: torch.nonzero(out.kind == k).flatten() for k in range(len(KIND_NAMES))}
        out._meas_R = self._meas_R[where[self._sel[ORIENTATION]]] if self._sel[ORIENTATION].numel() else self._meas_R
        return out

    @property
    def has_orientation(self) -> bool:
        """Some observations are orientations: the model must give marker rotations too."""
        return bool(self._sel[ORIENTATION].numel())

    @property
    def is_position(self) -> Tensor:
        """``(n,)`` bool: the observation is about where a point is (not how a frame is turned)."""
        return self.kind != ORIENTATION

    def angle_errors(self, r: Tensor) -> Tensor:
        """``(..., n, 3)`` residual vectors -> ``(..., n_orientation)`` angle errors (rad) of the
        orientation observations."""
        return r[..., self._sel[ORIENTATION], :].norm(dim=-1) / (self.rot_weight or 1.0)

    @property
    def dims(self) -> Tensor:
        """``(n,)`` measured components per observation."""
        return self.mask.sum(-1)

    @property
    def n_values(self) -> int:
        return int(self.mask.sum())

    @property
    def full_positions(self) -> Tensor:
        """``(n,)`` bool: the observation is a position seen in all three axes."""
        return (self.kind == POSITION) & self.mask.all(-1)

    def _setup(self, s: Tensor | None, P: int, dt, dev) -> Tensor:
        if s is None:
            S = 0 if self.setup is None else self.setup.n_params
            if S:
                raise ValueError("set-up values are needed for plane and fixed-point observations")
            return torch.zeros(P, 0, dtype=dt, device=dev)
        return s

    def residuals(self, p: Tensor, s: Tensor | None = None, R: Tensor | None = None) -> Tensor:
        """``p (P, N, M, 3)`` marker positions (instrument frame, m), ``s (P, S)`` set-up values and,
        with orientation observations, ``R (P, N, M, 3, 3)`` marker rotations (instrument frame)
        -> ``(P, n, 3)`` residual vectors (m), zero where nothing was measured."""
        P = p.shape[0]
        s = self._setup(s, P, p.dtype, p.device)
        pa = p[:, self.rows, self.marker]  # (P, n, 3)
        r = torch.zeros_like(pa)
        i = self._sel[POSITION]
        if i.numel():
            r[:, i] = (pa[:, i] - self.target[i]) * self.mask[i]
        i = self._sel[PLANE]
        if i.numel():
            n, d, _ = self.setup.planes_of(s)
            k = self.other[i]
            r[:, i, 0] = (n[:, k] * pa[:, i]).sum(-1) - d[:, k]
        i = self._sel[DISTANCE]
        if i.numel():
            pb = p[:, self.rows[i], self.other[i]]
            r[:, i, 0] = (pa[:, i] - pb).norm(dim=-1) - self.target[i, 0]
        i = self._sel[PIVOT]
        if i.numel():
            c = self.setup.centres_of(s)[:, self.other[i]]
            r[:, i, 0] = (pa[:, i] - c).norm(dim=-1) - self.target[i, 0]
        i = self._sel[ORIENTATION]
        if i.numel():
            r[:, i] = self.rot_weight * self._rotation_errors(R, i)
        return r

    def _rotation_errors(self, R: Tensor | None, i: Tensor) -> Tensor:
        """``log(R R_measuredᵀ)`` ``(P, n_i, 3)`` (rad) of the orientation observations ``i``."""
        if R is None:
            raise ValueError("these observations measure orientations: the model's marker rotations are needed")
        Ra = R[:, self.rows[i], self.marker[i]]
        return so3_log(Ra @ self._meas_R.transpose(-1, -2))

    def project(self, p: Tensor, D: Tensor, s: Tensor | None = None, W: Tensor | None = None,
                R: Tensor | None = None) -> Tensor:
        """How marker displacements change the residuals, to first order: ``p (N, M, 3)`` positions,
        ``D (N, M, 3, L)`` displacement of every marker per unit of ``L`` coordinates (instrument
        frame), ``s (S,)`` set-up values -> ``(n, 3, L)``. With orientation observations also
        ``W (N, M, 3, L)`` the markers' small rotations (rad, instrument frame, ``dR = skew(ω) R``)
        per unit coordinate and ``R (N, M, 3, 3)`` their rotations (None W: they do not turn)."""
        s = self._setup(None if s is None else s[None], 1, p.dtype, p.device)
        Da = D[self.rows, self.marker]  # (n, 3, L)
        out = torch.zeros_like(Da)
        i = self._sel[POSITION]
        if i.numel():
            out[i] = Da[i] * self.mask[i, :, None]
        i = self._sel[PLANE]
        if i.numel():
            n, _, _ = self.setup.planes_of(s)
            out[i, 0] = (n[0, self.other[i], :, None] * Da[i]).sum(1)
        for kind in (DISTANCE, PIVOT):
            i = self._sel[kind]
            if not i.numel():
                continue
            pa = p[self.rows[i], self.marker[i]]
            if kind == DISTANCE:
                pb, Db = p[self.rows[i], self.other[i]], D[self.rows[i], self.other[i]]
            else:
                pb, Db = self.setup.centres_of(s)[0, self.other[i]], torch.zeros_like(Da[i])
            u = (pa - pb) / (pa - pb).norm(dim=-1, keepdim=True).clamp(min=1e-300)
            out[i, 0] = (u[:, :, None] * (Da[i] - Db)).sum(1)
        i = self._sel[ORIENTATION]
        if i.numel() and W is not None:
            Jinv = so3_left_jacobian_inv(self._rotation_errors(R[None], i)[0])
            out[i] = self.rot_weight * (Jinv @ W[self.rows[i], self.marker[i]])
        return out

    def setup_jacobian(self, p: Tensor, s: Tensor) -> Tensor:
        """``(n, 3, S)`` derivative of the residuals with respect to the set-up values ``s (S,)``
        at positions ``p (N, M, 3)``."""
        S = 0 if self.setup is None else self.setup.n_params
        J = torch.zeros(self.n, 3, S, dtype=p.dtype, device=p.device)
        if not S:
            return J
        pa = p[self.rows, self.marker]
        i = self._sel[PLANE]
        if i.numel():
            n, _, ln = self.setup.planes_of(s[None])
            k = self.other[i]
            nk, lk = n[0, k], ln[0, k]
            x = pa[i]
            for j, t in enumerate((self.setup.t1[k], self.setup.t2[k])):
                # d n / d r_j = (t − n (nᵀt)) / |v|
                dn = (t - nk * (nk * t).sum(-1, keepdim=True)) / lk[:, None]
                J[i, 0, 3 * k + j] = (dn * x).sum(-1)
            J[i, 0, 3 * k + 2] = -1.0
        i = self._sel[PIVOT]
        if i.numel():
            c = self.setup.centres_of(s[None])[0, self.other[i]]
            u = (pa[i] - c) / (pa[i] - c).norm(dim=-1, keepdim=True).clamp(min=1e-300)
            o = 3 * len(self.setup.planes) + 3 * self.other[i]
            for j in range(3):
                J[i, 0, o + j] = -u[:, j]
        return J


