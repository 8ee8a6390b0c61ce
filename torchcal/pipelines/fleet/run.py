"""A fleet of robots of one model, calibrated in one batched solve.

The kinematics are batched over parameter populations; a fleet is such a population with its own
rows per member. :func:`calibrate_fleet` stacks every robot's measurements (ragged row counts
padded and masked), registers every instrument frame with one batched Kabsch, judges each robot's
identifiable parameters (:mod:`torchcal.pipelines.fleet.identify`), and fits all robots with one
block-diagonal Levenberg-Marquardt (:func:`~torchcal.optim.lm_batched.lm_batched`): each robot's
parameters, Jacobian, damping and stopping test are its own, and the result for each robot is what
``calibrate(robot, data, method="lm", prior=None)`` gives it. On top of that it reports how every parameter
spreads over the fleet and flags robots far from their siblings (:mod:`torchcal.pipelines.fleet.spread`),
and optionally couples the robots: a hierarchical prior around the fleet mean, joint compliance
with a payload shared by the fleet (:mod:`torchcal.pipelines.fleet.coupled`).

A fleet larger than one machine holds (:func:`calibrate_fleet_ray`, or ``calibrate_fleet(...,
ray=address)``): without a prior or a shared payload the robots are independent problems, so the
fleet splits into shards, each shard is one Ray task running the batched solve on its robots, and
the driver gathers the results and computes the fleet's parameter spread. Ray schedules the tasks,
moves the data and retries failed workers; nothing here queues jobs by hand. Ray is an optional
dependency (``pip install torchcal[ray]``), imported only when asked for.
"""
from __future__ import annotations

import os
import time
from dataclasses import fields, replace
from pathlib import Path

import torch

from torchcal.kinematics.robot import Robot
from torchcal.pipelines.fleet.coupled import solve_coupled
from torchcal.pipelines.fleet.data import (BASE_NAMES, FleetData, check_fleet_motion, gross_lists,
                                           register_fleet_robust, validate_fleet)
from torchcal.pipelines.fleet.independent import solve_independent
from torchcal.pipelines.fleet.options import FleetOptions
from torchcal.pipelines.fleet.result import FleetResult
from torchcal.pipelines.fleet.views import FleetResults
from torchcal.problems.template import candidate_template
from torchcal.pipelines.fleet.spread import FALSE_ALARM, parameter_spread
from torchcal.threads import threads_by_size

__all__ = ["calibrate_fleet", "FleetData", "FleetOptions", "validate_fleet"]

@threads_by_size("data", "test")
def calibrate_fleet(robot: Robot, data, *, names: list[str] | None = None, test=None,
                    settings: FleetOptions | None = None, **kw) -> FleetResult:
    """Calibrate ``R`` robots of one model in one batched solve.

    Args:
        robot: the model (:class:`~torchcal.kinematics.robot.Robot`) every robot is an instance of.
        data: one :class:`~torchcal.measure.io.Measurements` per robot (``q: (N_r, dof)`` rad, marker
            positions ``(N_r, M, 3)`` m in that robot's instrument frame; ``N_r`` may differ), as a
            list (ids from ``names``, default ``robot_000``…) or a dict id -> Measurements.
        test: held-out Measurements per robot (same form; missing robots allowed in a dict).
        settings: a :class:`~torchcal.pipelines.fleet.options.FleetOptions`; ``kw``: its fields
            (``prior``, ``effects``, ``identify``, ``plausible``, ``options`` …), overriding it.
    Returns:
        a :class:`FleetResult`.
    """
    t0 = time.perf_counter()
    opt = FleetOptions.build(settings, **kw)
    names, datasets, tests = validate_fleet(robot, data, names, test, opt.min_rows)
    opt = opt.checked(len(names))
    if opt.false_alarm is None:
        opt = replace(opt, false_alarm=FALSE_ALARM)
    if opt.ray is not None:
        return calibrate_fleet_ray(robot, dict(zip(names, datasets)), test=None if tests is None else
                                   {n: t for n, t in zip(names, tests) if t is not None}, address=opt.ray,
                                   shards=opt.ray_shards, **_fields(replace(opt, ray=None, ray_shards=None)))
    template = candidate_template(robot, datasets[0].marker_names, opt.params, opt.free)
    fd, fd_test = _batches(robot, names, datasets, tests, template)
    X0 = template.values.expand(len(names), -1).clone()
    gross = [[] for _ in names]
    if opt.register and bool(template.free[[robot.param_names.index(n) for n in BASE_NAMES]].any()):
        # a gross error (a glitch metres off) would drag its robot's frame, fit and noise: left out, listed
        X0, mask = register_fleet_robust(robot, fd, X0)
        if bool(mask.any()):
            gross = gross_lists(fd, mask, fd.errors(robot, X0), robot.marker_names)
            fd = replace(fd, seen=fd.seen & ~mask)
    solve = solve_coupled if opt.coupled else solve_independent
    sol = solve(robot, fd, template, X0, names, opt)
    results = FleetResults(robot, names, datasets, tests, fd, fd_test, template, X0, sol, time.perf_counter() - t0)
    results.suspects = gross  # per robot, its gross errors left out of the fit
    spread, flags = parameter_spread(names, results, opt.z_threshold, extra=sol.effects, false_alarm=opt.false_alarm)
    return FleetResult(robot=robot, names=names, results=results, values=sol.X, free=sol.free[:, : X0.shape[1]],
                       spread=spread, flags=flags, identify=opt.identify, z_threshold=opt.z_threshold,
                       prior=sol.prior, effects=sol.effects, wall_time_s=time.perf_counter() - t0,
                       false_alarm=opt.false_alarm)


