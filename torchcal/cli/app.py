"""Command line: ``torchcal calibrate | loop | simulate | correct | plan | fleet`` (also ``python -m torchcal``).

Every command claims its output (a second run on it is refused), refuses to overwrite what exists
(``--force`` replaces an earlier torchcal result, never an input), checks that its output can be
written before it works, writes under temporary names, and records in each output
directory the exact options (``run.yaml``, which ``--config`` reads back) and the provenance of
the result (``provenance.json``). Messages go to stderr through :mod:`logging` (``--quiet``,
``--verbose``); tables and results to stdout.
"""
from __future__ import annotations

import argparse
import errno
import logging
import shlex
import sys
import time
from pathlib import Path

import torch

from torchcal.advice import cli_wording
from torchcal.cli.bag import add_bag_parser
from torchcal.cli.common import (add_common, expand_config, fraction, inputs_of, int_at_least, join_negative_values,
                                 positive_float,
                                 nonnegative_float, parse_markers, report_failure, robot_and_data, run_record,
                                 setup_logging)
from torchcal.cli.conventions import (DefaultsFormatter, add_progress, method_choice, method_help, progress_on,
                                      renamed)
from torchcal.cli.correct import add_correct_parser
from torchcal.cli.runtime import StdoutLost, Terminated, command_runtime, stdout_lost_message, terminated
from torchcal.cli.strict import check_command_line, strict_parsers
from torchcal.cli.fleet import add_fleet_parser
from torchcal.cli.formats import add_format_options
from torchcal.cli.instrument import add_import_parser
from torchcal.cli.plan import add_plan_parser
from torchcal.deploy.persist import save
from torchcal.effects import EFFECTS
from torchcal.environment import NOTES
from torchcal.kinematics.robot import Robot
from torchcal.outputs import check_out_dir, check_out_file, claim, staged_dir
from torchcal.measure.records import Stage
from torchcal.optim import is_population, solvers
from torchcal.pipelines.calibrate import calibrate
from torchcal.pipelines.calibration_result import write_instrument
from torchcal.pipelines.loop.run import run_loop
from torchcal.report.calibration import save_calibration
from torchcal.report.loop import loop_json, write_loop_report
from torchcal.sim.serial import SimConfig, simulate_with_effects, write_dataset
from torchcal.threads import set_threads
from torchcal.version import __version__

__all__ = ["main", "build_parser"]

logger = logging.getLogger("torchcal")
EXIT_IOERR = 74  # EX_IOERR of sysexits.h: the run worked, its standard output failed


def _print_stages(stages: list[Stage], has_test: bool) -> None:
    """The per-stage error table both commands print (mm)."""
    w = max(12, max(len(s.name) for s in stages) + 2)
    cols = ["train mean", "train max"] + (["test mean", "test max"] if has_test else [])
    print(f"\n{'stage':<{w}}{'params':>7}" + "".join(f"{c:>12}" for c in cols))
    for s in stages:
        vals = [s.train.mean, s.train.max] + ([s.test.mean, s.test.max] if has_test else [])
        print(f"{s.name:<{w}}{s.n_params:>7}" + "".join(f"{v:>12.4f}" for v in vals) + "   [mm]")


def _inputs(a) -> dict:
    return {"urdf": a.robot, "data": a.data, "test": getattr(a, "test", None)}


def _refuse(cmd: str, problems: list[str]) -> int:
    for p in problems:
        print(f"torchcal {cmd}: error: {p}", file=sys.stderr)
    print(f"torchcal {cmd}: nothing was written", file=sys.stderr)
    return 2


def _calibrate(a, argv) -> int:
    check_out_dir(a.out, a.force, inputs_of(a))
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    robot, train, test = robot_and_data(a)
    progress = a.progress if a.progress is not None else (is_population(a.method) and progress_on(a))
    res = calibrate(robot, train, test=test, method=a.method, kind=a.kind, loss=a.loss, seed=a.seed,
                    progress=progress, polish=a.polish, free=a.free or None, plausible=_plausible(a),
                    prior=None if a.prior == "none" else a.prior)
    logger.info(f"calibration done in {time.perf_counter() - t0:.1f} s")
    if res.problems():
        return _refuse("calibrate", res.problems())
    out = save_calibration(res, a.out, force=a.force, with_instrument=a.with_instrument, with_markers=a.with_markers,
                           extra=lambda d: run_record(a, d, _inputs(a), argv))
    print(f"{robot.name}: {res.n_train} training rows" + (f", {res.n_test} held out" if res.n_test else ""))
    _print_stages(res.stages, test is not None)
    print(f"{len(res.unidentifiable)} parameters not identifiable (see {out / 'report.md'}); wrote {out}/")
    if res.suspects:
        print(f"{len(res.suspects)} gross error(s) left out of the fit, listed in the report (kept in the data and the "
              "statistics): rows " + ", ".join(str(s.row) for s in res.suspects[:10]))
    return 0


