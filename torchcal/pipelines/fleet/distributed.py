"""A fleet larger than one machine holds: the robots spread over a Ray cluster.

Without a prior or a shared payload the robots of a fleet are independent problems, so the fleet
splits into shards, each shard is one Ray task running the batched solve
(:func:`~torchcal.pipelines.fleet.run.calibrate_fleet`) on its robots, and the driver gathers the results and
computes the fleet's parameter spread. Ray schedules the tasks, moves the data and retries failed
workers; nothing here queues jobs by hand. Ray is an optional dependency: ``pip install
torchcal[ray]``.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import torch

__all__ = ["calibrate_fleet_ray", "import_ray"]


def import_ray():
    """The ``ray`` module, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError as e:
        raise ImportError("running a fleet on Ray needs the optional dependency ray: pip install torchcal[ray] "
                          f"(import failed: {e})") from None
    return ray


def _solve_shard(robot, data: dict, test: dict | None, kwargs: dict, threads: int):
    """One shard, solved in-process on a worker (one torch thread per CPU Ray gave the task)."""
    from torchcal.pipelines.fleet.run import calibrate_fleet

    torch.set_num_threads(threads)
    return calibrate_fleet(robot, data, test=test or None, **kwargs)


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
    from torchcal.pipelines.fleet.run import FleetResult
    from torchcal.report.fleet import parameter_spread

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
        refs = [task.remote(robot, {k: data[k] for k in c}, {k: test[k] for k in c if test and k in test}, kwargs, 1)
                for c in chunks]
        parts = ray.get(refs)
    finally:
        if started:
            ray.shutdown()
    results = [r for p in parts for r in p.results]
    spread, flags = parameter_spread(names, results, z)
    return FleetResult(robot=robot, names=names, results=results, values=torch.cat([p.values for p in parts]),
                       free=torch.cat([p.free for p in parts]), spread=spread, flags=flags, identify=parts[0].identify,
                       z_threshold=z, wall_time_s=time.perf_counter() - t0)


def _paths() -> list[str]:
    """Where this torchcal (and its dependencies) are found, for the workers' import path."""
    here = str(Path(__file__).resolve().parents[3])  # the directory holding the torchcal package
    extra = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return [here] + [p for p in extra if p != here]
