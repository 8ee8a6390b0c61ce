"""A fleet's per-robot results as views over its batched tensors, built when asked.

A fleet solve ends with tensors: every robot's parameters, free flags, standard errors, residuals,
decisions and solver records. A robot's :class:`~torchcal.pipelines.calibrate.CalibrationResult`
(what ``calibrate()`` returns: a ParamSet, a dict of standard errors, reasons in words, error
statistics per stage, the solver's record) costs Python per robot, and most callers read a few
robots or none: the fleet report reads the tensors. So :class:`FleetResults` builds a robot's
result on first access and keeps it; iterating builds them all, with the reasons and statistics
computed once for the whole fleet. :class:`FleetReasons` writes the reasons for the robots asked,
one least-squares solve per distinct decision (:func:`~torchcal.pipelines.fleet.identify.explain`).
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property

import torch
from torch import Tensor

from torchcal.measure.records import Stage, StageErrors, Suspect
from torchcal.measure.stats import errors_by_marker_batched
from torchcal.optim.lm_batched import BatchedLMResult
from torchcal.optim.result import Result
from torchcal.pipelines.calibration_result import CalibrationResult
from torchcal.pipelines.precision import imprecise_reason
from torchcal.pipelines.fleet.identify import FleetDecision, explain
from torchcal.pipelines.fleet.solution import FleetSolution

__all__ = ["FleetResults", "FleetReasons", "FleetSolvers"]


class FleetReasons(Sequence):
    """Per robot, why each dropped candidate is dropped (name -> sentence), written when first read.

    Args:
        decisions: ``(decision, row per robot, robots)`` per judgement, later entries winning.
        names, units: the candidate parameters.
        loose: ``(R, k)`` bool, candidates fixed because the data pin them down worse than a
            plausible error; ``loose_se``, ``loose_noise``: ``(R, k)`` their standard error and
            the per-axis noise (m) they were judged at.
    """

    def __init__(self, decisions: list[tuple[FleetDecision, Tensor, Tensor]], names: list[str], units: list[str],
                 loose: Tensor, loose_se: Tensor, loose_noise: Tensor):
        R_ = loose.shape[0]
        dev = loose.device
        self.entry = torch.full((R_,), -1, dtype=torch.long, device=dev)
        self.row = torch.zeros(R_, dtype=torch.long, device=dev)
        for t, (_, row, who) in enumerate(decisions):
            self.entry[who], self.row[who] = t, row
        # keep only the rows some robot ends with: a decision holds a (k, k) factor per row
        self.decisions = []
        for t, (d, _, _) in enumerate(decisions):
            mine = self.entry == t
            rows, at = torch.unique(self.row[mine], return_inverse=True)
            self.row[mine] = at
            self.decisions.append(FleetDecision(d.kept[rows], d.zero[rows], d.An[rows], d.norms[rows]))
        self.names, self.units = names, units
        self.loose, self.loose_se, self.loose_noise = loose, loose_se, loose_noise
        self._words: dict[int, dict[str, str]] = {}

    def __len__(self) -> int:
        return self.loose.shape[0]

    def __getitem__(self, b: int) -> dict[str, str]:
        if b not in self._words:
            self.fill([b])
        return self._words[b]

    def fill(self, robots=None) -> None:
        """Write the reasons of ``robots`` (default all): per decision, one :func:`explain` call
        over the distinct rows they end with."""
        todo = [b for b in (range(len(self)) if robots is None else robots) if b not in self._words]
        if not todo:
            return
        entry, row = self.entry[todo].tolist(), self.row[todo].tolist()
        loose = self._loose_words(todo)
        for t in sorted(set(entry)):
            mine = [(b, rw) for b, e, rw in zip(todo, entry, row) if e == t]
            uniq = sorted({rw for _, rw in mine})
            at = dict(zip(uniq, explain(self.decisions[t], self.names, self.units, rows=uniq)))
            for b, rw in mine:
                self._words[b] = {**at[rw], **loose[b]}

    def _loose_words(self, robots: list[int]) -> dict[int, dict[str, str]]:
        out: dict[int, dict[str, str]] = {b: {} for b in robots}
        sel = torch.as_tensor(robots, device=self.loose.device)
        hit = torch.nonzero(self.loose[sel])
        if hit.numel():
            se = self.loose_se[sel][hit[:, 0], hit[:, 1]].tolist()
            noise = self.loose_noise[sel][hit[:, 0], hit[:, 1]].tolist()
            for (i, c), s, n in zip(hit.tolist(), se, noise):
                out[robots[i]][self.names[c]] = imprecise_reason(self.names[c], self.units[c], s, n)
        return out


class FleetSolvers(Sequence):
    """Per robot, its last batched fit as a single solver's :class:`~torchcal.optim.Result`,
    built when first read (``fits[fit_of[b]].result(at[b], free[b])``)."""

    def __init__(self, fits: list[BatchedLMResult], fit_of: Tensor, at: Tensor, free: Tensor):
        self.fits, self.free = fits, free
        self.fit_of, self.at = fit_of.tolist(), at.tolist()
        self._made: dict[int, Result] = {}

    def __len__(self) -> int:
        return len(self.fit_of)

    def __getitem__(self, b: int) -> Result:
        if b not in self._made:
            self._made[b] = self.fits[self.fit_of[b]].result(self.at[b], self.free[b])
        return self._made[b]

    def converged(self) -> list[bool]:
        """Whether each robot's solver converged, read from the fits' tensors."""
        flags = [f.converged.tolist() for f in self.fits]
        return [flags[f][j] for f, j in zip(self.fit_of, self.at)]


class FleetResults(Sequence):
    """Every robot's :class:`~torchcal.pipelines.calibrate.CalibrationResult`, built on first access.

    ``X0``: ``(R, K)`` the start values; the fitted model comes from the fleet's solution ``sol``
    (:class:`~torchcal.pipelines.fleet.solution.FleetSolution`: its values, free flags, standard
    errors, training residuals, reasons, solver records, stage name, effect parameters per robot and
    held-out errors where the geometry alone does not predict them).
    """

    def __init__(self, robot, names: list[str], datasets, tests, fd, fd_test, template, X0: Tensor,
                 sol: FleetSolution, wall_time_s: float):
        X = sol.X
        K = X.shape[1]
        self.robot, self.names, self.fd, self.fd_test, self.template = robot, names, fd, fd_test, template
        self.n_train = [len(d) for d in datasets]
        self.has_test = [tests is not None and t is not None for t in (tests or [None] * len(names))]
        self.n_test = [len(t) if h else 0 for t, h in zip(tests or [None] * len(names), self.has_test)]
        self.X0, self.X, self.free, self.se = X0, X, sol.free[:, :K], sol.se[:, :K]
        self.residuals, self.reasons, self.solver, self.wall_time_s = sol.r, sol.reasons, sol.solver, wall_time_s
        # held-out errors of the final model: vectors (R, N', M, 3) keep what the plots need
        test_errors = sol.test_errors(fd_test) if fd_test is not None and sol.test_errors is not None else None
        self._test_vectors = test_errors
        self._test_errors = test_errors.norm(dim=-1) if test_errors is not None else None
        self.stage = sol.stage
        none = torch.zeros(len(names), dtype=torch.long, device=X.device)
        self.n_extra = none if sol.n_extra is None else sol.n_extra
        self._made: dict[int, CalibrationResult] = {}
        self._all_stats: dict | None = None
        self.suspects: list[list[Suspect]] = [[] for _ in names]  # per robot, gross errors left out of its fit

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, b):
        if isinstance(b, slice):
            return [self[i] for i in range(*b.indices(len(self)))]
        b = range(len(self))[b]  # negative indices, and an IndexError past the end
        if b not in self._made:
            self._made[b] = self._build(b, self._all_stats or self._stats(slice(b, b + 1), offset=b))
        return self._made[b]

    def __iter__(self):
        if len(self._made) < len(self):
            # a pass over every robot: the reasons and statistics of all of them at once
            if hasattr(self.reasons, "fill"):
                self.reasons.fill()
            if self._all_stats is None:
                self._all_stats = self._stats(slice(None), offset=0)
        return (self[b] for b in range(len(self)))

    def converged(self) -> list[bool]:
        """Whether each robot's solver converged, without building the results."""
        if hasattr(self.solver, "converged"):
            return self.solver.converged()
        return [s.converged for s in self.solver]

    def table(self) -> dict:
        """The parameters' ``names``, ``units``, the robot's ``markers`` and, as ``(R, K)`` nested
        lists read from the tensors, ``values``, ``free`` and ``std_errors`` (the fleet report's
        parameter spread needs no per-robot result)."""
        return {"names": self.template.names, "units": self.template.units, "markers": self.robot.marker_names,
                "values": self.X.tolist(), "free": self._host["free"], "std_errors": self._host["se"]}

    # ------------------------------------------------------------------ building one robot
    @cached_property
    def errors(self) -> dict[str, Tensor | None]:
        """``(R, N, M)`` errors (m): training and held-out, nominal and final."""
        R_, N, M = self.fd.seen.shape
        out = {"E0": self.fd.errors(self.robot, self.X0),
               "E": self.residuals.reshape(R_, -1)[:, :N * M * 3].reshape(R_, N, M, 3).norm(dim=-1),
               "Et0": None, "Et": None}
        if self.fd_test is not None:
            out["Et0"] = self.fd_test.errors(self.robot, self.X0)
            out["Et"] = self.fd_test.errors(self.robot, self.X) if self._test_errors is None else self._test_errors
        return out

    @cached_property
    def details(self) -> dict[str, list]:
        """Per split and stage (nominal, final), each robot's plotted error details (what
        :func:`~torchcal.measure.details.error_details` gives one data set), from the error vectors
        of all robots in one pass."""
        R_, N, M = self.fd.seen.shape
        final = self.residuals.reshape(R_, -1)[:, :N * M * 3].reshape(R_, N, M, 3)
        out = {"train": [self.fd.details(self.robot, self.X0, self.fd.error_vectors(self.robot, self.X0)),
                         self.fd.details(self.robot, self.X, final)]}
        if self.fd_test is not None:
            vt = self._test_vectors if self._test_vectors is not None else self.fd_test.error_vectors(self.robot, self.X)
            out["test"] = [self.fd_test.details(self.robot, self.X0, self.fd_test.error_vectors(self.robot, self.X0)),
                           self.fd_test.details(self.robot, self.X, vt)]
        return out

    def _stats(self, sel: slice, offset: int) -> dict:
        """Error statistics per stage of robots ``sel`` (``offset``: the first one's index)."""
        e, mk = self.errors, self.robot.marker_names
        out = {"offset": offset, "train": [errors_by_marker_batched(e[k][sel], self.fd.seen[sel], mk)
                                           for k in ("E0", "E")]}
        if self.fd_test is not None:
            out["test"] = [errors_by_marker_batched(e[k][sel], self.fd_test.seen[sel], mk) for k in ("Et0", "Et")]
        return out

    @cached_property
    def _host(self) -> dict:
        """What building a result reads as Python numbers, fetched from the device once."""
        return {"free": self.free.tolist(), "se": self.se.tolist(), "n_extra": self.n_extra.tolist(),
                "cand": self.template.free.tolist()}

    def _build(self, b: int, stats: dict) -> CalibrationResult:
        h = self._host
        p = self.template.clone()
        p.values, p.free = self.X[b].clone(), self.free[b].clone()
        start = self.template.clone()
        start.values = self.X0[b].clone()
        free = h["free"][b]
        std = {n: v for n, v, f in zip(p.names, h["se"][b], free) if f}
        dropped = [n for n, c, f in zip(p.names, h["cand"], free) if c and not f]
        reasons = self.reasons[b]
        stages, errors = self._stages(b, stats, sum(free) + h["n_extra"][b])
        return CalibrationResult(robot=self.robot, params=p, std_errors=std,
                                 unidentifiable={n: reasons.get(n, "not identifiable") for n in dropped},
                                 stages=stages, solver=self.solver[b], method="lm", n_train=self.n_train[b],
                                 n_test=self.n_test[b], start=start, loss="l2", wall_time_s=self.wall_time_s,
                                 errors=errors, suspects=self.suspects[b])

    def _stages(self, b: int, stats: dict, k: int) -> tuple[list[Stage], dict[str, StageErrors]]:
        """Robot ``b``'s stages (nominal, then the fitted model with ``k`` parameters): their error
        statistics, and the errors per stage and split that the plots read."""
        s, has_test = b - stats["offset"], self.has_test[b]
        stages, errors = [], {}
        for i, (name, n) in enumerate((("nominal", 0), (self.stage, k))):
            stages.append(Stage(name, n, stats["train"][i][s], stats["test"][i][s] if has_test else None))
            errors[name] = StageErrors(self.details["train"][i][b], self.details["test"][i][b] if has_test else None)
        return stages, errors