def _plausible(a) -> dict:
    """The largest plausible joint error per unit (m, rad) from --plausible-mm / --plausible-mrad."""
    return {"m": a.plausible_mm * 1e-3, "rad": a.plausible_mrad * 1e-3}


def _loop(a, argv) -> int:
    if a.effect and "none" in a.effect and len(set(a.effect)) > 1:
        others = sorted(set(a.effect) - {"none"})
        raise ValueError(f"--effect none (the geometry alone) cannot go with other effects {others}; give either")
    check_out_dir(a.out, a.force, inputs_of(a))
    torch.set_num_threads(a.threads)
    robot, train, test = robot_and_data(a)
    effects = None if a.effect is None else [e for e in a.effect if e != "none"]
    res = run_loop(robot, train, test, candidates=effects, folds=a.folds, seed=a.seed, elm=not a.no_elm,
                   noise_mm=a.noise_floor_mm, orientation_weight=a.orientation_weight, soft=not a.no_soft,
                   plausible=_plausible(a), progress=progress_on(a), log=None, reregister=a.reregister)
    for k, v in res.timings.items():
        logger.info(f"stage {k}: {v:.1f} s")
    if res.problems():
        return _refuse("loop", res.problems())

    cmd = "torchcal " + " ".join(shlex.quote(x) for x in argv) if a.command is None else a.command
    with staged_dir(a.out, a.force) as d:
        write_loop_report(res, d, command=cmd)
        geo = robot.params(res.params.values[: robot.n_params])
        note = None
        if res.effects:
            note = ("geometric part only: the calibrated model also applies " + "; ".join(
                f"{e.name} ({', '.join(lab for lab, _ in e.modes())})" for e in res.effects) +
                ". Those act through the saved model (torchcal.load('model'), torchcal correct), not through "
                "this URDF")
        se = {p["name"]: p.get("std_error") for p in res.parameters if p.get("std_error") is not None}
        robot.export_calibration(geo, d, with_instrument=a.with_instrument, note=note, with_markers=a.with_markers,
                                 std_errors=se)
        write_instrument(robot, geo, d / "instrument.json")
        prov = run_record(a, d, _inputs(a), argv)
        model = res.model(meta={"report": loop_json(res)})
        model.meta.update({"provenance": prov, "options": (d / "run.yaml").read_text()})
        save(model, d / "model")
    out = Path(a.out)
    _print_stages(res.stages, test is not None)
    if res.heldout is not None and res.heldout.reregistered_mm is not None:
        print(f"held out: {res.heldout.final_mm:.4f} mm as measured, {res.heldout.reregistered_mm:.4f} mm with the "
              "instrument frame registered anew on the held-out rows (mean)")
    found = list(dict.fromkeys(e["name"] for e in res.accepted))  # an effect that gained modes later: once
    print(f"effects found: {found or 'none'}; report in {out / 'report.md'}; calibrated "
          f"URDF {out / 'calibrated.urdf'}" + (" (geometric part)" if res.effects else "") + f"; model in {out / 'model'}")
    if res.suspects:
        print(f"{len(res.suspects)} suspect observation(s), listed in the report (kept in the data)")
    return 0


def _simulate(a, argv) -> int:
    out = Path(a.out)
    truth = out.with_suffix(".truth.json")
    for p in (out, truth):
        check_out_file(p, a.force, inputs=inputs_of(a))
    torch.set_num_threads(1)
    robot = Robot.from_urdf(a.robot, markers=parse_markers(a.marker, None) if a.marker else None)
    cfg = SimConfig(n=a.poses, noise=a.noise_mm * 1e-3, base_distance=a.base_distance, seed=a.seed,
                    length_error=a.length_error_mm * 1e-3, angle_error=a.angle_error_mrad * 1e-3)
    data, tr, effects = simulate_with_effects(robot, cfg, a.effect)
    before = {p: p.stat().st_ino if p.exists() else None for p in (out, truth)}
    try:
        write_dataset(out, data, tr, meta={"noise_mm": a.noise_mm, "seed": a.seed, "effects": effects})
    except BaseException:
        for p, ino in before.items():  # the data without its truth is half a result: remove what this run wrote
            if p.exists() and p.stat().st_ino != ino:
                p.unlink()
        raise
    print(f"wrote {len(data)} rows to {out} and the truth to {truth} (keep it away from the solver)")
    return 0


