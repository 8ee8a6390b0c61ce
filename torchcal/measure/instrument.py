"""An instrument's own export, read as it is: the separator and decimal mark of its locale, its
column names mapped to torchcal's, joint names with a prefix, and orientations as Euler angles.

:class:`InstrumentFormat` says how the file is written; :func:`translate` turns its header and rows
into the header and rows of torchcal's CSV (``<marker>.x/.y/.z``, ``<marker>.qw/.qx/.qy/.qz``, one
column per URDF joint), which :func:`~torchcal.measure.io.load_measurements` then reads and checks
as any other file. Positions in millimetres and joints in degrees are the reader's ``units``
(``--units mm`` / ``--units deg``), as for torchcal's own files.

**Euler angles.** Columns ``<marker>.rx/.ry/.rz`` (after the column map) are the three angles of a
rotation, in the order of ``euler``, in scipy's convention (:meth:`scipy.spatial.transform.
Rotation.from_euler`): upper-case letters are intrinsic rotations about the moving axes
(``"XYZ"``: about x, then the new y, then the newest z: ``R = Rx(a) Ry(b) Rz(c)``), lower-case
letters extrinsic rotations about the fixed axes (``"xyz"``: ``R = Rz(c) Ry(b) Rx(a)``, roll-pitch-yaw).
There is no default that a file could silently disagree with: a file with Euler columns needs
``euler`` stated.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.kinematics.transforms import matrix_to_quat, rot_x, rot_y, rot_z
from torchcal.measure.columns import QUAT, number_cell
from torchcal.options import Options

__all__ = ["InstrumentFormat", "translate", "parse_column_map", "EULER_COLUMNS", "ROT_UNITS"]

EULER_COLUMNS = (".rx", ".ry", ".rz")
ROT_UNITS = ("rad", "deg")
_ROT = {"x": rot_x, "y": rot_y, "z": rot_z}


@dataclass(frozen=True)
class InstrumentFormat(Options):
    """How an instrument's export is written.

    Attributes:
        sep: the cell separator (``";"`` where Excel writes CSV in many locales; ``"\\t"``).
        decimal: the decimal mark of number cells (``","`` in a German locale); thousands
            separators are not read.
        rot_units: ``"rad"`` or ``"deg"``: the unit of the Euler angle columns.
        euler: the Euler sequence of the ``<marker>.rx/.ry/.rz`` columns, in scipy's convention
            (``"XYZ"`` intrinsic, ``"xyz"`` extrinsic; any of the 12 sequences); required when the
            file has Euler columns.
        columns: the file's column name → torchcal's (``{"measurement_x": "tmac.x"}``); a column
            mapped to ``""`` is left out (a damaged time stamp, a commanded pose).
        strip_prefix: a prefix taken off every column name that has it (``"ur_"``: a bag's
            ``ur_shoulder_pan_joint`` is the URDF's ``shoulder_pan_joint``); applied after ``columns``.
    """
    sep: str = ","
    decimal: str = "."
    rot_units: str = "rad"
    euler: str | None = None
    columns: dict = field(default_factory=dict)
    strip_prefix: str = ""

    def __post_init__(self) -> None:
        if len(self.sep) != 1:
            raise ValueError(f"sep must be one character (',', ';', a tab), got {self.sep!r}")
        if self.decimal not in (".", ","):
            raise ValueError(f"decimal must be '.' or ',', got {self.decimal!r}")
        if self.decimal == self.sep:
            raise ValueError(f"the decimal mark and the separator are both {self.sep!r}; a file that writes "
                             "decimal commas separates cells with ';' (sep=';')")
        if self.rot_units not in ROT_UNITS:
            raise ValueError(f"rot_units must be one of {ROT_UNITS}, got {self.rot_units!r}")
        if self.euler is not None:
            e = self.euler
            ok = len(e) == 3 and (e.isupper() or e.islower()) and set(e.lower()) <= set("xyz") \
                and e[0].lower() != e[1].lower() and e[1].lower() != e[2].lower()
            if not ok:
                raise ValueError(f"euler {e!r} is not an Euler sequence: three axes of x, y, z, no axis twice in a "
                                 "row, all upper case (intrinsic, e.g. 'XYZ') or all lower case (extrinsic, 'xyz')")

    @property
    def is_plain(self) -> bool:
        """torchcal's own format: nothing to translate."""
        return self == InstrumentFormat()


def parse_column_map(items: list[str] | None) -> dict[str, str]:
    """``["measurement_x=tmac.x", "Timestamp="]`` → ``{"measurement_x": "tmac.x", "Timestamp": ""}``."""
    out: dict[str, str] = {}
    for it in items or []:
        if "=" not in it:
            raise ValueError(f"column map entry {it!r} is not FILE_COLUMN=TORCHCAL_COLUMN (e.g. measurement_x=tmac.x; "
                             "'Timestamp=' leaves a column out)")
        k, v = it.split("=", 1)
        if not k.strip():
            raise ValueError(f"column map entry {it!r} names no column of the file")
        out[k.strip()] = v.strip()
    return out


def euler_to_quat(angles: torch.Tensor, seq: str) -> torch.Tensor:
    """``(N, 3)`` rad in the order of ``seq`` (scipy's convention) → ``(N, 4)`` unit quaternions
    ``(w, x, y, z)``, ``w ≥ 0``."""
    R = [_ROT[a.lower()](angles[:, i]) for i, a in enumerate(seq)]
    M = R[0] @ R[1] @ R[2] if seq.isupper() else R[2] @ R[1] @ R[0]
    return matrix_to_quat(M)


def translate(path, header: list[str], rows: list[list[str]], fmt: InstrumentFormat
              ) -> tuple[list[str], list[list[str]]]:
    """The header and rows of torchcal's CSV from those of an export written as ``fmt`` says:
    columns renamed or left out, decimal commas read, Euler columns replaced by quaternions.
    Every cell stays text, for the reader's own checks."""
    header, rows = _renamed(path, header, rows, fmt)
    if fmt.decimal == ",":
        rows = [[c.replace(",", ".") for c in r] for r in rows]
    return _quaternions(path, header, rows, fmt)


def _renamed(path, header, rows, fmt: InstrumentFormat):
    missing = [k for k in fmt.columns if k not in header]
    if missing:
        raise ValueError(f"{path}: column map names {missing}, which the file does not have; its columns are {header}")
    names = [fmt.columns.get(h, h) for h in header]
    if fmt.strip_prefix:
        names = [n[len(fmt.strip_prefix):] if n.startswith(fmt.strip_prefix) else n for n in names]
    keep = [i for i, n in enumerate(names) if n]
    names = [names[i] for i in keep]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{path}: after the column map and prefix, column(s) {dup} appear twice; map one of them "
                         "to another name, or to '' to leave it out")
    return names, [[r[i] for i in keep] for r in rows]


