"""Measurement files: CSV with one column per joint, ``<marker>.x/.y/.z`` (m) per measured
marker, optional ``<marker>.qw/.qx/.qy/.qz`` orientation, and any other numeric column as a
covariate (time, temperature, direction of last motion …).

An empty cell means that value was not measured: a marker seen in one or two axes only (a
motion-capture camera pair, a dial gauge) keeps the axes it has; the row still counts for the
other markers.

Measurements that are not positions:

* ``<marker>.plane``: the marker touched a plane, named in the cell (any label: ``A``, ``table``,
  ``1``; empty = no contact). Only the distance along the plane's normal is measured (zero at
  contact); the plane's pose is unknown and identified with the robot. The marker's x/y/z cells
  stay empty in that row.
* ``<a>.dist.<b>`` (m): a distance measured from marker ``a``. When ``b`` is another marker, the
  distance between the two in that row; otherwise ``b`` names a fixed point whose position is
  unknown and identified (the pivot of a ball bar, the centre of a sphere the probe touches).
"""
from __future__ import annotations

import csv
import io
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from torchcal.advice import advice
from torchcal.measure.checks import check_motion, check_robot
from torchcal.measure.columns import PLANE, POS, QUAT, DIST, Columns, number_cell, sort_columns
from torchcal.measure.data import Measurements
from torchcal.measure.instrument import InstrumentFormat, translate
from torchcal.measure.levels import is_text_column, join_levels, level_covariates
from torchcal.measure.units import UNITS, UnitsError, convert_units
from torchcal.outputs import atomic_write_text

__all__ = ["load_measurements", "save_measurements", "read_csv", "read_table", "UNITS", "UnitsError"]

logger = logging.getLogger("torchcal")
_ABSURD = 1e6  # |value| beyond any joint (rad, m, deg) or instrument reading (m, mm)


def read_csv(path, what: str = "measurement file", sep: str = ",") -> tuple[list[str], list[list[str]]]:
    """Header and rows of a ``sep``-separated file, checked: an Excel byte-order mark is dropped,
    a semicolon-separated file (Excel in many locales) read as comma-separated is named as such,
    every row has the header's number of cells, column names are unique."""
    p = Path(path)
    if p.is_dir():
        inside = sorted(x.name for x in p.glob("*.csv"))[:5]
        raise IsADirectoryError(f"{what} {p} is a directory; give the CSV file itself"
                                + (f", e.g. {p / inside[0]} (it holds {inside})" if inside else " (it holds no .csv)"))
    if not p.is_file():
        raise FileNotFoundError(f"{what} not found: {p}")
    rows, lines = CsvRows(), []
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:  # utf-8-sig: strip Excel's BOM
            reader, end = csv.reader(fh, delimiter=sep), 0
            for r in reader:
                # blank lines are skipped, but every message names the line in the file as an editor shows it
                if r and not (len(r) == 1 and not r[0].strip()):
                    rows.append(r)
                    lines.append(end + 1)
                end = reader.line_num
    except UnicodeDecodeError as e:
        raise ValueError(f"{p}: not UTF-8 text ({e}); save the file as CSV UTF-8") from None
    rows.lines = lines
    if not rows:
        raise ValueError(f"{p}: the file is empty; it needs a header row and one row per pose")
    if rows[0][0].lstrip().startswith("#"):
        raise ValueError(f"{p}: line {lines[0]} starts with '#' ({','.join(rows[0])[:60]!r}); torchcal reads the column names "
                         "from the first line, as they are: delete comment lines above the header, and the '#' before "
                         "a header (numpy.savetxt writes one unless comments='')")
    if len(rows[0]) == 1 and rows[0][0].count(";") >= 2 and sep != ";":
        raise ValueError(f"{p} is separated by semicolons (as Excel writes CSV in many locales); torchcal reads "
                         "comma-separated files unless told otherwise: read it with "
                         + advice("InstrumentFormat(sep=';', decimal=',')", "--sep ';' --decimal ','")
                         + " (the decimal mark as the file writes it), or convert it once with `torchcal import`")
    if len(rows[0]) == 1 and rows[0][0].count("\t") >= 1 and sep != "\t":
        raise ValueError(f"{p} is separated by tabs; torchcal reads comma-separated files: save it as CSV (comma "
                         "delimited) or convert it, e.g. pandas.read_csv(path, sep='\\t').to_csv(out, index=False)")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise ValueError(f"{p}: duplicate column names {dup}")
    for i, r in enumerate(rows[1:], start=1):
        if len(r) != len(header):
            raise ValueError(f"{p}, line {lines[i]}: {len(r)} cells but the header has {len(header)} columns")
    body = CsvRows(rows[1:])
    body.lines = lines[1:]
    return header, body


