"""A fleet of robots of one model, calibrated in one batched solve.

The kinematics are batched over parameter populations; a fleet is such a population with its own
rows per member. :func:`calibrate_fleet` stacks every robot's measurements (ragged row counts
padded and masked), registers every instrument frame with one batched Kabsch, judges each robot's
identifiable parameters (:mod:`torchcal.pipelines.fleet.identify`), and fits all robots with one
block-diagonal Levenberg-Marquardt (:func:`~torchcal.optim.lm_batched.lm_batched`): each robot's
parameters, Jacobian, damping and stopping test are its own, and the result for each robot is what
``calibrate(robot, data, method="lm", prior=None)`` gives it. On top of that it reports how every parameter
spreads over the fleet and flags robots far from their siblings (:mod:`torchcal.report.fleet`),
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

import numbers
import os
import time
from dataclasses import replace
from pathlib import Path

import torch

from torchcal.advice import advice
from torchcal.kinematics.robot import Robot
from torchcal.params import ParamSet
from torchcal.pipelines.fleet.coupled import solve_coupled
from torchcal.pipelines.fitting import check_plausible
from torchcal.pipelines.fleet.data import (BASE_NAMES, FleetData, check_fleet_motion, fleet_template, gross_lists,
                                           register_fleet_robust, validate_fleet)
from torchcal.pipelines.fleet.independent import solve_independent
from torchcal.pipelines.fleet.result import FleetResult
from torchcal.pipelines.fleet.views import FleetResults
from torchcal.report.fleet import FALSE_ALARM, parameter_spread
from torchcal.threads import threads_by_size

__all__ = ["calibrate_fleet", "FleetData", "fleet_template", "validate_fleet"]

_LM_DEFAULTS = {"tau": 1e-6, "reuse": 0.9}
_PRIOR_MIN_ROBOTS = 3  # a spread estimated from fewer robots is no estimate


@threads_by_size("data", "test")
def calibrate_fleet(robot: Robot, data, *, names: list[str] | None = None, test=None, params: ParamSet | None = None,
                    free=None, prior: str | None = None, prior_scale: dict | None = None, effects=None,
                    payload: str = "shared", identify: str | None = None, register: bool = True, prefer=None,
                    min_rows: int = 3, z_threshold: float = 5.0, false_alarm: float = FALSE_ALARM,
                    plausible: dict | None = None, options: dict | None = None, ray: str | None = None,
                    ray_shards: int | None = None) -> FleetResult:
    """Calibrate ``R`` robots of one model in one batched solve.

    Args:
        robot: the model (:class:`~torchcal.kinematics.robot.Robot`) every robot is an instance of.
        data: one :class:`~torchcal.measure.io.Measurements` per robot (``q: (N_r, dof)`` rad, marker
            positions ``(N_r, M, 3)`` m in that robot's instrument frame; ``N_r`` may differ), as a
            list (ids from ``names``, default ``robot_000``…) or a dict id -> Measurements.
        test: held-out Measurements per robot (same form; missing robots allowed in a dict).
        params, free: the template ParamSet and glob patterns of parameters to identify, as for
            :func:`torchcal.pipelines.calibrate`.
        prior: ``None`` (every robot alone: the result equals ``calibrate(..., method="lm")``) or
            ``"fleet"``: each robot's geometric errors are drawn around the fleet mean, with
            scales and noise estimated from the fleet (empirical Bayes) unless ``prior_scale``
            gives them (``{"m": metres, "rad": radians}``). It needs at least 3 robots (2 when
            ``prior_scale`` is given).
        effects: ``None`` or ``["joint_compliance"]``: each robot's joints twist with the gravity
            torque (its own compliances), under a payload ``"shared"`` by the fleet or fitted
            ``"per_robot"`` (``payload``); needs URDF inertials.
        identify: ``"per_robot"`` (default without coupling) or ``"pooled"``: one identifiable
            set judged on all robots' poses together (always so with a prior or effects).
        min_rows: robots with fewer rows are refused.
        z_threshold: the least distance from its siblings (in their standard deviations) at which a
            robot's parameter is flagged (:mod:`torchcal.report.fleet`).
        false_alarm: the chance that a fleet of healthy robots raises any flag; with few robots the
            bound it sets (Student-t, Bonferroni over robots and parameters) exceeds ``z_threshold``.
        plausible: the largest plausible error per unit, as for :func:`torchcal.pipelines.calibrate`
            (a robot's parameter its data pin down worse is fixed; ``{}``: none is).
        options: Levenberg-Marquardt options (``max_iter``, ``tau``, ``gtol``, ``xtol``, ``ftol``).
        ray: address of a Ray cluster (``"auto"``, ``"ray://host:10001"``, or ``"local"`` for an
            in-process one) to spread the robots over (``pip install torchcal[ray]``); ``ray_shards``
            robots are solved per task batch (default: one shard per worker CPU).
    Returns:
        a :class:`FleetResult`.
    """
    t0 = time.perf_counter()
    names, datasets, tests = validate_fleet(robot, data, names, test, min_rows)
    effects = [effects] if isinstance(effects, str) else effects
    coupled = prior is not None or bool(effects)
    if prior not in (None, "fleet"):
        raise ValueError(f"prior must be None or 'fleet', got {prior!r}")
    if payload not in ("shared", "per_robot"):
        raise ValueError(f"payload must be 'shared' or 'per_robot', got {payload!r}")
    if not (isinstance(z_threshold, numbers.Real) and 0 < z_threshold < float("inf")):
        raise ValueError(f"z_threshold is a robust z-score beyond which a parameter is flagged: give a positive number "
                         f"(default 5), got {z_threshold!r}")
    if not (isinstance(false_alarm, numbers.Real) and 0 < false_alarm < 1):
        raise ValueError(f"false_alarm is the chance that a fleet of healthy robots raises any flag: give a number "
                         f"between 0 and 1 (default {FALSE_ALARM}), got {false_alarm!r}")
    need = _PRIOR_MIN_ROBOTS if prior_scale is None else 2
    if prior is not None and len(names) < need:
        raise ValueError("prior='fleet' pulls each robot towards the fleet mean by how far robots spread around it"
                         + (", which is estimated from the fleet" if prior_scale is None else "")
                         + f": {len(names)} robot(s) are too few to tell. Give at least {need} robots"
                         + (advice(" (or prior_scale={'m': …, 'rad': …} with 2)", "") if prior_scale is None else "")
                         + ", or leave out the prior")
    if identify not in (None, "per_robot", "pooled"):
        raise ValueError(f"identify must be 'per_robot' or 'pooled', got {identify!r}")
    if coupled and identify == "per_robot":
        raise ValueError("a prior or fleet-wide effects couple the robots: their parameters are judged on the pooled "
                         "design; use identify='pooled' (or leave it out)")
    identify = identify or ("pooled" if coupled else "per_robot")
    plausible = check_plausible(plausible)
    opts = {**_LM_DEFAULTS, **dict(options or {})}
    if ray is not None:
        if coupled:
            raise ValueError("on Ray the robots are solved independently; a prior or a shared payload couples them. "
                             "Run those in-process (leave out ray=)")
        return calibrate_fleet_ray(robot, dict(zip(names, datasets)), test=None if tests is None else
                                   {n: t for n, t in zip(names, tests) if t is not None}, address=ray,
                                   shards=ray_shards, params=params, free=free, identify=identify, register=register,
                                   prefer=prefer, min_rows=min_rows, z_threshold=z_threshold, false_alarm=false_alarm,
                                   plausible=plausible, options=options)
    template = fleet_template(robot, datasets[0].marker_names, params, free)
    fd = FleetData.build(robot, datasets)
    fd_test = None
    if tests is not None:
        none = torch.zeros(0, dtype=torch.long)
        fd_test = FleetData.build(robot, [t if t is not None else datasets[i].subset(none) for i, t in enumerate(tests)])
    X0 = template.values.expand(len(names), -1).clone()
    check_fleet_motion(robot, fd, names, X0)
    if fd_test is not None:
        check_fleet_motion(robot, fd_test, names, X0)
    bi = [robot.param_names.index(n) for n in BASE_NAMES]
    gross = [[] for _ in names]
    if register and bool(template.free[bi].any()):
        # a gross error (a glitch metres off) would drag its robot's frame, fit and noise: left out, listed
        X0, mask = register_fleet_robust(robot, fd, X0)
        if bool(mask.any()):
            gross = gross_lists(fd, mask, fd.errors(robot, X0), robot.marker_names)
            fd = replace(fd, seen=fd.seen & ~mask)
    extra = prior_info = None
    if coupled:
        sol = solve_coupled(robot, fd, template, X0, names, prior=prior, prior_scale=prior_scale,
                            effects=list(effects or []), payload=payload, prefer=prefer, options=opts)
        extra, prior_info = sol.effects, sol.prior
        stage = "geometric + joint_compliance" if effects else "geometric"
        wall = time.perf_counter() - t0
        held_out = sol.test_errors(fd_test) if fd_test is not None and sol.test_errors else None
        results = FleetResults(robot, names, datasets, tests, fd, fd_test, template, X0, sol.X, sol.free, sol.se,
                               sol.r, sol.reasons, sol.solver, wall, stage=stage, n_extra=sol.n_extra,
                               test_errors=held_out)
        X, free = sol.X, sol.free[:, : X0.shape[1]]
    else:
        sol = solve_independent(robot, fd, template, X0, names, identify, prefer, opts, plausible)
        X, free = sol.X, sol.free
        results = FleetResults(robot, names, datasets, tests, fd, fd_test, template, X0, X, free, sol.se, sol.r,
                               sol.reasons, sol.solver, time.perf_counter() - t0)
    results.suspects = gross  # per robot, its gross errors left out of the fit
    spread, flags = parameter_spread(names, results, z_threshold, extra=extra, false_alarm=false_alarm)
    return FleetResult(robot=robot, names=names, results=results, values=X, free=free, spread=spread, flags=flags,
                       identify=identify, z_threshold=z_threshold, prior=prior_info, effects=extra,
                       wall_time_s=time.perf_counter() - t0, false_alarm=false_alarm)


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
