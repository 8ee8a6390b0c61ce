"""``torchcal import``: an instrument's own export (``;``-separated, decimal commas, millimetres,
Euler angles in degrees) written once as torchcal's CSV, checked against the robot as every
command checks it."""
from __future__ import annotations

import argparse

from torchcal.cli.common import add_common, robot_for
from torchcal.cli.formats import add_format_options, format_of
from torchcal.measure.io import load_measurements, save_measurements
from torchcal.outputs import check_out_file

__all__ = ["add_import_parser", "import_main"]


def add_import_parser(sub) -> argparse.ArgumentParser:
    """Add ``torchcal import``: an instrument's export written once as torchcal's CSV (m, rad,
    quaternions), checked against the robot as every command checks it."""
    p = sub.add_parser("import", help="an instrument's export (';', decimal commas, mm, Euler angles) as torchcal's CSV",
                       description="Read an instrument's own export with the stated separator, decimal mark, units, "
                                   "Euler convention and column names, check it against the robot, and write it as "
                                   "torchcal's CSV (m, rad, quaternions qw/qx/qy/qz).")
    p.add_argument("export", help="the instrument's file")
    p.add_argument("--robot", required=True, help="URDF file (the joint columns must name its joints)")
    p.add_argument("--marker", action="append", help="measured frame: LINK or NAME@LINK[=x,y,z] (m); repeatable")
    p.add_argument("--out", required=True, help="torchcal CSV to write (refused if it exists; see --force)")
    add_format_options(p)
    add_common(p)
    p.set_defaults(func=import_main)
    return p


def import_main(a: argparse.Namespace, argv: list[str] | None = None) -> int:
    out = check_out_file(a.out, a.force, inputs=(a.export,))
    fmt = format_of(a)
    units = list(a.units or [])
    robot = robot_for(a.robot, a.marker, a.export, units, fmt)
    data = load_measurements(a.export, robot, units=units, fmt=fmt)
    save_measurements(out, data)
    extra = f", orientations of {', '.join(data.marker_names)}" if data.quaternions is not None else ""
    print(f"wrote {len(data)} rows to {out}: joints {', '.join(data.joint_names)}, markers "
          f"{', '.join(data.marker_names)} (m{extra}), covariates {', '.join(data.covariates) or 'none'}")
    return 0
