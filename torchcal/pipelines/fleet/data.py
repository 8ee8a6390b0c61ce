"""A fleet's measurements as one padded batch, its validation at the door, and the batched
registration of every robot's instrument frame."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.kinematics.transforms import kabsch, so3_log
from torchcal.measure.checks import check_fit_inputs, check_motion_arrays
from torchcal.measure.memory import check_memory
from torchcal.measure.records import ErrorDetails, Suspect
from torchcal.measure.registration import GROSS_FLOOR, GROSS_K
from torchcal.measure.data import Measurements
from torchcal.kinematics.slots import BASE_NAMES

__all__ = ["FleetData", "validate_fleet", "register_fleet", "register_fleet_robust", "gross_lists",
           "check_fleet_motion", "check_rows", "BASE_NAMES"]

# Jacobian entries evaluated at once, per device: a CPU's caches hold a few hundred robots' worth;
# a GPU wants large batches but the kinematics' intermediates are ~15 times the Jacobian
_CHUNK = {"cpu": 1 << 20, "cuda": 1 << 26}


@dataclass
class FleetData:
    """Measurements of ``R`` robots of one model, padded to one shape.

    Attributes:
        q: ``(R, N, dof)`` joint values (rad / m); padded rows hold zeros.
        measured: ``(R, N, M, 3)`` marker positions (m, each robot's instrument frame), markers in
            the robot model's order; 0 where not seen.
        seen: ``(R, N, M)`` bool: a real observation.
        rows: the number of real rows of each robot.
    """

    q: Tensor
    measured: Tensor
    seen: Tensor
    rows: list[int]
    covariates: list[dict] = field(default_factory=list)

    @classmethod
    def build(cls, robot: Robot, datasets: list[Measurements]) -> "FleetData":
        """Pad and stack the robots' measurements: one copy per field for all robots that list
        their markers in the same order (not one per robot)."""
        R, N, M = len(datasets), max(len(d) for d in datasets), len(robot.marker_names)
        dt = dict(dtype=robot.dtype, device=robot.device)
        lens = [len(d) for d in datasets]
        q = torch.zeros(R * N, robot.dof, **dt)
        meas = torch.zeros(R * N, M, 3, **dt)
        seen = torch.zeros(R * N, M, dtype=torch.bool, device=robot.device)
        groups: dict[tuple, list[int]] = {}
        for r, d in enumerate(datasets):
            groups.setdefault(tuple(d.marker_names), []).append(r)
        for order, members in groups.items():
            rows = torch.as_tensor(_rows(members, [lens[r] for r in members], N), device=robot.device)
            mk = torch.as_tensor([robot.marker_names.index(m) for m in order], device=robot.device)
            q[rows] = torch.cat([datasets[r].q for r in members]).to(**dt)
            pos = torch.cat([datasets[r].positions for r in members]).to(**dt)
            s = ~torch.isnan(pos).any(-1)
            seen[rows[:, None], mk[None, :]] = s
            meas[rows[:, None], mk[None, :]] = torch.where(s[..., None], pos, 0.0)
        return cls(q.view(R, N, -1), meas.view(R, N, M, 3), seen.view(R, N, M), lens,
                   [dict(d.covariates) for d in datasets])

    @property
    def n_obs(self) -> Tensor:
        """``(R,)`` marker observations per robot."""
        return self.seen.sum((1, 2))

    def positions(self, robot: Robot, X: Tensor, idx: Tensor, q: Tensor | None = None) -> Tensor:
        """``(b, N, M, 3)`` model positions (m) of robots ``idx`` with parameters ``X (b, K)``
        (joint values ``q (b, N, dof)`` when they differ from the commands)."""
        return robot.positions(self.q[idx] if q is None else q, X, check=False)

    def residuals(self, robot: Robot, X: Tensor, idx: Tensor) -> Tensor:
        """``(b, N·M·3)`` model minus measured positions (m), zero where nothing was seen."""
        r = (self.positions(robot, X, idx) - self.measured[idx]) * self.seen[idx][..., None]
        return r.reshape(r.shape[0], -1)

    def jacobian(self, robot: Robot, X: Tensor, idx: Tensor, q: Tensor | None = None,
                 cols: list[int] | None = None) -> Tensor:
        """``(b, N·M·3, c)`` analytic Jacobian of :meth:`residuals` (m per unit) over the parameters
        ``cols`` (indices into K, ascending; default all K).

        Evaluated a chunk of robots at a time: the kinematics' intermediates then stay in cache on
        a CPU and within bounds on a GPU, whatever the fleet's size."""
        b, N, M = idx.numel(), self.q.shape[1], self.seen.shape[2]
        q = self.q[idx] if q is None else q
        K = X.shape[1]
        out = X.new_empty(b, N * M * 3, K if cols is None else len(cols))
        step = max(1, _CHUNK.get(X.device.type, 1 << 24) // (N * M * 3 * K))
        for a in range(0, b, step):
            J = robot.param_jacobian(q[a:a + step], X[a:a + step], check=False, columns=cols)
            torch.mul(J, self.seen[idx[a:a + step]][..., None, None], out=out[a:a + step].view(J.shape))
        return out

    def error_vectors(self, robot: Robot, X: Tensor) -> Tensor:
        """``(R, N, M, 3)`` model minus measured positions (m) of every robot with its own
        parameters ``X (R, K)``; meaningful where :attr:`seen`."""
        idx = torch.arange(self.q.shape[0], device=self.q.device)
        return self.positions(robot, X, idx) - self.measured

    def errors(self, robot: Robot, X: Tensor) -> Tensor:
        """``(R, N, M)`` Euclidean errors (m) of every robot with its own parameters ``X (R, K)``."""
        return self.error_vectors(robot, X).norm(dim=-1)

    def details(self, robot: Robot, X: Tensor, V: Tensor) -> list[ErrorDetails]:
        """Per robot, what :func:`~torchcal.measure.details.error_details` gives one data set:
        ``e (n,)``, ``xyz (n, 3)`` and the marker's distance from the robot base ``dist (n,)`` (m)
        of its observations, from the error vectors ``V (R, N, M, 3)`` of parameters ``X (R, K)``.
        The base frame only turns and shifts, so that distance is ``|model − base translation|``
        in the instrument frame and needs no second pass of the kinematics."""
        t = X[:, [robot.param_names.index(n) for n in BASE_NAMES[:3]]]
        dist = (self.measured + V - t[:, None, None]).norm(dim=-1)
        e = V.norm(dim=-1)
        return [ErrorDetails(e=e[b][s], xyz=V[b][s], dist=dist[b][s]) for b, s in enumerate(self.seen)]


def _rows(robots: list[int], lens: list[int], N: int) -> np.ndarray:
    """Flat row indices ``r·N + i`` (``i < lens``) of ``robots`` in an ``(R·N, …)`` padded layout."""
    lens_ = np.asarray(lens, dtype=np.int64)
    start = np.repeat(np.asarray(robots, dtype=np.int64) * N - np.cumsum(lens_) + lens_, lens_)
    return start + np.arange(int(lens_.sum()), dtype=np.int64)


def _observations(datasets: list[Measurements]) -> list[int]:
    """Marker positions seen per data set, counted in one pass over all of them."""
    groups: dict[int, list[int]] = {}
    for r, d in enumerate(datasets):
        groups.setdefault(len(d.marker_names), []).append(r)
    out = [0] * len(datasets)
    for members in groups.values():
        seen = (~torch.isnan(torch.cat([datasets[r].positions for r in members])).any(-1)).sum(-1)
        ends = torch.cumsum(seen, 0).tolist()
        at = 0
        for r in members:
            n = len(datasets[r])
            out[r] = int(ends[at + n - 1] - (ends[at - 1] if at else 0)) if n else 0
            at += n
    return out


def _named(data, names, what: str) -> tuple[list[str], list]:
    if isinstance(data, dict):
        return [str(k) for k in data], list(data.values())
    if isinstance(data, Measurements) or not isinstance(data, (list, tuple)):
        raise TypeError(f"{what} must be a list of Measurements (one per robot) or a dict robot id -> Measurements, "
                        f"got {type(data).__name__}")
    if names is None:
        names = [f"robot_{i:03d}" for i in range(len(data))]
    names = [str(n) for n in names]
    if len(names) != len(data):
        raise ValueError(f"{what}: {len(data)} data sets for {len(names)} robot ids; give one per robot, in the same "
                         "order (or a dict robot id -> Measurements)")
    return names, list(data)


def validate_fleet(robot: Robot, data, names=None, test=None, min_rows: int = 3):
    """Check a fleet's inputs: ``(names, datasets, tests or None)``, or an error that says what is
    wrong and how to fix it."""
    if not isinstance(robot, Robot):
        raise TypeError(f"robot must be a torchcal.Robot (Robot.from_urdf(...)), got {type(robot).__name__}")
    names, datasets = _named(data, names, "data")
    if not datasets:
        raise ValueError("no robots: give a list of Measurements, one per robot")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"robot ids must be unique; repeated: {dup[:5]}")
    first = None
    for n, d in zip(names, datasets):
        if not isinstance(d, Measurements):
            raise TypeError(f"robot {n!r}: expected Measurements (torchcal.load_measurements), got {type(d).__name__}")
        if list(d.joint_names) != list(robot.joint_names):
            raise ValueError(f"robot {n!r}: joint columns {list(d.joint_names)} differ from the model's "
                             f"{robot.joint_names}; every robot of a fleet is the same model")
        unknown = [m for m in d.marker_names if m not in robot.marker_names]
        if unknown:
            raise ValueError(f"robot {n!r}: markers {unknown} are not markers of the model {robot.marker_names}")
        if first is None:
            first = (n, sorted(d.marker_names))
        elif sorted(d.marker_names) != first[1]:
            raise ValueError(f"robot {n!r} measures markers {sorted(d.marker_names)} but robot {first[0]!r} measures "
                             f"{first[1]}; the robots of a fleet share one marker set")
    for n, d, k in zip(names, datasets, _observations(datasets)):
        if len(d) < min_rows or k < 3:
            raise ValueError(f"robot {n!r} has {len(d)} rows ({k} marker observations); a calibration "
                             f"needs at least {max(min_rows, 3)} rows. Measure more poses or leave this robot out")
    tests = None
    if test is not None:
        tnames, tsets = _named(test, names if not isinstance(test, dict) else None, "test")
        extra = [t for t in tnames if t not in names]
        if extra:
            raise ValueError(f"held-out data for robots {extra[:5]}, which are not in the fleet (its robots: "
                             f"{names[:5]}{' …' if len(names) > 5 else ''}); name each robot's held-out data as its "
                             "training data (the same file name <robot>.csv, or the same dict key)")
        by = dict(zip(tnames, tsets))
        tests = [by.get(n) for n in names]
        for n, d in zip(names, tests):
            if d is not None and (not isinstance(d, Measurements) or list(d.joint_names) != list(robot.joint_names)):
                raise ValueError(f"robot {n!r}: held-out data must be Measurements with the model's joint columns")
    checked: set[tuple[int, int]] = set()
    fewest = min(range(len(datasets)), key=lambda i: len(datasets[i]))
    for i, (n, d) in enumerate(zip(names, datasets)):  # the rules every fit has, robot by robot
        t = None if tests is None else tests[i]
        if (id(d), id(t)) in checked:  # the same data given twice is checked once
            continue
        checked.add((id(d), id(t)))
        try:
            # the minimum of data (a rank at the robot's poses) is judged for the robot with the fewest
            # rows here, and for every robot from the batched judgement's ranks (check_rows)
            check_fit_inputs(robot, d, t, enough=i == fewest, motion=False)
        except (ValueError, TypeError) as e:
            raise type(e)(f"robot {n!r}: {e}") from None
    # the batched fit holds every robot's Jacobian at once: judge the memory of the whole fleet
    rows = sum(len(d) for d in datasets) + sum(len(t) for t in (tests or []) if t is not None)
    check_memory(rows, len(robot.marker_names), robot.n_params, who=f"fleet fit ({len(datasets)} robots)",
                 itemsize=torch.finfo(robot.dtype).bits // 8)
    return names, datasets, tests


def register_fleet(robot: Robot, fd: FleetData, X: Tensor) -> Tensor:
    """Every robot's instrument frame by one batched Kabsch registration of its nominal marker
    positions (current non-base errors) onto the measured ones: ``X (R, K)`` with base entries set."""
    bi = [robot.param_names.index(n) for n in BASE_NAMES]
    X = X.clone()
    X[:, bi] = 0.0
    idx = torch.arange(X.shape[0], device=X.device)
    model = fd.positions(robot, X, idx)  # robot base frame
    R_, N, M = fd.seen.shape
    w = fd.seen.reshape(R_, N * M).to(X.dtype)
    try:
        # on the host: a GPU's batched SVD of many 3 x 3 matrices is slow, and R·N·M points cost
        # little to move
        Rb, t = kabsch(model.reshape(R_, N * M, 3).cpu(), fd.measured.reshape(R_, N * M, 3).cpu(), weights=w.cpu())
    except ValueError as e:
        raise ValueError(f"base registration failed: {e} (problems are robots in fleet order)") from None
    X[:, bi] = torch.cat([t, so3_log(Rb)], -1).to(X)
    return X


def check_fleet_motion(robot: Robot, fd: FleetData, names: list[str], X: Tensor) -> None:
    """Every robot's points move about as far as its model's (:func:`~torchcal.measure.checks.check_motion`),
    from one batched kinematics call at ``X (R, K)`` and one copy to the host."""
    idx = torch.arange(X.shape[0], device=X.device)
    model = fd.positions(robot, X, idx).detach().cpu().numpy()
    meas, seen = fd.measured.detach().cpu().numpy(), fd.seen.cpu().numpy()
    for b, n in enumerate(names):
        check_motion_arrays(robot.marker_names, model[b], meas[b], seen[b], f"robot {n!r}")


def register_fleet_robust(robot: Robot, fd: FleetData, X: Tensor, rounds: int = 5) -> tuple[Tensor, Tensor]:
    """:func:`register_fleet`, then again without each robot's gross errors (further from its
    registered nominal model than ``GROSS_K`` times its median error and than ``GROSS_FLOOR``:
    :mod:`~torchcal.measure.registration`), until they settle, all robots at once. Returns
    ``(X (R, K), gross (R, N, M) bool)``: a glitch metres off drags neither its robot's frame nor
    its fit."""
    gross = torch.zeros_like(fd.seen)
    for _ in range(rounds):
        Xr = register_fleet(robot, replace(fd, seen=fd.seen & ~gross), X)
        E = fd.errors(robot, Xr)
        med = torch.where(fd.seen, E, torch.full_like(E, float("nan"))).flatten(1).nanmedian(1).values
        lim = (GROSS_K * med).clamp(min=GROSS_FLOOR)
        nxt = fd.seen & (E > lim[:, None, None])
        if torch.equal(nxt, gross):  # one read a round for the whole fleet
            break
        gross = nxt
    return Xr, gross


def gross_lists(fd: FleetData, gross: Tensor, E: Tensor, marker_names: list[str]) -> list[list[Suspect]]:
    """Per robot, its gross errors as a report lists them (one read of the device for the whole fleet)."""
    out: list[list[Suspect]] = [[] for _ in range(gross.shape[0])]
    idx = torch.nonzero(gross)
    for (r, i, m), e in zip(idx.tolist(), E[gross].tolist()):
        out[r].append(Suspect(i, marker_names[m], 1e3 * e))
    return out


def check_rows(fd: FleetData, free: Tensor, names: list[str]) -> None:
    """Refuse robots with too few rows: those whose residuals do not outnumber their identifiable
    parameters (the fit would pass through every point), and those too short to identify what their
    siblings identify (few rows limit the rank, so the identifiable set alone hides them)."""
    m, k = 3 * fd.n_obs, free.sum(-1)
    typical = int(k.sort().values[k.numel() // 2])  # the upper median: what most robots identify
    short = torch.nonzero((m <= k) | ((k < typical) & (m <= typical))).flatten().tolist()
    if short:
        need = typical // 3 + 1
        raise ValueError("too few rows: " + "; ".join(
            f"robot {names[i]!r} has {fd.rows[i]} rows ({int(m[i])} residuals) for the {typical} parameters the "
            f"fleet identifies" for i in short[:5]) + f". Measure at least {need} marker positions per robot, leave "
            "those robots out, or use prior='fleet' so that they borrow strength from the fleet")