class CsvRows(list):
    """The data rows of a CSV file (lists of cells); ``lines[i]`` the file line of row ``i``."""

    lines: list[int]


class _Source(str):
    """A file's name that knows the file line of each data row (blank lines are not rows)."""

    def __new__(cls, path, rows):
        self = super().__new__(cls, str(path))
        self.lines = list(getattr(rows, "lines", None) or range(2, len(rows) + 2))
        return self

    def line(self, i) -> int:
        return self.lines[int(i)]


def read_table(path, fmt: InstrumentFormat | None = None, what: str = "measurement file"
               ) -> tuple[list[str], list[list[str]]]:
    """Header and rows in torchcal's format: :func:`read_csv`, then an instrument's export
    translated (:func:`~torchcal.measure.instrument.translate`) when ``fmt`` says how it is written."""
    if fmt is None or fmt.is_plain:
        return read_csv(path, what)
    return translate(path, *read_csv(path, what, sep=fmt.sep), fmt)


def load_measurements(path: str | os.PathLike, robot, *, dtype: torch.dtype | None = None,
                      units: list[str] | tuple[str, ...] = (), fmt: InstrumentFormat | None = None) -> Measurements:
    """Read a measurement CSV and check it against ``robot``.

    Every actuated joint of the robot must have a column (named as in the URDF), every marker
    of the robot its ``.x/.y/.z`` columns (or plane / distance columns, see the module
    docstring). The robot's markers choose what is used: the columns of markers it does not
    declare are left out, with one logged warning naming them (declare unknown points with
    ``Robot.from_urdf(..., markers=["m1@link=x,y,z"])`` or ``--marker`` on the command line).

    Args:
        units: ``"deg"``: revolute joint columns are in degrees; ``"mm"``: positions and prismatic
            joints are in millimetres. Both are converted. Without them, values that look like
            degrees or millimetres raise :class:`UnitsError`, which says how to convert: a wrong
            unit gives a wrong calibration, not a warning.
        fmt: how an instrument's own export is written (separator, decimal mark, column names,
            Euler angles: :class:`~torchcal.measure.instrument.InstrumentFormat`); default torchcal's CSV.
    Raises ``ValueError`` saying exactly what is wrong; warns about rows that repeat another
    row exactly (they count twice; cross-validation keeps them in one fold).
    """
    check_robot(robot, precision=False)
    units = [units] if isinstance(units, str) else list(units)  # units="deg" is one unit, not three letters
    bad_units = [u for u in units if u not in UNITS]
    if bad_units:
        raise ValueError(f"unknown unit(s) {bad_units}; declare 'deg' (joint angles) and/or 'mm' (positions)")
    header, rows = read_table(path, fmt)
    if not rows:
        raise ValueError(f"{path}: the file has a header but no rows")
    path = _Source(path, rows)
    c = sort_columns(path, header, rows, robot)
    data = _cells(path, c)
    Q = _joint_values(path, robot, c, data)
    P = _marker_positions(path, c, data)
    planes, plane_names = _plane_contacts(path, c, P)
    D = _distances(path, c, data)
    n_contacts = 0 if planes is None else int((planes >= 0).sum())
    if not np.isfinite(P).any() and not n_contacts and not any(np.isfinite(v).any() for v in D.values()):
        raise ValueError(f"{path}: no marker was seen in any row")
    Q, P, D = convert_units(path, robot, Q, P, D, units)
    _warn_duplicates(path, data)
    Qt = _orientations(path, c, data)
    dt = dtype or robot.dtype
    q = robot.check_q(torch.as_tensor(Q, dtype=dt), what=f"{path} joint columns", units_judged=True).to(robot.device)
    as_t = lambda v: torch.as_tensor(v, dtype=dt, device=robot.device)  # noqa: E731
    cov = {k: as_t(v) for k, v in _covariates(path, c, data).items()}
    for k in _text_columns(c):  # a text column is a factor: one 0/1 covariate per level
        cov.update({n: as_t(v) for n, v in level_covariates(k, [r[c.idx[k]] for r in c.rows]).items()})
    out = Measurements(q, as_t(P), c.measured, c.joints, None if Qt is None else as_t(Qt), cov, str(path),
                       None if planes is None else torch.as_tensor(planes, device=robot.device), plane_names,
                       {k: as_t(v) for k, v in D.items()}, robot.name)
    check_motion(robot, out, units, where=str(path), lines=path.lines)
    return out


