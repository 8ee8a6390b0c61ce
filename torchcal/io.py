"""Measurement files: CSV with one column per joint, ``<marker>.x/.y/.z`` (m) per measured
marker, optional ``<marker>.qw/.qx/.qy/.qz`` orientation, and any other numeric column as a
covariate (time, temperature, direction of last motion …).

An empty marker cell means the marker was not seen in that row; the row still counts for
the other markers.
"""
from __future__ import annotations

import csv
import difflib
import io
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .outputs import atomic_write_text

__all__ = ["Measurements", "load_measurements", "save_measurements", "marker_columns_in", "read_csv", "UNITS",
           "UnitsError"]

UNITS = ("deg", "mm")


class UnitsError(ValueError):
    """Values that look like degrees or millimetres where torchcal expects radians and metres."""

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

    def __repr__(self) -> str:
        seen = ", ".join(f"{m}: {int(n)}" for m, n in zip(self.marker_names, self.seen.sum(0).tolist()))
        cov = f", covariates {sorted(self.covariates)}" if self.covariates else ""
        src = f" from {self.source}" if self.source else ""
        return (f"Measurements({len(self)} rows × {len(self.joint_names)} joints, markers seen {{{seen}}}{cov}{src}; "
                "q in rad / m, positions in m)")

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


def read_csv(path, what: str = "measurement file") -> tuple[list[str], list[list[str]]]:
    """Header and rows of a comma-separated file, checked: an Excel byte-order mark is dropped,
    a semicolon-separated file (Excel in many locales) is named as such, every row has the
    header's number of cells, column names are unique."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} not found: {p}")
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:  # utf-8-sig: strip Excel's BOM
            rows = list(csv.reader(fh))
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: not UTF-8 text ({e}); save the file as CSV UTF-8") from None
    rows = [r for r in rows if r and not (len(r) == 1 and not r[0].strip())]
    if not rows:
        raise ValueError(f"{p}: the file is empty; it needs a header row and one row per pose")
    if len(rows[0]) == 1 and rows[0][0].count(";") >= 2:
        raise ValueError(f"{p} is separated by semicolons (as Excel writes CSV in many locales); torchcal reads "
                         "comma-separated files with '.' as the decimal point: save it as 'CSV UTF-8 (comma "
                         "delimited)' or convert it, e.g. pandas.read_csv(path, sep=';', decimal=',').to_csv(out)")
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


def load_measurements(path: str | os.PathLike, robot, *, dtype: torch.dtype | None = None,
                      units: list[str] | tuple[str, ...] = ()) -> Measurements:
    """Read a measurement CSV and check it against ``robot``.

    Every actuated joint of the robot must have a column (named as in the URDF), every marker
    of the robot its ``.x/.y/.z`` columns. Marker columns must name markers of the robot
    (declare unknown points with ``Robot.from_urdf(..., markers=["m1@link=x,y,z"])`` or
    ``--marker`` on the command line).

    Args:
        units: ``"deg"``: revolute joint columns are in degrees; ``"mm"``: positions and prismatic
            joints are in millimetres. Both are converted. Without them, values that look like
            degrees or millimetres raise :class:`UnitsError`, which says how to convert: a wrong
            unit gives a wrong calibration, not a warning.
    Raises ``ValueError`` saying exactly what is wrong; warns about rows that repeat another
    row exactly (they count twice; cross-validation keeps them in one fold).
    """
    bad_units = [u for u in units if u not in UNITS]
    if bad_units:
        raise ValueError(f"unknown unit(s) {bad_units}; declare 'deg' (joint angles) and/or 'mm' (positions)")
    header, rows = read_csv(path)
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
    absent = [m for m in robot_markers if m not in markers_in_file]
    if absent:
        raise ValueError(f"{path}: marker(s) {absent} are declared but the file has no '<marker>.x/.y/.z' columns for "
                         f"them (it has {markers_in_file}); declare only the markers that were measured")
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
    Q, P = _units(path, robot, Q, P, seen, units)
    _warn_duplicates(path, data)
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


def _units(path, robot, Q: np.ndarray, P: np.ndarray, seen: np.ndarray, units) -> tuple[np.ndarray, np.ndarray]:
    """Convert declared units; refuse values that look like degrees or millimetres otherwise."""
    rev = np.array([u == "rad" for u in robot.joint_units])
    if "deg" in units:
        Q = np.where(rev, np.deg2rad(Q), Q)
    if "mm" in units:
        Q = np.where(rev, Q, Q / 1000.0)
        P = P / 1000.0
    lo, hi = (x.cpu().numpy() for x in robot.joint_limits)
    for j, n in enumerate(robot.joint_names):
        v = float(np.abs(Q[:, j]).max())
        span = max(abs(lo[j]), abs(hi[j])) if np.isfinite(lo[j]) and np.isfinite(hi[j]) else 0.0
        if rev[j] and v > max(2.2 * np.pi, 1.5 * span):
            raise UnitsError(f"{path}: joint column {n!r} reaches |q| = {v:.1f}, which looks like degrees; torchcal "
                             "expects radians: convert (rad = deg × π/180) or declare the unit (--units deg, "
                             "load_measurements(..., units=['deg']))")
        if not rev[j] and v > max(5.0, 3 * span):
            raise UnitsError(f"{path}: prismatic joint column {n!r} reaches |q| = {v:.1f}, which looks like "
                             "millimetres; torchcal expects metres: divide by 1000 or declare --units mm")
    med = float(np.median(np.abs(P[seen])))
    if med > 20.0:
        raise UnitsError(f"{path}: marker coordinates have median |value| {med:.0f}, which looks like millimetres; "
                         "torchcal expects metres: divide by 1000 or declare the unit (--units mm, "
                         "load_measurements(..., units=['mm']))")
    return Q, P


def _warn_duplicates(path, data: np.ndarray) -> None:
    _, first, counts = np.unique(np.nan_to_num(data, nan=np.inf), axis=0, return_index=True, return_counts=True)
    n_dup = int((counts - 1).sum())
    if n_dup:
        lines = sorted(int(i) + 2 for i, c in zip(first, counts) if c > 1)[:5]
        warnings.warn(f"{path}: {n_dup} row(s) repeat another row exactly (first at line(s) {lines}); each copy counts "
                      "in the fit, and cross-validation keeps copies in one fold", stacklevel=3)


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
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in M:
        w.writerow(["" if not np.isfinite(v) else f"{v:.{digits}g}" for v in row])
    atomic_write_text(path, buf.getvalue())