def _quaternions(path, header, rows, fmt: InstrumentFormat):
    markers = [h[: -len(EULER_COLUMNS[0])] for h in header if h.endswith(EULER_COLUMNS[0])]
    if not markers:
        return header, rows
    if fmt.euler is None:
        raise ValueError(f"{path}: column(s) {[m + '.rx' for m in markers]} hold Euler angles, whose sequence must be "
                         "stated: euler='XYZ' (intrinsic x, then y, then z, as scipy's from_euler('XYZ')) or 'xyz' "
                         "(extrinsic, roll-pitch-yaw), or --euler on the command line")
    scale = math.pi / 180 if fmt.rot_units == "deg" else 1.0
    for m in markers:
        cols = [m + s for s in EULER_COLUMNS]
        lack = [c for c in cols if c not in header]
        if lack or any(m + s in header for s in QUAT):
            raise ValueError(f"{path}: marker {m!r} needs all of {cols} and no quaternion columns"
                             + (f"; missing {lack}" if lack else ""))
        idx = [header.index(c) for c in cols]
        vals = torch.tensor([[number_cell(r[j], i + 2, header[j], path) for j in idx] for i, r in enumerate(rows)],
                            dtype=torch.float64)
        seen = torch.isfinite(vals).all(1)
        q = torch.full((len(rows), 4), math.nan, dtype=torch.float64)
        if seen.any():
            q[seen] = euler_to_quat(vals[seen] * scale, fmt.euler)
        keep = [i for i in range(len(header)) if i not in idx]
        header = [header[i] for i in keep] + [m + s for s in QUAT]
        rows = [[r[i] for i in keep] + ["" if math.isnan(v) else repr(v) for v in q[k].tolist()]
                for k, r in enumerate(rows)]
    return header, rows