def _cells(path, c: Columns) -> np.ndarray:
    """``(N, columns)`` the numeric cells (NaN where empty and in the plane columns), checked for
    values no unit makes plausible."""
    text = set(_text_columns(c))
    numeric = [col for col in c.header if col not in c.plane_cols.values() and col not in text]
    data = np.full((len(c.rows), len(c.header)), np.nan)
    for i, r in enumerate(c.rows):
        for col in numeric:
            j = c.idx[col]
            data[i, j] = number_cell(r[j], path.line(i), col, path)
    _absurd(path, data, c.header, set(c.covariates))
    return data


def _text_columns(c: Columns) -> list[str]:
    """Covariate columns holding text (a tool name, an operator): read as levels, not numbers."""
    return [k for k in c.covariates if is_text_column([r[c.idx[k]] for r in c.rows])]


def _joint_values(path, robot, c: Columns, data: np.ndarray) -> np.ndarray:
    """``(N, dof)`` joint values, every one given; URDF joints past the markers must not move."""
    Q = data[:, [c.idx[j] for j in c.joints]]
    _joints_past_markers(path, robot, c.other, {col: c.col(data, col) for col in c.header if col in c.other})
    bad = np.argwhere(~np.isfinite(Q))
    if len(bad):
        i, j = bad[0]
        raise ValueError(f"{path}, line {path.line(i)}: joint {c.joints[j]!r} is empty or not finite; every row needs all "
                         "joint values (drop the row if the robot state was not recorded)")
    return Q


def _marker_positions(path, c: Columns, data: np.ndarray) -> np.ndarray:
    """``(N, M, 3)`` marker positions, NaN where not measured; none infinite."""
    N = data.shape[0]
    P = np.stack([data[:, [c.idx[m + s] for s in POS]] if m + POS[0] in c.idx else np.full((N, 3), np.nan)
                  for m in c.measured], 1)
    if np.isinf(P).any():
        i, m = np.argwhere(np.isinf(P).any(-1))[0]
        raise ValueError(f"{path}, line {path.line(i)}: marker {c.measured[m]!r} has an infinite coordinate")
    return P


def _plane_contacts(path, c: Columns, P: np.ndarray) -> tuple[np.ndarray | None, list[str]]:
    """``(N, M)`` the plane each marker touched (an index into the names, -1: none), and the plane
    names in order of appearance; ``None`` without plane columns. A contact row has no position."""
    if not c.plane_cols:
        return None, []
    planes, plane_names = np.full((len(c.rows), len(c.measured)), -1, dtype=np.int64), []
    for k, m in enumerate(c.measured):
        if m not in c.plane_cols:
            continue
        j = c.idx[c.plane_cols[m]]
        for i, r in enumerate(c.rows):
            lab = r[j].strip()
            if not lab:
                continue
            if np.isfinite(P[i, k]).any():
                raise ValueError(f"{path}, line {path.line(i)}: marker {m!r} has a plane contact ({lab!r}) and position "
                                 "cells; a contact measures only the distance along the plane's normal: leave "
                                 "x/y/z empty in contact rows")
            if lab not in plane_names:
                plane_names.append(lab)
            planes[i, k] = plane_names.index(lab)
    return planes, plane_names


