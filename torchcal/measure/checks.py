"""What every fit checks at its door (``calibrate``, ``run_loop``, ``calibrate_fleet``), before any
work: the arguments are a robot and measurements of it, enough of them, and measured points that
move as the joints say they should.

* The data were loaded for this robot: the same joint columns, and the robot they were read for
  (:attr:`Measurements.robot`) is this one.
* One minimum of data for every fit: at least twice as many measured values as the unknowns every
  model has (the instrument frame, 6, and 3 per marker point), and more than the geometric errors
  the poses can identify, so that something is left to judge a fit by.
* Each measured point moves about as far as the model moves it through the same joint values. A
  point that does not move while the joints do is an instrument fault (lost lock, a repeated
  value); one that moves a thousandth or a thousand times as far has the wrong units.
* Joint values beyond the URDF's limits (by more than :data:`LIMIT_SLACK` of the range) are named
  in a warning: their zero or direction may differ from the URDF's, which a fitted offset would hide.
* Held-out rows that repeat the training rows are named in a warning: their figures are not held out.
"""
from __future__ import annotations

import math
import os
import warnings

import numpy as np
import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.kinematics.robot import Robot
from torchcal.measure.data import Measurements
from torchcal.measure.memory import check_memory

__all__ = ["check_fit_inputs", "check_robot", "check_data_type", "check_enough", "check_motion", "warn_limits",
           "identifiable_count", "MOTION_RATIO", "LIMIT_SLACK"]

#: a marker whose measured spread differs from the model's spread by more than this factor is refused
MOTION_RATIO = 20.0
_STILL_M = 1e-3  # a model spread below this (m) says nothing about the measured one
_ORIENT = (".droll", ".dpitch", ".dyaw")
#: joint values further beyond a URDF limit than this fraction of the joint's range are named
LIMIT_SLACK = 0.02


def check_robot(robot, who: str = "robot", precision: bool = True) -> None:
    """``robot`` is a :class:`~torchcal.kinematics.robot.Robot` (in float64 when ``precision``)."""
    if not isinstance(robot, Robot):
        if isinstance(robot, (str, os.PathLike)):
            raise TypeError(f"{who} must be a torchcal.Robot, got the path {str(robot)!r}; build it with "
                            "Robot.from_urdf(path, markers=['smr@flange=0,0,0.05'])")
        raise TypeError(f"{who} must be a torchcal.Robot (Robot.from_urdf(path, markers=[...])), got "
                        f"{type(robot).__name__}")
    if precision and robot.dtype != torch.float64:
        raise TypeError(f"{who} {robot.name!r} computes in {str(robot.dtype).replace('torch.', '')}; a calibration "
                        "needs float64 (single precision loses tenths of a millimetre in the fit): build it with "
                        "dtype=torch.float64, the default, or convert it: robot.to(dtype=torch.float64)")


def check_data_type(data, who: str = "data") -> None:
    """``data`` is :class:`~torchcal.measure.data.Measurements`, with what to do when it is not."""
    if isinstance(data, Measurements):
        return
    if isinstance(data, (str, os.PathLike)):
        raise TypeError(f"{who} must be Measurements, got the path {str(data)!r}; read the file with "
                        "torchcal.load_measurements(path, robot)")
    raise TypeError(f"{who} must be Measurements, got {type(data).__name__}; read a CSV with "
                    "torchcal.load_measurements(path, robot), or build Measurements(q, positions, marker_names, "
                    "joint_names) from tensors (q: (N, dof) rad / m, positions: (N, M, 3) m)")


def _tie(robot: Robot, data: Measurements, who: str) -> None:
    """The data were loaded for this robot."""
    other = data.robot is not None and data.robot != robot.name
    if list(data.joint_names) != list(robot.joint_names) or other:
        was = f"robot {data.robot!r}" if data.robot is not None else "another robot"
        raise ValueError(f"the {who} rows were loaded for {was} (joints {list(data.joint_names)}), not for "
                         f"{robot.name!r} (joints {list(robot.joint_names)}); calibrate each robot with its own "
                         "measurements, or load the file again for this robot: load_measurements(path, robot)")
    missing = [m for m in data.marker_names if m not in robot.marker_names]
    if missing:
        raise ValueError(f"the {who} rows measure markers {missing} that robot {robot.name!r} does not have (its "
                         f"markers: {robot.marker_names}); load them for a robot declared with those markers")
    if data.q.dtype != robot.dtype:
        raise TypeError(f"the {who} rows are {str(data.q.dtype).replace('torch.', '')} but the robot computes in "
                        f"{str(robot.dtype).replace('torch.', '')}: convert them, data.to(dtype=torch.float64)")


