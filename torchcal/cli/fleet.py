"""``torchcal fleet``: calibrate every robot of one model from a folder of measurement CSVs.

One CSV per robot (the robot id is the file's stem), in the format ``torchcal calibrate`` reads.
Writes ``OUT/<robot>/calibrated.urdf``, ``report.md``, ``report.json`` and ``OUT/fleet.md``,
``OUT/fleet.json`` (the spread of every parameter over the fleet, and the robots flagged).
"""
from __future__ import annotations

import argparse
import glob
import logging
import os
import time
from pathlib import Path

import torch

from torchcal.cli.conventions import add_progress, progress_on
from torchcal.cli.common import (add_common, inputs_of, int_at_least, positive_float, probability, robot_for,
                                 run_record)
from torchcal.pipelines.fleet.run import calibrate_fleet
from torchcal.pipelines.fleet.spread import FALSE_ALARM
from torchcal.report.fleet import save_fleet
from torchcal.measure.io import UnitsError, load_measurements, read_csv
from torchcal.outputs import check_out_dir, staged_dir
from torchcal.kinematics.urdf import load_joints

__all__ = ["add_fleet_parser", "fleet_main", "fleet_files"]

logger = logging.getLogger("torchcal")


def fleet_files(spec: str) -> list[Path]:
    """The CSV files of a fleet: every ``*.csv`` in a directory, or the files a glob matches."""
    p = Path(spec)
    # .CSV as Windows tools write it is a CSV too
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() == ".csv") if p.is_dir() else \
        sorted(Path(f) for f in glob.glob(spec) if f.lower().endswith(".csv"))
    if not files:
        where = f"the directory {spec}" if p.is_dir() else f"{spec!r}"
        raise ValueError(f"no CSV files in {where}; give a directory of <robot>.csv files or a glob such as "
                         "'data/*.csv' (quote it so the shell does not expand it)")
    stems = [f.stem for f in files]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ValueError(f"robot ids must be unique, but several files are named {dup[:5]}; rename them")
    return files


def _same_joints(files: list[Path], urdf: str) -> None:
    """Refuse a fleet whose files name different joints: they are not one robot model."""
    _, joints, _ = load_joints(urdf)
    known = {j.name for j in joints}
    first = None
    for f in files:
        header, _ = read_csv(f)
        cols = sorted(c for c in header if c in known)
        if first is None:
            first = (f, cols)
        elif cols != first[1]:
            raise ValueError(f"{f.name} has joint columns {cols} but {first[0].name} has {first[1]}; every file of a "
                             "fleet must come from the same robot model (same joint columns)")


def _load_all(files: list[Path], robot, units: list[str]) -> dict:
    """Robot id -> measurements (m, rad) of every file; a file in other units than the rest is
    named, with the reminder that ``--units`` holds for every file of the fleet."""
    out = {}
    for f in files:
        try:
            out[f.stem] = load_measurements(f, robot, units=units)
        except UnitsError as e:
            raise UnitsError(f"{e}. --units applies to every file of the fleet: convert the files that differ, so "
                             "that all share one unit") from None
    return out


