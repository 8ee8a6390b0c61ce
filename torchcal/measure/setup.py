"""The unknowns of a measuring set-up besides the instrument frame: the planes a probe touches and
the fixed points distances are measured to (:class:`Setup`), located from the data and identified
with the robot; which rows need them, and whether held-out rows use only those the training rows
located."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcal.measure.data import Measurements, is_quality_column
from torchcal.params import ParamSet

__all__ = ["Setup", "SETUP_PREFIXES", "needs_setup", "setup_refs", "check_heldout", "marker_index"]

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
    lack = [c for c in train.covariates if c not in test.covariates and not is_quality_column(c)]
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


def marker_index(robot, data: Measurements) -> Tensor:
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
    size, and the fit keeps it at zero (:class:`~torchcal.problems.effect_calibration.EffectCalibrationProblem`).
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
        mk = marker_index(robot, data)
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
