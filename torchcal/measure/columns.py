"""The columns of a measurement file (the format :mod:`torchcal.measure.io` reads): which hold
joints, which a marker's position, orientation, plane contact or a distance, which are covariates,
checked against the robot that reads the file."""
from __future__ import annotations

import difflib
import math
import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["Columns", "sort_columns", "marker_columns_in", "POS", "QUAT", "PLANE", "DIST", "number_cell"]

logger = logging.getLogger("torchcal")

POS = (".x", ".y", ".z")
QUAT = (".qw", ".qx", ".qy", ".qz")
PLANE = ".plane"
DIST = ".dist."


def marker_columns_in(header: list[str]) -> list[str]:
    """Marker names that have measurement columns in a CSV header (position, plane contact, or a
    distance measured from them), in order of appearance."""
    out = []
    for c in header:
        name = None
        for s in POS + (PLANE,):
            if c.endswith(s):
                name = c[: -len(s)]
        if DIST in c:
            name = c.split(DIST)[0]
        if name and name not in out:
            out.append(name)
    return out


def _distance_columns(header: list[str]) -> dict[str, tuple[str, str]]:
    return {c: tuple(c.split(DIST, 1)) for c in header if DIST in c}


def _without_undeclared(path, header: list[str], rows: list[list[str]], markers: list[str]):
    """The header and rows without the columns of markers the robot does not declare (a file often
    holds more markers than a calibration uses: the declared ones choose), the names left out,
    for the caller to name. Their columns: ``.x/.y/.z``, orientation, plane contacts,
    distances measured from them and to them."""
    undeclared = [m for m in marker_columns_in(header) if m not in markers]
    if not undeclared:
        return header, rows, []
    gone = set(undeclared)
    drop = [i for i, c in enumerate(header)
            if (DIST in c and (c.split(DIST, 1)[0] in gone or c.split(DIST, 1)[1] in gone))
            or any(c == m + s for m in gone for s in POS + QUAT + (PLANE,))]
    keep = [i for i in range(len(header)) if i not in set(drop)]
    return [header[i] for i in keep], [[r[i] for i in keep] for r in rows], undeclared


@dataclass
class Columns:
    """What each column of a measurement file holds, for the robot reading it (see
    :func:`~torchcal.measure.io.load_measurements`): the header and rows without undeclared
    markers' columns, the robot's joints, the markers measured (robot order), those left out, the
    distance columns (``column -> (from, to)``), the markers with orientations and with plane
    contacts (``marker -> column``), the covariates, the URDF joints that are not columns of
    ``q`` (:meth:`Robot.other_joints`) and each column's index."""

    header: list[str]
    rows: list[list[str]]
    joints: list[str]
    measured: list[str]
    undeclared: list[str]
    dist_cols: dict[str, tuple[str, str]]
    has_quat: list[str]
    plane_cols: dict[str, str]
    covariates: list[str]
    other: dict
    idx: dict[str, int]

    def col(self, data: np.ndarray, name: str) -> np.ndarray:
        return data[:, self.idx[name]]


def sort_columns(path, header: list[str], rows: list[list[str]], robot) -> Columns:
    """Sort the columns: joints (all required), markers the robot declares (others left out, with
    a warning), their positions, orientations, plane contacts and distances, and covariates."""
    joints = list(robot.joint_names)
    cols = set(header)
    _require_joints(path, header, joints)
    robot_markers = list(robot.marker_names)
    header, rows, undeclared = _without_undeclared(path, header, rows, robot_markers)
    markers_in_file = marker_columns_in(header)
    dist_cols = _distance_columns(header)
    for col, (a_, b_) in dist_cols.items():
        if not b_ or a_ == b_:
            raise ValueError(f"{path}: distance column {col!r} must be named '<marker>.dist.<other marker or fixed "
                             "point>'")
    measured = [m for m in robot_markers if m in markers_in_file or any(b_ == m for _, b_ in dist_cols.values())]
    absent = [m for m in robot_markers if m not in measured]
    if absent and (measured or undeclared):
        raise ValueError(f"{path}: marker(s) {absent} are declared but the file has no columns for them (it has "
                         f"columns for {markers_in_file + undeclared}); declare only the markers that were measured, "
                         f"named as in the file (e.g. --marker {(markers_in_file + undeclared)[0]}@LINK[=x,y,z])")
    if not measured:
        raise ValueError(f"{path}: no marker columns; expected '<marker>.x', '<marker>.y', '<marker>.z' (or "
                         f"'<marker>.plane', '<marker>.dist.<point>') for one of {robot_markers}")
    if undeclared:
        logger.warning(f"{path}: left out the columns of marker(s) {undeclared}, which the robot does not declare "
                       f"(it uses {measured}); declare a marker to use it (--marker NAME@LINK[=x,y,z], or "
                       "Robot.from_urdf(urdf, markers=[...]))")
    has_quat = _require_marker_columns(path, measured, cols)
    plane_cols = {m: m + PLANE for m in measured if m + PLANE in cols}
    used = (set(joints) | {m + s for m in measured for s in POS} | {m + s for m in has_quat for s in QUAT}
            | set(plane_cols.values()) | set(dist_cols))
    other = robot.other_joints()  # a column named like a joint of the URDF is a joint, never a covariate
    covariates = [col for col in header if col not in used and col not in other]
    return Columns(header, rows, joints, measured, undeclared, dist_cols, has_quat, plane_cols, covariates, other,
                    {col: i for i, col in enumerate(header)})


def _require_joints(path, header: list[str], joints: list[str]) -> None:
    """Refuse a file without a column for every joint, suggesting a close name."""
    missing = [j for j in joints if j not in set(header)]
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


def _require_marker_columns(path, measured: list[str], cols: set[str]) -> list[str]:
    """Refuse a marker with some but not all of its position or orientation columns; the markers
    with orientation columns."""
    for m in measured:
        have = [m + s for s in POS if m + s in cols]
        if have and len(have) < 3:
            raise ValueError(f"{path}: marker {m!r} has position columns {have} but not "
                             f"{[m + s for s in POS if m + s not in cols]}; give all three columns (leave the cells "
                             "of an axis that was not measured empty)")
    has_quat = [m for m in measured if any(m + s in cols for s in QUAT)]
    for m in has_quat:
        absent = [m + s for s in QUAT if m + s not in cols]
        if absent:
            raise ValueError(f"{path}: marker {m!r} has some orientation columns but not {absent}")
    return has_quat


def number_cell(cell: str, line: int, col: str, path) -> float:
    """A CSV cell as a number (empty or ``nan``: NaN), refused with its file, line and column."""
    s = cell.strip()
    if s == "" or s.lower() == "nan":
        return math.nan
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{path}, line {line}, column {col!r}: {cell!r} is not a number") from None
