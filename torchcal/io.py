"""Measurement files: CSV with one column per joint, ``<marker>.x/.y/.z`` (m) per measured
marker, optional ``<marker>.qw/.qx/.qy/.qz`` orientation, and any other numeric column as a
covariate (time, temperature, direction of last motion …).

An empty marker cell means the marker was not seen in that row; the row still counts for
the other markers.
"""
from __future__ import annotations

import csv
import difflib
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = ["Measurements", "load_measurements", "save_measurements", "marker_columns_in"]

_POS = (".x", ".y", ".z")
_QUAT = (".qw", ".qx", ".qy", ".qz")


@dataclass
class Measurements:
    """Joint values and what an instrument saw, row by row.

    Attributes:
        q: ``(N, dof)`` joint values (rad / m) in ``joint_names`` order.
        positions: ``(N, M, 3)`` measured marker positions (m, instrument frame); NaN = not seen.
        quaternions: ``(N, M, 4)`` measured orientations (w, x, y, z) or ``None``; NaN = not seen.
        marker_names: the M markers, in the robot's marker order.
        covariates: other columns, name -> ``(N,)``.
    """

    q: Tensor
    positions: Tensor
    marker_names: list[str]
    joint_names: list[str]
    quaternions: Tensor | None = None
    covariates: dict[str, Tensor] = field(default_factory=dict)
    source: str | None = None

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

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def seen(self) -> Tensor:
        """``(N, M)`` bool: marker position measured in that row."""
        return ~torch.isnan(self.positions).any(-1)

    def subset(self, idx) -> "Measurements":
        """Rows ``idx`` (indices or a bool mask)."""
        idx = torch.as_tensor(idx)
        if idx.dtype == torch.bool:
            idx = torch.nonzero(idx).flatten()
        return Measurements(self.q[idx], self.positions[idx], list(self.marker_names), list(self.joint_names),
                            None if self.quaternions is None else self.quaternions[idx],
                            {k: v[idx] for k, v in self.covariates.items()}, self.source)

    def select_markers(self, names: list[str]) -> "Measurements":
        """The same rows with only the markers ``names`` (in that order), e.g. one point of a
        motion-capture rigid body for a protocol that uses one."""
        missing = [n for n in names if n not in self.marker_names]
        if missing:
            raise ValueError(f"no marker {missing}; these rows have {self.marker_names}")
        k = [self.marker_names.index(n) for n in names]
        return Measurements(self.q, self.positions[:, k], list(names), list(self.joint_names),
                            None if self.quaternions is None else self.quaternions[:, k], dict(self.covariates),
                            self.source)

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
        return Measurements(f(self.q), f(self.positions), list(self.marker_names), list(self.joint_names),
                            f(self.quaternions), {k: f(v) for k, v in self.covariates.items()}, self.source)


def marker_columns_in(header: list[str]) -> list[str]:
    """Marker names that have position columns in a CSV header, in order of appearance."""
    out = []
    for c in header:
        for s in _POS:
            if c.endswith(s) and c[: -len(s)] not in out:
                out.append(c[: -len(s)])
    return out


def _read_csv(path) -> tuple[list[str], list[list[str]]]:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"measurement file not found: {p}")
    with open(p, newline="") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if r and not (len(r) == 1 and not r[0].strip())]
    if not rows:
        raise ValueError(f"{p}: the file is empty; it needs a header row and one row per pose")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise ValueError(f"{p}: duplicate column names {dup}")
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise ValueError(f"{p}, line {i}: {len(r)} cells but the header has {len(header)} columns")
    return header, rows[1:]


def _number(cell: str, line: int, col: str, path) -> float:
    s = cell.strip()
    if s == "" or s.lower() == "nan":
        return math.nan
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{path}, line {line}, column {col!r}: {cell!r} is not a number") from None


