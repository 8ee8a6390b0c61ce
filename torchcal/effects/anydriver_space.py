"""The search space of :class:`~torchcal.effects.anydriver.ParameterDrivers` beyond its screening:
every shape of a (parameter, driver) pair, the steps, settlings and knees its driver's grid offers,
the cycles a time driver is searched for, and the rigid things whose coordinates move together (a
marker point, the instrument frame).

The screening (:mod:`torchcal.pipelines.loop.screen`) keeps the pairs that explain something and the
best breaks of each; :func:`expanded` turns them into the terms the selection chooses from, and
:func:`space_size` counts the whole space searched (the selection's Bonferroni threshold)."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects.drivers import driver_kind, driver_values
from torchcal.effects.shapes import (PERIODIC, WINDOW, grid_tags, harmonic_tags, period_frequencies, smooth_tags,
                                     window_grid)
from torchcal.kinematics.slots import BASE_NAMES
from torchcal.measure.levels import factor_levels

# shapes a rigid thing takes as a whole, all its coordinates one mode, when one coordinate shows them
RIGID_BREAKS = ("step", WINDOW, "exp", *PERIODIC)

__all__ = ["RIGID_BREAKS", "rigid", "coordinates", "shapes_for", "breaks", "cycles", "expanded", "space_size",
           "len_windows"]


def rigid(p: str, markers) -> str | None:
    """The rigid thing parameter ``p`` is a coordinate of: a marker of ``markers`` (its point) or
    ``"base"`` (the instrument frame); None for a joint's parameter."""
    head = p.rsplit(".", 1)[0]
    return head if head in markers or head == "base" else None


def coordinates(m: str) -> list[str]:
    """The parameters of the rigid thing ``m`` (:func:`rigid`): the frame's six, a point's three."""
    if m == "base":
        return list(BASE_NAMES)
    return [f"{m}.{a}" for a in ("dx", "dy", "dz")]


def shapes_for(eff, driver: str, x: Tensor) -> list[str]:
    """Every shape of a (numeric) driver with training values ``x (N,)``, its breaks aside (steps,
    settlings and knees: the best of their grids, chosen by the screening)."""
    robot = eff.robot
    rev = driver_kind(driver) == "q" and robot.joint_units[robot.joint_names.index(driver.split(":", 1)[1])] == "rad"
    # a stiffness that changes with the load deflects as an odd function of the torque, about zero
    # torque: the bow and the S about the training mean are not
    odd = ["odd2", "odd3"] if driver_kind(driver) == "torque" else []
    return ["lin"] + smooth_tags(x) + odd + (harmonic_tags() if rev else [])


def breaks(eff, driver: str, data, tq: Tensor | None = None) -> list[str]:
    """Every step, settling or knee ``driver`` can have on ``data`` (:func:`~torchcal.effects.shapes.grid_tags`);
    none for a text column (``tq``: the gravity torques on ``data``, when known)."""
    kind = driver_kind(driver)
    if kind == "level":
        return []
    if kind == "torque" and tq is None:
        tq = eff.torques(data.q, data.covariates)
    x = driver_values(eff.robot, driver, data.q, data.covariates, tq)
    return grid_tags(kind, x[torch.isfinite(x)])


def cycles(eff, driver: str, data) -> tuple[list[float], float]:
    """The frequencies (cycles per driver unit) a time driver is searched for on ``data``
    (:func:`~torchcal.effects.shapes.period_frequencies`) and its first training value, where each
    cycle's phase is counted from; no frequency for any other driver."""
    if driver_kind(driver) != "time":
        return [], 0.0
    x = driver_values(eff.robot, driver, data.q, data.covariates, None)
    x = x[torch.isfinite(x)]
    return (period_frequencies(x), float(x.min())) if x.numel() else ([], 0.0)


def expanded(eff, pairs: list[tuple[str, str]], data, steps: dict | None = None):
    """A copy of ``eff`` whose terms are every shape of each of ``pairs`` on ``data`` (``steps``: pair
    -> the breaks to offer, :func:`breaks`). A rigid thing moves as a whole: per level all its
    coordinates, and every step any of its coordinates found is offered for all of them (a set-up
    changed, per level or mid-session, is one rigid motion)."""
    robot = eff.robot
    tq = eff.torques(data.q, data.covariates) if any(d.startswith("torque:") for _, d in pairs) else None
    levels = factor_levels(data.covariates)
    names = set(robot.param_names)
    steps = steps or {}
    whole = []
    jumps: dict[tuple[str, str], list[str]] = {}  # (rigid thing, driver) -> the steps any coordinate found
    for p, d in pairs:
        m = rigid(p, robot.marker_names)
        whole += [(c, d) for c in coordinates(m)] if m is not None and driver_kind(d) == "level" else [(p, d)]
        if m is not None:
            jumps.setdefault((m, d), []).extend(t for t in steps.get((p, d), []) if t.startswith(RIGID_BREAKS))
    terms = []
    for p, d in dict.fromkeys(q for q in whole if q[0] in names):
        if driver_kind(d) == "level":
            terms += [(p, d, f"lvl={lv}") for lv in levels[d.split(":", 1)[1]][1:]]  # the first: the baseline
            continue
        x = driver_values(robot, d, data.q, data.covariates, tq)
        terms += [(p, d, t) for t in shapes_for(eff, d, x[torch.isfinite(x)])]
        own = rigid(p, robot.marker_names) is None
        terms += [(p, d, t) for t in steps.get((p, d), []) if own or not t.startswith(RIGID_BREAKS)]
    for (m, d), tags in jumps.items():
        terms += [(c, d, t) for t in dict.fromkeys(tags) for c in coordinates(m) if c in names]
    return eff._copy(terms=list(dict.fromkeys(terms)))


def len_windows(driver: str, x: Tensor) -> int:
    """How many windows (a change and its return) a time or row driver with training values ``x`` is
    scanned for (:func:`~torchcal.effects.shapes.window_grid`); none for any other driver."""
    if driver_kind(driver) not in ("time", "row"):
        return 0
    return int(window_grid(x)[1].sum())


def space_size(eff, pairs: list[tuple[str, str]], data) -> int:
    """Columns of the whole space of ``pairs`` on ``data``: every shape of every pair, every break of
    its driver's grid, every window between two of a time or row driver's breaks, both phases of every
    cycle searched, every level."""
    tq = eff.torques(data.q, data.covariates) if any(d.startswith("torque:") for _, d in pairs) else None
    levels = factor_levels(data.covariates)
    per: dict[str, int] = {}
    for d in dict.fromkeys(d for _, d in pairs):
        if driver_kind(d) == "level":
            per[d] = len(levels[d.split(":", 1)[1]]) - 1
            continue
        x = driver_values(eff.robot, d, data.q, data.covariates, tq)
        per[d] = (len(shapes_for(eff, d, x[torch.isfinite(x)])) + len(breaks(eff, d, data, tq))
                  + 2 * len(cycles(eff, d, data)[0]) + len_windows(d, x[torch.isfinite(x)]))
    return sum(per[d] for _, d in pairs)
