"""Measured data held in memory: joint values, marker positions (and optional orientations, plane
contacts, distances, temperatures, times, approach directions) for N poses, in m and rad."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["Measurements", "is_quality_column"]


def is_quality_column(name: str) -> bool:
    """A covariate that describes the measurement, not the robot's state (``marker_std_mm``, any
    ``*_std*`` spread, ``marker_samples``): no model reads it as a driver."""
    return "_std" in name or name == "marker_samples"


@dataclass
class Measurements:
    """Joint values and what an instrument saw, row by row.

    Attributes:
        q: ``(N, dof)`` joint values (rad / m) in ``joint_names`` order.
        positions: ``(N, M, 3)`` measured marker positions (m, instrument frame); NaN = not seen.
        quaternions: ``(N, M, 4)`` measured orientations (w, x, y, z) or ``None``; NaN = not seen.
        marker_names: the M markers, in the robot's marker order.
        covariates: other columns, name -> ``(N,)``.
        planes: ``(N, M)`` integer index into ``plane_names`` of the plane each marker touched in
            each row, -1 = none (or ``None``: no plane contacts).
        plane_names: the planes' labels.
        distances: ``(a, b) -> (N,)`` measured distances (m, NaN = not measured) from marker ``a``
            to marker ``b`` in the same row, or to the fixed point named ``b`` when ``b`` is not a
            marker of these rows.
        robot: the name of the robot the rows were loaded for (:func:`~torchcal.measure.io.load_measurements`),
            or None; a fit for another robot refuses them.
    """

    q: Tensor
    positions: Tensor
    marker_names: list[str]
    joint_names: list[str]
    quaternions: Tensor | None = None
    covariates: dict[str, Tensor] = field(default_factory=dict)
    source: str | None = None
    planes: Tensor | None = None
    plane_names: list[str] = field(default_factory=list)
    distances: dict[tuple[str, str], Tensor] = field(default_factory=dict)
    robot: str | None = None

    def __post_init__(self):
        N = self.q.shape[0]
        if self.positions.shape != (N, len(self.marker_names), 3):
            raise ValueError(f"positions must be (N, M, 3) = ({N}, {len(self.marker_names)}, 3), "
                             f"got {tuple(self.positions.shape)}")
        if self.quaternions is not None and self.quaternions.shape != (N, len(self.marker_names), 4):
            raise ValueError(f"quaternions must be (N, M, 4), got {tuple(self.quaternions.shape)}")
        for k, v in self.covariates.items():
            if v.shape != (N,):
                raise ValueError(f"covariate {k!r} has shape {tuple(v.shape)}, expected ({N},)")
        if self.planes is not None:
            if self.planes.shape != (N, len(self.marker_names)) or self.planes.dtype != torch.long:
                raise ValueError(f"planes must be an integer (N, M) = ({N}, {len(self.marker_names)}) tensor, got "
                                 f"{self.planes.dtype} {tuple(self.planes.shape)}")
            if self.planes.numel() and (int(self.planes.max()) >= len(self.plane_names) or int(self.planes.min()) < -1):
                raise ValueError(f"planes must index plane_names ({len(self.plane_names)} planes) or be -1")
            both = (self.planes >= 0) & ~torch.isnan(self.positions).all(-1)
            if bool(both.any()):
                i, m = torch.nonzero(both)[0].tolist()
                raise ValueError(f"row {i}: marker {self.marker_names[m]!r} has a plane contact and a position; a "
                                 "contact measures only the distance along the plane's normal: give one or the other")
        for (a, b), v in self.distances.items():
            if a not in self.marker_names:
                raise ValueError(f"distance from {a!r}: not a marker of these rows ({self.marker_names})")
            if a == b:
                raise ValueError(f"distance from {a!r} to itself")
            if v.shape != (N,):
                raise ValueError(f"distance {a}.dist.{b} has shape {tuple(v.shape)}, expected ({N},)")
            if bool((v < 0).any() | torch.isinf(v).any()):
                raise ValueError(f"distance {a}.dist.{b} has negative or infinite values; distances are metres, zero or "
                                 "more (NaN where not measured)")

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def __repr__(self) -> str:
        seen = ", ".join(f"{m}: {int(n)}" for m, n in zip(self.marker_names, self.seen.sum(0).tolist()))
        part = int((self.observed & ~self.seen).sum())
        more = f", {part} partial" if part else ""
        if self.planes is not None and bool((self.planes >= 0).any()):
            more += f", {int((self.planes >= 0).sum())} contacts on planes {self.plane_names}"
        if self.distances:
            more += f", {sum(int(torch.isfinite(v).sum()) for v in self.distances.values())} distances"
        cov = f", covariates {sorted(self.covariates)}" if self.covariates else ""
        src = f" from {self.source}" if self.source else ""
        return (f"Measurements({len(self)} rows × {len(self.joint_names)} joints, markers seen {{{seen}}}{more}{cov}"
                f"{src}; q in rad / m, positions in m)")

    @property
    def seen(self) -> Tensor:
        """``(N, M)`` bool: marker position measured in that row, all three axes."""
        return ~torch.isnan(self.positions).any(-1)

    @property
    def axes_seen(self) -> Tensor:
        """``(N, M, 3)`` bool: which position axes were measured."""
        return ~torch.isnan(self.positions)

    @property
    def observed(self) -> Tensor:
        """``(N, M)`` bool: at least one position axis of the marker measured in that row."""
        return self.axes_seen.any(-1)

    @property
    def pivots(self) -> list[str]:
        """Fixed points that distances are measured to (not markers), in order of appearance."""
        out = []
        for _, b in self.distances:
            if b not in self.marker_names and b not in out:
                out.append(b)
        return out

    @property
    def n_values(self) -> int:
        """Number of measured scalars: position axes, plane contacts and distances."""
        n = int(self.axes_seen.sum())
        if self.planes is not None:
            n += int((self.planes >= 0).sum())
        return n + sum(int(torch.isfinite(v).sum()) for v in self.distances.values())

    @property
    def positions_only(self) -> bool:
        """Every observation is a full 3-D position (no partial axes, planes or distances)."""
        return (bool((self.observed == self.seen).all()) and not self.distances
                and (self.planes is None or not bool((self.planes >= 0).any())))

    def _with(self, q, positions, markers, quaternions, covariates, planes, distances) -> "Measurements":
        return Measurements(q, positions, markers, list(self.joint_names), quaternions, covariates, self.source,
                            planes, list(self.plane_names), distances, self.robot)

    def subset(self, idx) -> "Measurements":
        """Rows ``idx`` (indices or a bool mask)."""
        idx = torch.as_tensor(idx)
        if idx.dtype == torch.bool:
            idx = torch.nonzero(idx).flatten()
        return self._with(self.q[idx], self.positions[idx], list(self.marker_names),
                          None if self.quaternions is None else self.quaternions[idx],
                          {k: v[idx] for k, v in self.covariates.items()},
                          None if self.planes is None else self.planes[idx],
                          {k: v[idx] for k, v in self.distances.items()})

    def hide(self, mask: Tensor) -> "Measurements":
        """The same rows with the position observations ``mask (N, M)`` marked not seen (NaN), e.g.
        gross errors left out of a fit."""
        pos = self.positions.masked_fill(mask[..., None].to(self.positions.device), float("nan"))
        return self._with(self.q, pos, list(self.marker_names), self.quaternions, dict(self.covariates), self.planes,
                          dict(self.distances))

    def select_markers(self, names: list[str]) -> "Measurements":
        """The same rows with only the markers ``names`` (in that order), e.g. one point of a
        motion-capture rigid body for a protocol that uses one."""
        missing = [n for n in names if n not in self.marker_names]
        if missing:
            raise ValueError(f"no marker {missing}; these rows have {self.marker_names}")
        k = [self.marker_names.index(n) for n in names]
        dist = {(a, b): v for (a, b), v in self.distances.items()
                if a in names and (b in names or b not in self.marker_names)}
        return self._with(self.q, self.positions[:, k], list(names),
                          None if self.quaternions is None else self.quaternions[:, k], dict(self.covariates),
                          None if self.planes is None else self.planes[:, k], dist)

    def split(self, holdout: float, seed: int = 0) -> tuple["Measurements", "Measurements"]:
        """Random split into (train, test) with ``holdout`` of the rows in test."""
        if not 0 < holdout < 1:
            raise ValueError(f"holdout must be a fraction in (0, 1), got {holdout}")
        g = torch.Generator().manual_seed(seed)
        perm = torch.randperm(len(self), generator=g)
        n_test = max(1, int(round(holdout * len(self))))
        return self.subset(perm[n_test:].sort().values), self.subset(perm[:n_test].sort().values)

    def to(self, device=None, dtype=None) -> "Measurements":
        f = lambda t: None if t is None else t.to(device=device, dtype=dtype or t.dtype)  # noqa: E731
        return self._with(f(self.q), f(self.positions), list(self.marker_names), f(self.quaternions),
                          {k: f(v) for k, v in self.covariates.items()},
                          None if self.planes is None else self.planes.to(device=device),
                          {k: f(v) for k, v in self.distances.items()})