def load_measurements(path: str | os.PathLike, robot, *, dtype: torch.dtype | None = None) -> Measurements:
    """Read a measurement CSV and check it against ``robot``.

    Every actuated joint of the robot must have a column (named as in the URDF). Marker
    columns must name markers of the robot (declare unknown points with
    ``Robot.from_urdf(..., markers=["m1@link=x,y,z"])`` or ``--marker`` on the command line).
    Raises ``ValueError`` saying exactly what is wrong; warns when values look like degrees
    or millimetres.
    """
    header, rows = _read_csv(path)
    if not rows:
        raise ValueError(f"{path}: the file has a header but no rows")
    joints = list(robot.joint_names)
    cols = set(header)
    missing = [j for j in joints if j not in cols]
    if missing:
        hints = []
        for j in missing:
            close = difflib.get_close_matches(j, header, n=1)
            if close:
                hints.append(f"{j!r} (is {close[0]!r} meant?)")
            else:
                hints.append(repr(j))
        raise ValueError(f"{path}: no column for joint(s) {', '.join(hints)}. The robot's joints are {joints}; "
                         "name the joint columns exactly as in the URDF")
    markers_in_file = marker_columns_in(header)
    robot_markers = list(robot.marker_names)
    unknown = [m for m in markers_in_file if m not in robot_markers]
    if unknown:
        raise ValueError(f"{path}: marker column(s) for {unknown}, which the robot does not have (its markers: "
                         f"{robot_markers}). Declare them, e.g. Robot.from_urdf(urdf, markers=['{unknown[0]}@LINK']) "
                         f"or --marker {unknown[0]}@LINK[=x,y,z]")
    measured = [m for m in robot_markers if m in markers_in_file]
    if not measured:
        raise ValueError(f"{path}: no marker columns; expected '<marker>.x', '<marker>.y', '<marker>.z' for one of "
                         f"{robot_markers}")
    for m in measured:
        absent = [m + s for s in _POS if m + s not in cols]
        if absent:
            raise ValueError(f"{path}: marker {m!r} has some position columns but not {absent}")
    has_quat = [m for m in measured if any(m + s in cols for s in _QUAT)]
    for m in has_quat:
        absent = [m + s for s in _QUAT if m + s not in cols]
        if absent:
            raise ValueError(f"{path}: marker {m!r} has some orientation columns but not {absent}")
    used = set(joints) | {m + s for m in measured for s in _POS} | {m + s for m in has_quat for s in _QUAT}
    covariates = [c for c in header if c not in used]
    idx = {c: i for i, c in enumerate(header)}
    N = len(rows)
    data = np.empty((N, len(header)))
    for i, r in enumerate(rows):
        for c, j in idx.items():
            data[i, j] = _number(r[j], i + 2, c, path)
    Q = data[:, [idx[j] for j in joints]]
    bad = np.argwhere(~np.isfinite(Q))
    if len(bad):
        i, j = bad[0]
        raise ValueError(f"{path}, line {i + 2}: joint {joints[j]!r} is empty or not finite; every row needs all "
                         "joint values (drop the row if the robot state was not recorded)")
    P = np.stack([data[:, [idx[m + s] for s in _POS]] for m in measured], 1)
    partial = np.isnan(P).any(-1) & ~np.isnan(P).all(-1)
    if partial.any():
        i, m = np.argwhere(partial)[0]
        raise ValueError(f"{path}, line {i + 2}: marker {measured[m]!r} has some of x/y/z but not all; "
                         "leave all three empty when the marker was not seen")
    if np.isinf(P).any():
        i, m = np.argwhere(np.isinf(P).any(-1))[0]
        raise ValueError(f"{path}, line {i + 2}: marker {measured[m]!r} has an infinite coordinate")
    seen = ~np.isnan(P).any(-1)
    if not seen.any():
        raise ValueError(f"{path}: no marker was seen in any row")
    med = float(np.median(np.abs(P[seen]))) if seen.any() else 0.0
    if med > 20.0:
        warnings.warn(f"{path}: marker coordinates have median |value| {med:.0f}; that looks like millimetres. "
                      "torchcal expects metres (divide by 1000)", stacklevel=2)
    Qt = None
    if has_quat:
        Qt = np.full((N, len(measured), 4), np.nan)
        for k, m in enumerate(measured):
            if m in has_quat:
                qq = data[:, [idx[m + s] for s in _QUAT]]
                norm = np.linalg.norm(qq, axis=1)
                ok = np.isfinite(norm)
                if ok.any() and np.abs(norm[ok] - 1).max() > 1e-3:
                    i = int(np.argmax(np.where(ok, np.abs(norm - 1), 0)))
                    raise ValueError(f"{path}, line {i + 2}: quaternion of {m!r} has norm {norm[i]:.4f}; "
                                     "give unit quaternions (qw, qx, qy, qz)")
                Qt[:, k] = qq / np.where(ok, norm, 1)[:, None]
    dt = dtype or robot.dtype
    q = robot.check_q(torch.as_tensor(Q, dtype=dt), what=f"{path} joint columns", _stacklevel=3).to(robot.device)
    cov = {c: torch.as_tensor(data[:, idx[c]], dtype=dt, device=robot.device) for c in covariates}
    return Measurements(q, torch.as_tensor(P, dtype=dt, device=robot.device), measured, joints,
                        None if Qt is None else torch.as_tensor(Qt, dtype=dt, device=robot.device), cov, str(path))


def save_measurements(path: str | os.PathLike, data: Measurements, digits: int = 17) -> None:
    """Write measurements in the format :func:`load_measurements` reads (NaN -> empty cell)."""
    header = list(data.joint_names)
    cols = [data.q[:, i] for i in range(data.q.shape[1])]
    for k, m in enumerate(data.marker_names):
        for a, s in enumerate(_POS):
            header.append(m + s)
            cols.append(data.positions[:, k, a])
        if data.quaternions is not None:
            for a, s in enumerate(_QUAT):
                header.append(m + s)
                cols.append(data.quaternions[:, k, a])
    for c, v in data.covariates.items():
        header.append(c)
        cols.append(v)
    M = torch.stack([c.detach().cpu().double() for c in cols], 1).numpy()
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in M:
            w.writerow(["" if not np.isfinite(v) else f"{v:.{digits}g}" for v in row])
