"""Command line: ``torchcal calibrate``, ``loop``, ``simulate``, ``correct`` and ``fleet``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _robot(urdf: str, markers: list[str] | None, data_csv: str | None):
    from .io import _read_csv, marker_columns_in
    from .robot import Robot
    from .urdf import urdf_links

    if not markers:
        if data_csv is None:
            raise SystemExit("give --marker (a link name or NAME@LINK=x,y,z)")
        header, _ = _read_csv(data_csv)
        cols = marker_columns_in(header)
        links = set(urdf_links(urdf))
        unknown = [c for c in cols if c not in links]
        if unknown:
            raise SystemExit(f"marker column(s) {unknown} are not links of {urdf}; declare each as an unknown point "
                             f"on a link, e.g. --marker {unknown[0]}@LINK or --marker {unknown[0]}@LINK=0.05,0,0.1 (m)")
        if not cols:
            raise SystemExit(f"{data_csv} has no '<marker>.x/.y/.z' columns")
        markers = cols
    return Robot.from_urdf(urdf, markers=markers)


def _load(a):
    """Robot, training and held-out data from the common options."""
    import torch

    from .io import load_measurements

    torch.set_num_threads(a.threads)
    robot = _robot(a.robot, a.marker, a.data)
    train = load_measurements(a.data, robot)
    test = load_measurements(a.test, robot) if a.test else None
    if test is None and a.holdout:
        train, test = train.split(a.holdout, seed=a.seed)
    return robot, train, test


def _print_stages(stages: list[dict], has_test: bool) -> None:
    """The per-stage error table both commands print (mm)."""
    w = max(12, max(len(s["name"]) for s in stages) + 2)
    cols = ["train mean", "train max"] + (["test mean", "test max"] if has_test else [])
    print(f"\n{'stage':<{w}}{'params':>7}" + "".join(f"{c:>12}" for c in cols))
    for s in stages:
        vals = [s["train"]["mean_mm"], s["train"]["max_mm"]]
        if has_test:
            vals += [s["test"]["mean_mm"], s["test"]["max_mm"]]
        print(f"{s['name']:<{w}}{s['n_params']:>7}" + "".join(f"{v:>12.4f}" for v in vals) + "   [mm]")


def _calibrate(a) -> int:
    from .calibrate import SWARM_METHODS, calibrate

    robot, train, test = _load(a)
    progress = a.progress if a.progress is not None else (a.method in SWARM_METHODS and sys.stderr.isatty())
    res = calibrate(robot, train, test=test, method=a.method, kind=a.kind, loss=a.loss, seed=a.seed,
                    progress=progress, polish=a.polish, free=a.free or None)
    out = res.save(a.out)
    print(f"{robot.name}: {res.n_train} training rows" + (f", {res.n_test} held out" if res.n_test else ""))
    _print_stages(res.stages, test is not None)
    print(f"{len(res.unidentifiable)} parameters not identifiable (see {out / 'report.md'}); wrote {out}/")
    return 0


def _loop(a) -> int:
    import shlex

    from .loop import run_loop
    from .loop_report import write_loop_report

    robot, train, test = _load(a)
    res = run_loop(robot, train, test, candidates=a.candidates, folds=a.folds, seed=a.seed, elm=not a.no_elm,
                   noise_mm=a.noise_mm)
    out = Path(a.out)
    cmd = "torchcal " + " ".join(shlex.quote(x) for x in sys.argv[1:]) if a.command is None else a.command
    write_loop_report(res, out, command=cmd)
    try:
        from .persist import save

        save(res.model(), out / "model")
        saved = f"; model in {out / 'model'}"
    except Exception as e:  # the report is still worth having
        saved = f"; the model could not be saved: {e}"
    _print_stages(res.stages, test is not None)
    print(f"effects found: {[e['name'] for e in res.accepted] or 'none'}; report in {out / 'report.md'}{saved}")
    return 0


def _simulate(a) -> int:
    import torch

    from .robot import Robot
    from .sim import SimConfig, simulate_with_effects, write_dataset

    torch.set_num_threads(1)
    robot = Robot.from_urdf(a.robot, markers=a.marker or None)
    cfg = SimConfig(n=a.poses, noise=a.noise_mm * 1e-3, base_distance=a.base_distance, seed=a.seed,
                    length_error=a.length_error_mm * 1e-3, angle_error=a.angle_error_mrad * 1e-3)
    data, truth, effects = simulate_with_effects(robot, cfg, a.effect)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_dataset(out, data, truth, meta={"noise_mm": a.noise_mm, "seed": a.seed, "effects": effects})
    print(f"wrote {len(data)} rows to {out} and the truth to {out.with_suffix('.truth.json')} (keep it away from the solver)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="torchcal", description="Robot calibration on torch tensors.")
    sub = ap.add_subparsers(dest="cmd", required=True)

    c = sub.add_parser("calibrate", help="identify geometric errors from a measurement CSV")
    c.add_argument("--robot", required=True, help="URDF file")
    c.add_argument("--data", required=True, help="training CSV: joint columns + <marker>.x/.y/.z in m")
    c.add_argument("--test", help="held-out CSV (measured only, never fitted)")
    c.add_argument("--holdout", type=float, default=0.0, help="without --test: fraction of rows held out")
    c.add_argument("--marker", action="append", help="measured frame: LINK or NAME@LINK[=x,y,z] (m); repeatable. "
                                                     "Default: the marker columns of --data that are link names")
    c.add_argument("--method", default="lm", choices=["lm", "gn", "lbfgs", "pso", "ldpso-bt", "cpso", "ga", "ma", "mma",
                                                      "hybrid"])
    c.add_argument("--kind", default="position", choices=["position", "pose"])
    c.add_argument("--loss", default="l2", choices=["l2", "huber", "cauchy"])
    c.add_argument("--free", action="append", help="glob pattern of parameters to identify (repeatable)")
    c.add_argument("--polish", action="store_true", help="after a swarm method, polish with LM")
    c.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress bar (default: on for swarm methods in a terminal)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--threads", type=int, default=1)
    c.add_argument("--out", required=True, help="output directory")
    c.set_defaults(func=_calibrate)

    lp = sub.add_parser("loop", help="calibrate, trace the residual to the effect the model lacks, add it, report")
    lp.add_argument("--robot", required=True, help="URDF file")
    lp.add_argument("--data", required=True, help="training CSV")
    lp.add_argument("--test", help="held-out CSV (only measured)")
    lp.add_argument("--holdout", type=float, default=0.0, help="without --test: fraction of rows held out")
    lp.add_argument("--marker", action="append", help="LINK or NAME@LINK[=x,y,z] (m); repeatable")
    lp.add_argument("--candidates", nargs="*", help="effects to consider (default: all the data allows)")
    lp.add_argument("--folds", type=int, default=5)
    lp.add_argument("--noise-mm", type=float, help="instrument noise for the report (mean error, mm)")
    lp.add_argument("--no-elm", action="store_true", help="skip the residual ELM stage")
    lp.add_argument("--seed", type=int, default=0)
    lp.add_argument("--threads", type=int, default=1)
    lp.add_argument("--command", help=argparse.SUPPRESS)
    lp.add_argument("--out", required=True, help="output directory (report, figures, model/)")
    lp.set_defaults(func=_loop)

    s = sub.add_parser("simulate", help="simulate laser-tracker measurements with geometric errors")
    s.add_argument("--robot", required=True)
    s.add_argument("--marker", action="append")
    s.add_argument("--poses", type=int, default=100)
    s.add_argument("--noise-mm", type=float, default=0.02)
    s.add_argument("--length-error-mm", type=float, default=0.5)
    s.add_argument("--angle-error-mrad", type=float, default=1.0)
    s.add_argument("--base-distance", type=float, default=3.0, help="instrument distance from the base (m)")
    s.add_argument("--effect", action="append", default=[], help="physical effect to simulate (repeatable): "
                   "joint_compliance, backlash, cyclic_joint_error, joint_scale, thermal_drift")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True, help="CSV path; the truth goes beside it as .truth.json")
    s.set_defaults(func=_simulate)

    from .cli_correct import add_correct_parser
    from .cli_fleet import add_fleet_parser

    add_correct_parser(sub)
    add_fleet_parser(sub)
    a = ap.parse_args(argv)
    try:
        return a.func(a)
    except (ValueError, FileNotFoundError, KeyError) as e:
        print(f"torchcal {a.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