class _robot_bar:
    """A context giving ``tick(robot_id)``: a tqdm bar over the robots written (with ``on``),
    else a log line at each tenth of the fleet, so that a long write shows it is moving."""

    def __init__(self, on: bool, n: int):
        self.on, self.n, self.i, self.bar = on, n, 0, None

    def __enter__(self):
        if self.on:
            from tqdm.auto import tqdm
            self.bar = tqdm(total=self.n, desc="fleet: writing robots", unit="robot")
        return self.tick

    def tick(self, name: str) -> None:
        self.i += 1
        if self.bar is not None:
            self.bar.set_postfix_str(name, refresh=False)
            self.bar.update(1)
        elif self.i == self.n or self.i % max(1, self.n // 10) == 0:
            logger.info(f"  wrote {self.i}/{self.n} robots (last: {name})")

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def add_fleet_parser(sub) -> argparse.ArgumentParser:
    """Add the ``fleet`` sub-command to an ``argparse`` sub-parser set."""
    f = sub.add_parser("fleet", help="calibrate many robots of one model in one batched solve",
                       description="Calibrate every robot of one model: one CSV per robot (robot id = file stem). "
                                   "Writes OUT/<robot>/calibrated.urdf, report.md/json and OUT/fleet.md/json.")
    f.add_argument("--robot", required=True, help="URDF file of the model")
    f.add_argument("--data", required=True, help="directory of <robot>.csv files, or a glob ('data/*.csv')")
    f.add_argument("--test", help="held-out CSVs, named like the training files (directory or glob)")
    f.add_argument("--marker", action="append", help="LINK or NAME@LINK[=x,y,z] (m); repeatable")
    f.add_argument("--prior", choices=["fleet"], help="hierarchical prior: each robot's errors around the fleet mean")
    f.add_argument("--effect", action="append", choices=["joint_compliance"],
                   help="fit joint compliance per robot (needs URDF inertials)")
    f.add_argument("--payload", choices=["shared", "per_robot"], default="shared",
                   help="with --effect: one unknown payload for the fleet, or one per robot")
    f.add_argument("--z", type=positive_float, default=5.0,
                   help="flag a robot's parameter this many standard deviations from its siblings")
    f.add_argument("--false-alarm", type=probability, default=FALSE_ALARM,
                   help="chance that a fleet of healthy robots raises any flag; with few robots it raises the bound "
                        "above --z")
    f.add_argument("--min-rows", type=int_at_least(1), default=3, help="refuse robots with fewer rows")
    f.add_argument("--ray", metavar="ADDRESS", help="run on Ray: 'local' (in-process), 'auto' or ray://host:port "
                                                   "(pip install torchcal[ray])")
    f.add_argument("--shards", type=int_at_least(1), help="with --ray: how many tasks the fleet is cut into")
    f.add_argument("--no-figures", action="store_true", help="skip the error histograms per robot")
    f.add_argument("--with-markers", action="store_true",
                   help="add a fixed link marker_<name> per measured point to each robot's calibrated URDF")
    f.add_argument("--out", required=True, help="output directory (refused if it holds anything; see --force)")
    f.add_argument("--plausible-mm", type=positive_float, default=10.0,
                   help="largest plausible shift of a joint origin (mm): a robot's parameter its data pin down worse "
                        "than this is fixed")
    f.add_argument("--plausible-mrad", type=positive_float, default=10.0,
                   help="largest plausible turn of a joint origin or zero offset (mrad)")
    add_progress(f, "the robots (their reports and figures written after the batched solve)")
    add_common(f)
    f.set_defaults(func=fleet_main)
    return f


def fleet_main(a: argparse.Namespace, argv: list[str] | None = None) -> int:
    """Run ``torchcal fleet`` with parsed arguments (see :func:`add_fleet_parser`)."""
    check_out_dir(a.out, a.force, inputs_of(a))
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    units = list(a.units or [])
    files = fleet_files(a.data)
    _same_joints(files, a.robot)
    robot = robot_for(a.robot, a.marker, files[0], units)
    data = _load_all(files, robot, units)
    test_files = fleet_files(a.test) if a.test else []
    test = _load_all(test_files, robot, units) or None
    logger.info(f"read {len(data)} robots ({sum(len(d) for d in data.values())} rows"
                + (f", {len(test)} held-out files" if test else "") + f") in {time.perf_counter() - t0:.1f} s; "
                "calibrating them in one batched solve" + (f" on Ray ({a.ray})" if a.ray else "") + " …")
    fr = calibrate_fleet(robot, data, test=test, prior=a.prior, effects=a.effect, payload=a.payload,
                         z_threshold=a.z, false_alarm=a.false_alarm, min_rows=a.min_rows, ray=a.ray,
                         ray_shards=a.shards, plausible={"m": a.plausible_mm * 1e-3, "rad": a.plausible_mrad * 1e-3})
    inputs = {"urdf": a.robot, **{f"data:{f.stem}": f for f in files}, **{f"test:{f.stem}": f for f in test_files}}
    logger.info(f"calibrated {len(fr)} robots in {fr.wall_time_s:.2f} s; writing each robot's report"
                + (" and figures" if not a.no_figures else "") + " …")
    with staged_dir(a.out, a.force) as d, _robot_bar(progress_on(a), len(fr)) as tick:
        save_fleet(fr, d, figures=not a.no_figures, on_robot=tick, with_markers=a.with_markers)
        run_record(a, d, inputs, list(argv or []))
    out = Path(a.out)
    print(f"{robot.name}: {len(fr)} robots calibrated in {fr.wall_time_s:.2f} s (all told "
          f"{time.perf_counter() - t0:.1f} s, reports included); wrote {out}{os.sep}<robot>/ and "
          f"{out / 'fleet.md'}")
    gross = {n: len(r.suspects) for n, r in zip(fr.names, fr.results) if r.suspects}
    if gross:
        print(f"gross errors left out of the fit (listed in each robot's report): {gross}")
    if fr.flags:
        print(f"{len(fr.flags)} flag(s) (robust |z| > {a.z:g}):")
        for fl in fr.flags[:20]:
            print(f"  {fl['robot']}: {fl['parameter']} z = {fl['z']:+.1f}")
    else:
        print("no robot stands out")
    return 0