def _data_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", required=True, help="URDF file")
    p.add_argument("--data", required=True, help="training CSV: joint columns (rad / m) + <marker>.x/.y/.z (m)")
    p.add_argument("--test", help="held-out CSV (measured only, never fitted)")
    p.add_argument("--holdout", type=fraction, default=0.0, help="without --test: fraction of rows held out")
    p.add_argument("--marker", action="append", help="measured frame: LINK or NAME@LINK[=x,y,z] (m); repeatable. "
                                                     "Default: the marker columns of --data that are link names")
    p.add_argument("--seed", type=int, default=0, help="seeds every random choice (the --holdout split, the solver, "
                                                        "the folds): the same seed gives the same result")
    p.add_argument("--with-instrument", action="store_true",
                   help="calibrated URDF rooted in the instrument frame (default: the robot's own root; the "
                        "registration goes to instrument.json)")
    p.add_argument("--with-markers", action="store_true",
                   help="add a fixed link marker_<name> per measured point to the calibrated URDF (without it the "
                        "URDF differs from the input only in the joint origins the calibration changed)")
    p.add_argument("--plausible-mm", type=positive_float, default=10.0,
                   help="largest plausible shift of a joint origin (mm); a model needing more is refused")
    p.add_argument("--plausible-mrad", type=positive_float, default=10.0,
                   help="largest plausible turn of a joint origin or zero offset (mrad)")
    p.add_argument("--out", required=True, help="output directory (refused if it holds anything; see --force)")
    add_format_options(p)
    add_common(p)