def _distances(path, c: Columns, data: np.ndarray) -> dict[tuple[str, str], np.ndarray]:
    """``(from, to) -> (N,)`` measured distances (m), NaN where not measured; each a length."""
    D = {(a_, b_): c.col(data, col) for col, (a_, b_) in c.dist_cols.items()}
    for (a_, b_), v in D.items():
        if np.isinf(v).any() or (v[np.isfinite(v)] < 0).any():
            i = int(np.argmax(np.isinf(v) | (np.nan_to_num(v) < 0)))
            raise ValueError(f"{path}, line {path.line(i)}: distance {a_}.dist.{b_} = {v[i]} is not a length; a distance is "
                             "a finite number of metres, zero or more: correct the cell, or leave it empty where "
                             "nothing was measured")
    return D


def _orientations(path, c: Columns, data: np.ndarray) -> np.ndarray | None:
    """``(N, M, 4)`` unit quaternions ``(qw, qx, qy, qz)`` (NaN where not measured), ``None``
    without orientation columns; a quaternion must have norm 1 (to 1e-3) and is normalised."""
    if not c.has_quat:
        return None
    Qt = np.full((data.shape[0], len(c.measured), 4), np.nan)
    for k, m in enumerate(c.measured):
        if m in c.has_quat:
            qq = data[:, [c.idx[m + s] for s in QUAT]]
            norm = np.linalg.norm(qq, axis=1)
            ok = np.isfinite(norm)
            if ok.any() and np.abs(norm[ok] - 1).max() > 1e-3:
                i = int(np.argmax(np.where(ok, np.abs(norm - 1), 0)))
                raise ValueError(f"{path}, line {path.line(i)}: quaternion of {m!r} has norm {norm[i]:.4f}; "
                                 "give unit quaternions (qw, qx, qy, qz)")
            Qt[:, k] = qq / np.where(ok, norm, 1)[:, None]
    return Qt


def _covariates(path, c: Columns, data: np.ndarray) -> dict[str, np.ndarray]:
    """The covariate columns (a temperature, a time) an effect may read: an infinite value is
    refused with its line; a column with empty cells is left out, with one warning, since a model
    that reads it could not be evaluated on those rows (the thermal search would fit NaN)."""
    out = {}
    text = set(_text_columns(c))
    for k in c.covariates:
        if k in text:  # read as levels (load_measurements)
            continue
        v = c.col(data, k)
        if np.isinf(v).any():
            i = int(np.flatnonzero(np.isinf(v))[0])
            raise ValueError(f"{path}, line {path.line(i)}, column {k!r}: {v[i]} is not a finite value; a covariate "
                             "(a temperature, a time) needs a number in every row: correct the cell, or delete the "
                             "column to calibrate without it")
        empty = np.flatnonzero(np.isnan(v))
        if len(empty):
            which = "is empty" if len(empty) == len(v) else \
                f"is empty in {len(empty)} of {len(v)} rows (lines {[path.line(i) for i in empty[:5]]})"
            warnings.warn(f"{path}: column {k!r} {which}; it is not used as a covariate (no effect reads it): fill "
                          "it in every row to use it, or delete it", stacklevel=3)
            continue
        out[k] = v
    return out


