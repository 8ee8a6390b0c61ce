"""What an instrument measured, as residuals of the model's marker positions: full or partial
positions, contacts with planes, distances between markers or to fixed points, orientations of
marker frames. The unknowns of the set-up that planes and fixed points bring are in
:mod:`torchcal.measure.setup`.

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

import torch
from torch import Tensor

from torchcal.kinematics.transforms import quat_to_matrix, so3_left_jacobian_inv, so3_log
from torchcal.measure.data import Measurements
from torchcal.measure.setup import Setup, marker_index, needs_setup, setup_refs

__all__ = ["Observations", "POSITION", "PLANE", "DISTANCE", "PIVOT", "ORIENTATION", "KIND_NAMES"]

POSITION, PLANE, DISTANCE, PIVOT, ORIENTATION = 0, 1, 2, 3, 4
KIND_NAMES = ("position", "plane contact", "distance between markers", "distance to a fixed point", "orientation")


class Observations:
    """Every observation of ``data`` as a residual vector of the model's marker positions.

    Order: positions (a marker seen in at least one axis, row-major), plane contacts, distances
    between markers, distances to fixed points, orientations: kind by kind, which every
    :meth:`view` keeps and the residuals are assembled in. Attributes: ``rows (n,)`` the row, ``marker
    (n,)`` the robot's marker index (for distances the marker measured from), ``data_marker (n,)``
    the index into ``data.marker_names``, ``kind (n,)``, ``mask (n, 3)`` the components measured.

    Args:
        setup: the plane poses and fixed points; required when the data touches planes or
            measures distances to fixed points, and must know every one of them.
        rot_weight: m/rad; with it, every measured marker orientation (finite quaternion) is an
            observation too, after the positions' and set-up's (None: orientations unused).
    """

    def __init__(self, robot, data: Measurements, setup: Setup | None = None, rot_weight: float | None = None):
        mk = marker_index(robot, data)
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

    def as_poses(self) -> "Observations":
        """The observations as poses (``calibrate(kind="pose")``): each marker seen in all three
        axes with a measured orientation gives its position and its orientation, nothing else
        counts. Position ``i`` and orientation ``n/2 + i`` are the same marker in the same row
        (row-major), so ``cat(r[..., :n/2, :], r[..., n/2:, :], -1)`` holds one 6-component pose
        residual (m, then ``rot_weight ·`` rad) per observation, on which a loss acts as a whole."""
        if not self.has_orientation:
            raise ValueError("no measured orientation: poses need rot_weight and quaternion columns")
        key = self.rows * (int(self.data_marker.max()) + 1) + self.data_marker
        full, turn = self.full_positions, self.kind == ORIENTATION
        return self.view((full | turn) & torch.isin(key, key[full]) & torch.isin(key, key[turn]))

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
        s = self._setup(s, p.shape[0], p.dtype, p.device)
        parts = []  # one per kind present, in the observations' order (kind by kind)
        i = self._sel[POSITION]
        if i.numel():
            parts.append((p[:, self.rows[i], self.marker[i]] - self.target[i]) * self.mask[i])
        i = self._sel[PLANE]
        if i.numel():
            n, d, _ = self.setup.planes_of(s)
            k = self.other[i]
            parts.append(_first((n[:, k] * p[:, self.rows[i], self.marker[i]]).sum(-1) - d[:, k], -1))
        for kind in (DISTANCE, PIVOT):
            i = self._sel[kind]
            if i.numel():
                b = (p[:, self.rows[i], self.other[i]] if kind == DISTANCE
                     else self.setup.centres_of(s)[:, self.other[i]])
                parts.append(_first((p[:, self.rows[i], self.marker[i]] - b).norm(dim=-1) - self.target[i, 0], -1))
        i = self._sel[ORIENTATION]
        if i.numel():
            parts.append(self.rot_weight * self._rotation_errors(R, i))
        return _joined(parts, p.new_zeros(p.shape[0], 0, 3), 1)

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
        parts = []  # as in residuals: kind by kind
        i = self._sel[POSITION]
        if i.numel():
            parts.append(D[self.rows[i], self.marker[i]] * self.mask[i, :, None])
        i = self._sel[PLANE]
        if i.numel():
            n, _, _ = self.setup.planes_of(s)
            parts.append(_first((n[0, self.other[i], :, None] * D[self.rows[i], self.marker[i]]).sum(1), 1))
        for kind in (DISTANCE, PIVOT):
            i = self._sel[kind]
            if not i.numel():
                continue
            pa, Da = p[self.rows[i], self.marker[i]], D[self.rows[i], self.marker[i]]
            if kind == DISTANCE:
                pb, Db = p[self.rows[i], self.other[i]], D[self.rows[i], self.other[i]]
            else:
                pb, Db = self.setup.centres_of(s)[0, self.other[i]], torch.zeros_like(Da)
            u = (pa - pb) / (pa - pb).norm(dim=-1, keepdim=True).clamp(min=1e-300)
            parts.append(_first((u[:, :, None] * (Da - Db)).sum(1), 1))
        i = self._sel[ORIENTATION]
        if i.numel() and W is not None:
            Jinv = so3_left_jacobian_inv(self._rotation_errors(R[None], i)[0])
            parts.append(self.rot_weight * (Jinv @ W[self.rows[i], self.marker[i]]))
        elif i.numel():
            parts.append(D.new_zeros(i.numel(), 3, D.shape[-1]))
        return _joined(parts, D.new_zeros(0, 3, D.shape[-1]), 0)

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


def _first(v: Tensor, axis: int) -> Tensor:
    """A one-component residual ``v`` as the first of three components along ``axis`` (zeros after)."""
    z = torch.zeros_like(v)
    return torch.stack([v, z, z], axis)


def _joined(parts: list[Tensor], empty: Tensor, axis: int) -> Tensor:
    """The kinds' parts end to end along the observation ``axis`` (the observations are kind by kind)."""
    if not parts:
        return empty
    return parts[0] if len(parts) == 1 else torch.cat(parts, axis)