def identifiable_count(robot: Robot, data: Measurements, q: Tensor | None = None) -> int:
    """How many of the robot's default free errors the full positions of ``data`` (at joint values
    ``q``, default the data's) can identify: the rank of their column-scaled Jacobian at the nominal
    model (marker orientations and markers the data do not measure left out)."""
    p = robot.params()
    measured = set(data.marker_names)
    keep = [f and not any(n.startswith(f"{m}.") and (m not in measured or n.endswith(_ORIENT)) for m in
                          robot.marker_names) for n, f in zip(p.names, p.free.tolist())]
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    J = robot.param_jacobian((data.q if q is None else q).to(robot.dtype), check=False)[:, mk]
    J = (J[data.seen] if q is None else J.reshape(-1, *J.shape[-2:])).reshape(-1, J.shape[-1])
    J = J[:, torch.tensor(keep, device=J.device)]
    if J.numel() == 0:
        return 0
    s = torch.linalg.svdvals(J / J.norm(dim=0).clamp(min=1e-300))
    return int((s > 1e-8 * s[0]).sum()) if float(s[0]) > 0 else 0


def _spread_poses(robot: Robot, n: int) -> Tensor:
    """``(n, dof)`` seeded joint values across the limits (±π where there are none)."""
    lo, hi = (x.clone() for x in robot.joint_limits)
    lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    u = torch.rand(n, robot.dof, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return lo + (hi - lo) * u.to(device=lo.device, dtype=lo.dtype)


def distinct_poses(data: Measurements) -> int:
    """How many different joint commands the rows hold (a pose measured 100 times is one pose)."""
    return int(torch.unique(data.q.detach(), dim=0).shape[0]) if len(data) else 0


def check_poses_move(data: Measurements, who: str = "training") -> None:
    """Refuse data whose rows all hold the same joint values: the joints never moved, and no
    geometric error shows in one pose, however often it is measured."""
    if len(data) >= 2 and distinct_poses(data) == 1:
        src = f" ({data.source})" if data.source else ""
        raise ValueError(f"the joints never moved: all {len(data)} rows of the {who} data{src} hold the same joint "
                         "values, one pose measured again and again; a calibration compares many poses across the "
                         "workspace: measure different poses (torchcal plan chooses them)")


def check_enough(robot: Robot, data: Measurements, who: str = "training") -> None:
    """The one minimum of data every fit asks: at least twice as many measured values as the
    unknowns every model has (instrument frame and marker points), and, for positions, more values
    than the errors the poses can identify (:func:`identifiable_count`): else a fit passes through
    every point, its noise estimate collapses to zero and its error reads 0.0000 mm."""
    check_poses_move(data, who)
    M = max(len(data.marker_names), 1)
    unknowns = 6 + 3 * len(data.marker_names)
    need = 2 * unknowns
    # a pose measured again adds no geometry: count the values of different poses only
    poses = distinct_poses(data)
    values = data.n_values if poses == len(data) else int(round(data.n_values * poses / max(len(data), 1)))
    why = (f"every fit identifies at least {unknowns} unknowns (where the instrument stands, and each marker's point), "
           "and needs at least twice as many values")
    refuse = values < need
    if data.positions_only and int(data.seen.sum()) >= 3:
        k = identifiable_count(robot, data)
        if refuse or values <= k:
            most = identifiable_count(robot, data, _spread_poses(robot, robot.n_params // 3 + 8))
            need, refuse = max(most + 1, need), True
            if values <= k:
                why = (f"these poses can identify {k} geometric errors, as many as their values, so a fit passes "
                       f"through every point and leaves nothing to judge it by (poses spread over the workspace "
                       f"identify {most} errors of this robot)")
    if refuse:
        rows = -(-need // (3 * M))
        src = f" ({data.source})" if data.source else ""
        same = "" if poses == len(data) else f", only {poses} different poses (the others repeat a joint command)"
        raise ValueError(f"too few rows: the {who} data{src} have {len(data)} rows ({data.n_values} measured values"
                         f"{same}); {why}: measure at least {rows} poses, each a different joint command (a geometric "
                         "calibration wants several times more)")


def _spread(x: np.ndarray) -> float:
    """Median distance (m) of the points ``x (n, 3)`` from their median point: how far they move,
    blind to a few glitches."""
    return float(np.median(np.linalg.norm(x - np.median(x, axis=0), axis=1)))


def _stale(src: str, marker: str, meas: np.ndarray, model: np.ndarray, rows: np.ndarray, file) -> None:
    """Refuse rows that repeat another row's measured position exactly where the model moves the
    marker: an instrument that lost the target and kept reporting its last value."""
    idx = np.flatnonzero(rows)
    _, first, inv = np.unique(meas[idx], axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    moved = np.linalg.norm(model[idx] - model[idx][first][inv], axis=1) > _STILL_M
    if moved.any():
        # CSV line numbers (given, or counted from a file without blank lines), or row indices
        at = (lambda r: file[r]) if isinstance(file, (list, tuple)) else (lambda r: r + 2) if file else (lambda r: r)
        lines = sorted({at(int(idx[first[inv[i]]])) for i in np.flatnonzero(moved)} |
                       {at(int(idx[i])) for i in np.flatnonzero(moved)})
        raise ValueError(f"{src}: marker {marker!r} has exactly the same position in {len(lines)} rows "
                         f"({'lines' if file else 'rows'} "
                         f"{lines[:8]}{' …' if len(lines) > 8 else ''}) whose joint values move it in the model: the "
                         "instrument repeated a stale value (it lost the target). Drop those rows, or measure them "
                         "again")


def check_motion(robot: Robot, data: Measurements, units=(), where: str | None = None,
                 lines: list[int] | None = None) -> None:
    """Each marker's measured positions spread about as far as the model's, through the same joint
    values (a rigid instrument frame does not change a spread). ``units``: the units declared for
    the file, which word the advice; ``lines``: the file line of each row."""
    seen = data.seen.cpu().numpy()
    if seen.sum() < 3:
        return
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    model = robot.positions(data.q.to(robot.dtype), check=False).detach().cpu().numpy()[:, mk]
    check_motion_arrays(data.marker_names, model, data.positions.detach().cpu().numpy(), seen,
                        where or (data.source or "the data"), lines if lines is not None else where is not None, units)


def check_motion_arrays(markers: list[str], model: np.ndarray, meas: np.ndarray, seen: np.ndarray, src: str,
                        file: bool | list[int] = False, units=()) -> None:
    """:func:`check_motion` on arrays already at hand: ``model`` and ``meas`` ``(N, M, 3)`` (m) of the
    ``markers``, ``seen (N, M)``; a fleet computes the model of every robot in one batched call.
    ``file``: rows come from a file (True), with these file lines (a list), or not (False)."""
    for k, m in enumerate(markers):
        rows = seen[:, k]
        if rows.sum() < 3:
            continue
        _stale(src, m, meas[:, k], model[:, k], rows, file)
        want = _spread(model[rows, k])
        got = _spread(meas[rows, k])
        if want < _STILL_M:
            continue
        ratio = got / want
        if ratio * MOTION_RATIO >= 1 and ratio <= MOTION_RATIO:
            continue
        said = (f"{src}: marker {m!r} moves {1e3 * got:.3g} mm about its median point, but the joint values move it "
                f"{1e3 * want:.3g} mm in the model")
        if "mm" in units and 3e-4 < ratio < 3e-3:
            raise ValueError(f"{said}: the positions look like metres already, and declaring millimetres shrank them "
                             "1000 times; "
                             + advice("leave out units=['mm']", "leave out --units mm"))
        if "deg" in units and ratio > MOTION_RATIO:
            raise ValueError(f"{said}: the joint values look like radians already, and declaring degrees shrank them; "
                             + advice("leave out units=['deg']", "leave out --units deg"))
        if ratio < 1 / MOTION_RATIO:
            raise ValueError(f"{said}: a measured point that stays put while the joints move is an instrument fault "
                             "(the tracker lost the reflector and repeated a value, or measured another target). "
                             "Check the instrument's export; these rows cannot calibrate anything")
        raise ValueError(f"{said}: the joint values or positions are scaled wrong (degrees, millimetres), or the "
                         "marker is declared on a link before the one that carries it; check the units and the "
                         "marker's link")


def warn_limits(robot: Robot, sets: list[tuple[Measurements, str]]) -> None:
    """One warning per joint whose values leave the URDF's limits in any of the ``(data, name)``
    sets (training, held-out)."""
    lo, hi = (x.cpu().numpy() for x in robot.joint_limits)
    for j, n in enumerate(robot.joint_names):
        if not (np.isfinite(lo[j]) and np.isfinite(hi[j])):
            continue
        tol = LIMIT_SLACK * (hi[j] - lo[j])  # a controller overshooting its limit a little is no sign
        where, by = [], 0.0
        for data, who in sets:
            q = data.q[:, j].detach().cpu().numpy()
            out = (q < lo[j] - tol) | (q > hi[j] + tol)
            if out.any():
                where.append(f"{int(out.sum())} of {len(q)} {who} rows")
                by = max(by, float(np.max(np.maximum(lo[j] - q, q - hi[j]))))
        if where:
            unit = robot.joint_units[j]
            warnings.warn(f"joint {n!r} is beyond its URDF limits [{lo[j]:.4g}, {hi[j]:.4g}] {unit} in "
                          f"{' and '.join(where)} (by up to {by:.3g} {unit}): the data's zero or direction for this "
                          "joint may differ from the URDF's, and a fitted offset would hide it. Check the joint "
                          "convention of the export (or the URDF's limits)", stacklevel=3)


def _warn_repeated(train: Measurements, test: Measurements) -> None:
    # rows split from one file (--holdout, Measurements.split) share its source but not its rows:
    # only the rows themselves tell a repeat
    same = False
    if len(train) and len(test):
        rows = torch.cat([train.q, test.q], 0)
        _, inv = torch.unique(rows, dim=0, return_inverse=True)
        shared = int(torch.isin(inv[len(train):], inv[: len(train)]).sum())
        same = shared > len(test) // 2
    if same:
        one_file = (test.source is not None and train.source is not None and len(test) == len(train)
                    and os.path.realpath(str(test.source)) == os.path.realpath(str(train.source)))
        what = (f"the held-out file is the training file ({test.source})" if one_file else
                f"the held-out rows ({test.source or 'test'}) are the same rows as the training rows")
        warnings.warn(f"{what}: the held-out figures are training figures, not a test. Hold out rows the fit does "
                      f"not see (another file, or {advice('Measurements.split', '--holdout')})", stacklevel=3)


def check_fit_inputs(robot, train, test=None, enough: bool = True, motion: bool = True) -> None:
    """The door of every fit: refuse (or warn) as the module docstring says, before any work.
    ``enough=False`` leaves the minimum of data to the caller (:func:`check_enough`), after the
    refusals that say more about the data it has; ``motion=False`` leaves :func:`check_motion` to
    it (a fleet judges every robot's motion from one batched kinematics call)."""
    check_robot(robot)
    check_data_type(train, "data")
    if test is not None:
        check_data_type(test, "test")
    sets = [(d, who) for d, who in ((train, "training"), (test, "held-out")) if d is not None]
    check_poses_move(train)
    for d, who in sets:
        _tie(robot, d, who)
        if motion:
            check_motion(robot, d)
    warn_limits(robot, sets)
    if enough:
        check_enough(robot, train)
    check_memory(sum(len(d) for d, _ in sets), len(train.marker_names), robot.n_params,
                 itemsize=torch.finfo(robot.dtype).bits // 8)
    if test is not None:
        _warn_repeated(train, test)