def build_parser() -> tuple[argparse.ArgumentParser, dict]:
    ap = argparse.ArgumentParser(prog="torchcal", description="Robot calibration on torch tensors.",
                                 formatter_class=DefaultsFormatter)
    ap.add_argument("--version", action="version", version=f"torchcal {__version__} (torch {torch.__version__})")
    sub = ap.add_subparsers(dest="cmd", required=True)

    c = sub.add_parser("calibrate", help="identify geometric errors from a measurement CSV")
    c.add_argument("--method", default="lm", choices=list(solvers()), type=method_choice(solvers()), metavar="METHOD",
                   help=method_help(solvers(), list(solvers(population=True))))
    c.add_argument("--kind", default="position", choices=["position", "pose"],
                   help="what is fitted: marker positions only, or positions and orientations (the data's "
                        "<marker>.qw/.qx/.qy/.qz columns)")
    c.add_argument("--loss", default="l2", choices=["l2", "huber", "cauchy"],
                   help="l2: least squares; huber, cauchy: robust losses whose scale follows the residuals (outliers "
                        "pull less)")
    c.add_argument("--free", action="append", help="glob pattern of parameters to identify (repeatable)")
    c.add_argument("--polish", action="store_true",
                   help="after a population method, polish its best with LM (the result is then named e.g. pso+lm)")
    add_progress(c, "the iterations of a population method (LM's few iterations show none)")
    c.add_argument("--prior", default="auto", choices=["auto", "cv", "none"],
                   help="Gaussian prior on the geometric errors, its scale chosen by cross-validation: 'auto' on "
                        "small data (< 10 values per parameter) or when a joint would move implausibly; 'cv' always; "
                        "'none' never")
    _data_options(c)
    c.set_defaults(func=_calibrate)

    lp = sub.add_parser("loop", help="calibrate, trace the residual to the effect the model lacks, add it, report")
    lp.add_argument("--effect", action="append", choices=sorted(EFFECTS) + ["none"], metavar="EFFECT",
                    help="an effect to consider (repeatable; 'none': the geometry only). Without it: every effect the "
                         f"data allows: {', '.join(sorted(EFFECTS))}")
    renamed(lp, "--candidates", "--effect", "give each effect as --effect NAME (repeatable), as plan and fleet take "
            "them; '--effect none' for the geometry only", nargs="*")
    lp.add_argument("--folds", type=int_at_least(2), default=5, help="cross-validation folds (≥ 2)")
    add_progress(lp, "the candidate effects of each round")
    lp.add_argument("--noise-floor-mm", type=nonnegative_float,
                    help="the mean Euclidean error a perfect model would leave (mm; for an instrument of per-axis "
                         "standard deviation s, about 1.596 s), to judge what is left. Default: from rows that repeat a "
                         "command, or a marker_std_mm column; else none is known")
    renamed(lp, "--noise-mm", "--noise-floor-mm", "in loop it meant the mean error a perfect model leaves; --noise-mm "
            "now means a per-axis standard deviation everywhere (simulate, plan)")
    lp.add_argument("--no-elm", action="store_true", help="skip the residual ELM stage")
    lp.add_argument("--orientation-weight", type=nonnegative_float,
                    help="m/rad: how a measured orientation error counts against a position error (σ_position / "
                         "σ_rotation); default estimated from the residuals when the data has <marker>.qw…; 0 ignores "
                         "orientations")
    lp.add_argument("--no-soft", action="store_true",
                    help="choose a family's modes one by one only (default: a family may also be kept whole under a "
                         "prior whose scale cross-validation chooses)")
    lp.add_argument("--reregister", action="store_true",
                    help="register the instrument frame anew on the held-out rows (--test from another session, the "
                         "tracker set up anew) and report that figure beside the first")
    lp.add_argument("--command", help=argparse.SUPPRESS)
    _data_options(lp)
    lp.set_defaults(func=_loop)

    s = sub.add_parser("simulate", help="simulate laser-tracker measurements with geometric errors")
    s.add_argument("--robot", required=True, help="URDF file of the nominal robot")
    s.add_argument("--marker", action="append", help="measured frame: LINK or NAME@LINK[=x,y,z] (m); repeatable. "
                                                     "Default: every leaf link")
    s.add_argument("--poses", type=int_at_least(1), default=100, help="measured poses (rows), drawn in the joint limits")
    s.add_argument("--noise-mm", type=nonnegative_float, default=0.02,
                   help="instrument noise: standard deviation per axis (mm)")
    s.add_argument("--length-error-mm", type=nonnegative_float, default=0.5,
                   help="standard deviation of the simulated joint-origin shifts (mm)")
    s.add_argument("--angle-error-mrad", type=nonnegative_float, default=1.0,
                   help="standard deviation of the simulated joint-origin turns and zero offsets (mrad)")
    s.add_argument("--base-distance", type=nonnegative_float, default=3.0, help="instrument distance from the base (m)")
    s.add_argument("--effect", action="append", default=[], help="physical effect to simulate (repeatable): "
                   "joint_compliance, backlash, cyclic_joint_error, joint_scale, thermal_drift")
    s.add_argument("--seed", type=int, default=0, help="seeds the robot's errors, the poses and the noise")
    s.add_argument("--out", required=True, help="CSV path; the truth goes beside it as .truth.json")
    add_common(s, units=False)
    s.set_defaults(func=_simulate)

    add_correct_parser(sub)
    add_plan_parser(sub)
    add_fleet_parser(sub)
    add_bag_parser(sub)
    add_import_parser(sub)
    for p in sub.choices.values():  # every command's --help shows every default
        p.formatter_class = DefaultsFormatter
    strict_parsers(ap, sub.choices)
    return ap, sub.choices


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap, sub = build_parser()
    own = join_negative_values(argv, sub)  # the user's own command line, without --config's options
    try:
        argv = expand_config(argv, sub)
    except SystemExit as e:
        print(e, file=sys.stderr)
        return 2
    a = ap.parse_args(join_negative_values(argv, sub))
    problem = check_command_line(own[1:], a, sub[a.cmd])
    if problem:
        print(f"torchcal {a.cmd}: error: {problem}", file=sys.stderr)
        return 2
    setup_logging(a)
    for note in NOTES:
        logger.warning(f"torchcal {a.cmd}: warning: {note}")
    # each command sets torch's threads from --threads; the library's own choice would override it
    threads, choice = torch.get_num_threads(), set_threads("caller")
    try:
        with cli_wording(), command_runtime(), claim(a.out):  # a second run on the same output is refused at once
            return a.func(a, argv)
    except StdoutLost as e:
        print(stdout_lost_message(a.cmd, e, getattr(a, "out", None)), file=sys.stderr)
        return 0 if e.errno == errno.EPIPE else EXIT_IOERR
    except KeyboardInterrupt as e:
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        print(f"torchcal {a.cmd}: {how}; nothing was written", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except Exception as e:  # a refusal (exit 2) or a bug (exit 70): cli/common.py says which is which
        if terminated():  # the interrupt, come out as another error (a library cut short in its import)
            print(f"torchcal {a.cmd}: terminated (SIGTERM); nothing was written", file=sys.stderr)
            return 143
        return report_failure(a.cmd, e, getattr(a, "verbose", False), getattr(a, "out", None))
    finally:
        set_threads(choice)
        torch.set_num_threads(threads)


if __name__ == "__main__":
    raise SystemExit(main())
