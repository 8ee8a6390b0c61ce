"""The options that say how a measurement file is written when it is an instrument's own export,
taken by every command that reads measurements: ``--sep``, ``--decimal``, ``--rot-units``,
``--euler``, ``--column-map``, ``--strip-prefix`` (positions in millimetres are ``--units mm``)."""
from __future__ import annotations

import argparse

from torchcal.measure.instrument import ROT_UNITS, InstrumentFormat, parse_column_map

__all__ = ["add_format_options", "format_of"]

_SEPS = {"tab": "\t", "\\t": "\t", "comma": ",", "semicolon": ";"}


def _sep(text: str) -> str:
    s = _SEPS.get(text, text)
    if len(s) != 1:
        raise argparse.ArgumentTypeError(f"a separator is one character (',', ';', 'tab'), got {text!r}")
    return s


def add_format_options(p: argparse.ArgumentParser) -> None:
    """The options that say how a measurement file is written, when it is an instrument's export."""
    g = p.add_argument_group("instrument export", "read an instrument's own file as it is (positions in mm: --units mm)")
    g.add_argument("--sep", type=_sep, default=",", help="cell separator: ',' (default), ';' or 'tab'")
    g.add_argument("--decimal", choices=(".", ","), default=".", help="decimal mark of the numbers (default '.')")
    g.add_argument("--rot-units", choices=ROT_UNITS, default="rad",
                   help="unit of the Euler angle columns <marker>.rx/.ry/.rz (default rad)")
    g.add_argument("--euler", help="Euler sequence of the <marker>.rx/.ry/.rz columns, as scipy's from_euler: upper "
                                   "case intrinsic ('XYZ': about x, then the new y, then the newest z), lower case "
                                   "extrinsic ('xyz': roll-pitch-yaw about the fixed axes). Required with Euler columns")
    g.add_argument("--column-map", action="append", default=[], metavar="FILE_COLUMN=NAME",
                   help="rename a column of the file to torchcal's name (measurement_x=tmac.x, measurement_rx=tmac.rx); "
                        "'COLUMN=' leaves it out. Repeatable")
    g.add_argument("--strip-prefix", default="", metavar="PREFIX",
                   help="take PREFIX off the column names that start with it (ur_shoulder_pan_joint -> "
                        "shoulder_pan_joint with --strip-prefix ur_)")


def format_of(a: argparse.Namespace) -> InstrumentFormat | None:
    """The :class:`InstrumentFormat` the options describe; None for torchcal's own CSV."""
    if not hasattr(a, "sep"):
        return None
    fmt = InstrumentFormat(sep=a.sep, decimal=a.decimal, rot_units=a.rot_units, euler=a.euler,
                           columns=parse_column_map(a.column_map), strip_prefix=a.strip_prefix)
    return None if fmt.is_plain else fmt