def _absurd(path, data: np.ndarray, header: list[str], covariates: set[str]) -> None:
    """Refuse a joint or measurement cell no unit makes plausible (1e308 is a broken export, not
    a gross error), naming its line."""
    cols = [j for j, c in enumerate(header) if c not in covariates]
    x = data[:, cols]
    big = np.isfinite(x) & (np.abs(np.where(np.isfinite(x), x, 0.0)) > _ABSURD)  # inf: named by the checks below
    if big.any():
        i, j = np.argwhere(big)[0]
        raise ValueError(f"{path}, line {path.line(i)}, column {header[cols[j]]!r}: {data[i, cols[j]]:.4g} is not a plausible "
                         "joint value or measurement in any unit (radians, metres, degrees, millimetres); correct the "
                         "cell, or drop the row")


def _joints_past_markers(path, robot, other: dict, columns: dict) -> None:
    """Refuse joint columns that move in the data but come after a marker's link: the marker is
    declared on a link before the one that carries it, and those joints would have no effect."""
    moving = [c for c, v in columns.items() if other[c] is not None and np.nanmax(v) - np.nanmin(v) > 1e-6]
    if moving:
        links = sorted({other[c] for c in moving})
        raise ValueError(f"{path}: joint column(s) {moving} move, but come after link(s) {links}, where the markers "
                         f"are declared ({[f'{m.name}@{m.link}' for m in robot.markers]}): on that link the marker "
                         "would not feel them. Declare each marker on the link that carries it (the flange or tool "
                         "beyond those joints), e.g. " + advice(f"markers=['{robot.markers[0].name}@LINK=x,y,z']",
                                                                f"--marker {robot.markers[0].name}@LINK=x,y,z"))
    if columns:
        logger.info(f"{path}: column(s) {sorted(columns)} are joints of the URDF that move no declared marker; not "
                    "used")


def _warn_duplicates(path, data: np.ndarray) -> None:
    _, first, counts = np.unique(np.nan_to_num(data, nan=np.inf), axis=0, return_index=True, return_counts=True)
    n_dup = int((counts - 1).sum())
    if n_dup:
        lines = sorted(path.line(i) for i, c in zip(first, counts) if c > 1)[:5]
        warnings.warn(f"{path}: {n_dup} row(s) repeat another row exactly (first at line(s) {lines}); each copy counts "
                      "in the fit, and cross-validation keeps copies in one fold", stacklevel=3)


def save_measurements(path: str | os.PathLike, data: Measurements, digits: int = 17) -> None:
    """Write measurements in the format :func:`load_measurements` reads (NaN -> empty cell)."""
    header = list(data.joint_names)
    cols = [data.q[:, i] for i in range(data.q.shape[1])]
    labels: dict[int, list[str]] = {}
    for k, m in enumerate(data.marker_names):
        if bool((~torch.isnan(data.positions[:, k])).any()) or data.planes is None:
            for a, s in enumerate(POS):
                header.append(m + s)
                cols.append(data.positions[:, k, a])
        if data.quaternions is not None:
            for a, s in enumerate(QUAT):
                header.append(m + s)
                cols.append(data.quaternions[:, k, a])
        if data.planes is not None and bool((data.planes[:, k] >= 0).any()):
            labels[len(header)] = ["" if int(i) < 0 else data.plane_names[int(i)] for i in data.planes[:, k].tolist()]
            header.append(m + PLANE)
            cols.append(torch.full((len(data),), float("nan")))
    for (a, b), v in data.distances.items():
        header.append(f"{a}{DIST}{b}")
        cols.append(v)
    numeric, text = join_levels(data.covariates)
    for c, v in numeric.items():
        header.append(c)
        cols.append(v)
    for c, cells in text.items():  # levels written back as the text column they came from
        labels[len(header)] = cells
        header.append(c)
        cols.append(torch.full((len(data),), float("nan")))
    M = torch.stack([c.detach().cpu().double() for c in cols], 1).numpy()
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for i, row in enumerate(M):
        cells = ["" if not np.isfinite(v) else f"{v:.{digits}g}" for v in row]
        for j, lab in labels.items():
            cells[j] = lab[i]
        w.writerow(cells)
    atomic_write_text(path, buf.getvalue())