def _batches(robot: Robot, names: list[str], datasets: list, tests: list | None, template) -> tuple:
    """The training rows and the held-out ones (or None) as padded batches, each robot's motion
    checked against its model at the template's values."""
    fd = FleetData.build(robot, datasets)
    fd_test = None
    if tests is not None:
        none = torch.zeros(0, dtype=torch.long)
        fd_test = FleetData.build(robot, [t if t is not None else d.subset(none) for d, t in zip(datasets, tests)])
    X0 = template.values.expand(len(names), -1)
    check_fleet_motion(robot, fd, names, X0)
    if fd_test is not None:
        check_fleet_motion(robot, fd_test, names, X0)
    return fd, fd_test


def _fields(opt: FleetOptions) -> dict:
    """The settings as keywords (those a Ray shard passes on to its own calibration)."""
    return {f.name: getattr(opt, f.name) for f in fields(opt)}


# ------------------------------------------------------------------------- beyond one machine (Ray)
def import_ray():
    """The ``ray`` module, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError as e:
        raise ImportError("running a fleet on Ray needs the optional dependency ray: pip install torchcal[ray] "
                          f"(import failed: {e})") from None
    return ray


def _solve_shard(robot, data: dict, test: dict | None, kwargs: dict, threads: int):
    """One shard, solved in-process on a worker (one torch thread per CPU Ray gave the task); its
    per-robot results are built there, so that only they travel back."""
    torch.set_num_threads(threads)
    fr = calibrate_fleet(robot, data, test=test or None, **kwargs)
    fr.results = list(fr.results)
    return fr


def calibrate_fleet_ray(robot, data: dict, *, test: dict | None = None, address: str | None = "local",
                        shards: int | None = None, workers: int | None = None, **kwargs):
    """:func:`~torchcal.pipelines.fleet.run.calibrate_fleet` with the robots spread over a Ray cluster.

    Args:
        data, test: robot id -> Measurements.
        address: ``"local"`` (or None) starts a Ray instance in this process with ``workers`` CPUs
            (default: all) and stops it afterwards; anything else is passed to ``ray.init`` (e.g.
            ``"auto"`` or ``"ray://head:10001"``) and the cluster is left running.
        shards: how many tasks the fleet is cut into (default: the cluster's CPU count, capped by
            the number of robots); each task solves its robots as one batch.
        kwargs: the options of :func:`~torchcal.pipelines.fleet.run.calibrate_fleet` (no ``prior`` or
            ``effects``: those couple the robots).
    Returns:
        a :class:`~torchcal.pipelines.fleet.run.FleetResult` over all robots, in the order of ``data``.
    """

    ray = import_ray()
    t0 = time.perf_counter()
    started = False
    if not ray.is_initialized():
        if address in (None, "local"):
            ray.init(num_cpus=workers or os.cpu_count(), include_dashboard=False, log_to_driver=False,
                     runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(_paths())}})
            started = True
        else:
            ray.init(address=address, runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(_paths())}})
    try:
        names = list(data)
        n = max(1, min(len(names), shards or int(ray.cluster_resources().get("CPU", 1))))
        bounds = [round(i * len(names) / n) for i in range(n + 1)]
        chunks = [names[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        task = ray.remote(num_cpus=1)(_solve_shard)
        z = kwargs.pop("z_threshold", 5.0)
        alarm = kwargs.pop("false_alarm", FALSE_ALARM)
        refs = [task.remote(robot, {k: data[k] for k in c}, {k: test[k] for k in c if test and k in test}, kwargs, 1)
                for c in chunks]
        parts = ray.get(refs)
    finally:
        if started:
            ray.shutdown()
    results = [r for p in parts for r in p.results]
    spread, flags = parameter_spread(names, results, z, false_alarm=alarm)
    return FleetResult(robot=robot, names=names, results=results, values=torch.cat([p.values for p in parts]),
                       free=torch.cat([p.free for p in parts]), spread=spread, flags=flags, identify=parts[0].identify,
                       z_threshold=z, wall_time_s=time.perf_counter() - t0, false_alarm=alarm)


def _paths() -> list[str]:
    """Where this torchcal (and its dependencies) are found, for the workers' import path."""
    here = str(Path(__file__).resolve().parents[3])  # the directory holding the torchcal package
    extra = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return [here] + [p for p in extra if p != here]
