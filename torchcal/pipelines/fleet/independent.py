"""The fleet's robots solved as independent problems in one batch: each robot's identifiable set
judged, its parameters fitted by the block-diagonal Levenberg-Marquardt, judged again at the
solution, and refitted while the set grows or a parameter its data pin down worse than its
plausible size leaves: the rounds of :func:`~torchcal.pipelines.rounds.fit_rounds`, with each
piece batched over the robots (:mod:`torchcal.pipelines.rounds` says where the batch's rounds
differ from :func:`~torchcal.pipelines.fitting.fit_identified`'s for one robot)."""
from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.optim.lm_batched import lm_batched
from torchcal.pipelines.fitting import FitOptions
from torchcal.pipelines.precision import drop_imprecise
from torchcal.pipelines.fleet.data import BASE_NAMES, FleetData, check_rows
from torchcal.params import ParamSet
from torchcal.pipelines.fleet.identify import FleetDecision, check_rank, decide
from torchcal.pipelines.fleet.options import FleetOptions
from torchcal.pipelines.fleet.solution import FleetSolution
from torchcal.pipelines.fleet.views import FleetReasons, FleetSolvers
from torchcal.pipelines.rounds import fit_rounds
from torchcal.problems.uncertainty import residual_noise, standard_errors

__all__ = ["solve_independent", "pooled_decision"]


def pooled_decision(robot: Robot, fd: FleetData, X: Tensor, cand: Tensor, names_c: list[str], prefer=None):
    """The identifiable candidates of the pooled design: every robot's poses at the fleet's mean
    parameters in the robot base frame, judged as one data set (one kept set for all robots)."""
    bi = [robot.param_names.index(n) for n in BASE_NAMES]
    xm = X.mean(0, keepdim=True).clone()
    xm[:, bi] = 0.0
    R_ = X.shape[0]
    idx = torch.arange(R_, device=X.device)
    J = fd.jacobian(robot, xm.expand(R_, -1), idx, cols=cand.tolist())
    return decide(J.reshape(1, -1, J.shape[-1]), names_c, robot.marker_names, prefer)


def solve_independent(robot: Robot, fd: FleetData, template: ParamSet, X0: Tensor, names: list[str],
                      opt: FleetOptions) -> FleetSolution:
    """Rounds of judge -> batched LM -> judge again at the solution, per robot
    (:func:`~torchcal.pipelines.rounds.fit_rounds`, as :func:`torchcal.pipelines.fitting.fit_identified`
    runs them for one robot with ``noise="residuals"``, as :func:`~torchcal.pipelines.calibrate.calibrate`
    calls it): a parameter that grows identifiable is fitted in the next round; one the robot's data
    pin down worse than its plausible size is fixed at its start for good and the robot refitted
    without it. The LM's Jacobian at its solution serves the next judgement and the next round's start.

    Every decision is a batched tensor over the candidate parameters; a round waits for the device
    only to learn which robots go on. The reasons in words and each robot's solver record are
    views, written when read (:mod:`torchcal.pipelines.fleet.views`)."""
    batch = _Batch(robot, fd, template, X0, names, opt)
    fit_rounds(batch, FitOptions().rounds)
    return batch.solution()


class _Batch:
    """The pieces of a round (:class:`~torchcal.pipelines.rounds.Rounds`) for ``R`` robots at once,
    each a batched tensor operation over the robots still changing.

    State: ``X (R, K)`` current values; ``free (R, K)`` what each robot fits; ``loose (R, k)`` the
    candidates fixed for imprecision for good, with their standard errors and the noise (m) they
    were judged at; ``decisions``: ``(decision, its row per robot, robots)`` per judgement, later
    entries winning; ``todo``: the robots the next fit refits."""

    def __init__(self, robot: Robot, fd: FleetData, template: ParamSet, X0: Tensor, names: list[str],
                 opt: FleetOptions):
        self.robot, self.fd, self.template, self.X0, self.names = robot, fd, template, X0, names
        self.identify, self.prefer, self.lm = opt.identify, opt.prefer, opt.options
        R_, dev = X0.shape[0], X0.device
        self.cand = template.free_index
        self.cand_list = self.cand.tolist()
        self.names_c = [template.names[i] for i in self.cand_list]
        self.units_c = [template.units[i] for i in self.cand_list]
        self.limit = torch.tensor([opt.plausible.get(u, float("inf")) for u in self.units_c], dtype=X0.dtype,
                                  device=dev)
        self.everyone = torch.arange(R_, device=dev)
        self.precise = self.identify != "pooled"  # a pooled design pins every robot's parameters down together
        self.loose = torch.zeros(R_, self.cand.numel(), dtype=torch.bool, device=dev)
        self.loose_se, self.loose_noise = X0.new_zeros(self.loose.shape), X0.new_zeros(self.loose.shape)
        self.fits: list = []
        self.fit_of = torch.zeros(R_, dtype=torch.long, device=dev)
        self.at = torch.zeros(R_, dtype=torch.long, device=dev)

    def in_k(self, t: Tensor) -> Tensor:
        """``(b, k)`` candidate columns spread into ``(b, K)`` (zeros elsewhere)."""
        return torch.zeros(t.shape[0], self.X0.shape[1], dtype=t.dtype, device=t.device).index_copy_(1, self.cand, t)

    def jacobian(self, Xb: Tensor, idx: Tensor) -> Tensor:
        return self.fd.jacobian(self.robot, Xb, idx, cols=self.cand_list)

    def decide(self, X: Tensor, J: Tensor, idx: Tensor):
        """``(decision, kept (b, k), the decision's row per robot)`` for robots ``idx``."""
        dev = X.device
        if self.identify == "pooled":
            d = pooled_decision(self.robot, self.fd, X, self.cand, self.names_c, self.prefer)
            return d, d.kept.expand(idx.numel(), -1), torch.zeros(idx.numel(), dtype=torch.long, device=dev)
        # a parameter already fixed for imprecision is no candidate: its column is left out (zero)
        d = decide(J, self.names_c, self.robot.marker_names, self.prefer, out=self.loose[idx])
        return d, d.kept, torch.arange(idx.numel(), device=dev)

    def fit(self, sub: Tensor, J0: Tensor | None):
        """The batched LM on robots ``sub`` from their current values (``J0``: their Jacobian there)."""
        fd, robot = self.fd, self.robot
        res = lm_batched(lambda Xb, i: fd.residuals(robot, Xb, sub[i]), lambda Xb, i: self.jacobian(Xb, sub[i]),
                         self.X[sub], self.free[sub], self.template.lower, self.template.upper, jac0=J0,
                         columns=self.cand, **self.lm)
        self.X[sub], self.r_fin[sub], self.J_fin[sub] = res.x, res.residuals, res.jacobian
        self.fit_of[sub], self.at[sub] = len(self.fits), torch.arange(sub.numel(), device=sub.device)
        # a record needs neither the residuals nor the (b, m, k) Jacobian: keep copies of nothing, not views
        self.fits.append(replace(res, residuals=res.residuals.new_zeros(0), jacobian=res.jacobian.new_zeros(0)))
        return res

    def precision(self, d: FleetDecision, nxt: Tensor, res, sub: Tensor) -> Tensor:
        """``(b, k)`` the kept candidates robots ``sub`` pin down worse than their plausible size at
        the noise their fit shows, recorded as loose for good."""
        noise = residual_noise(res.residuals, self.free[sub].sum(-1))
        drop, se = _imprecise(d, nxt, self.limit, noise)
        self.loose_se[sub] = torch.where(drop, se, self.loose_se[sub])
        self.loose_noise[sub] = torch.where(drop, noise[:, None], self.loose_noise[sub])
        self.loose[sub] |= drop
        return drop

    # ------------------------------------------------------------------ the Rounds hooks
    def start(self) -> None:
        X0, everyone = self.X0, self.everyone
        J = self.jacobian(X0, everyone)
        dec, kept, row = self.decide(X0, J, everyone)
        self.decisions = [(dec, row, everyone)]
        self.free = self.in_k(kept)
        check_rows(self.fd, self.free, self.names)
        self.X = X0.clone()
        self.r_fin, self.J_fin = X0.new_zeros(X0.shape[0], J.shape[1]), torch.zeros_like(J)
        self.todo, self.J = everyone, J

    def solve(self) -> None:
        self.sub = self.todo
        self.res = self.fit(self.sub, self.J)

    def judge(self, last: bool):
        """Rank and precision at the solution: ``(decision, next kept set, its rows, which robots
        change, which dropped a fitted parameter)`` over the robots just fitted, or None."""
        sub, res = self.sub, self.res
        d2, nxt, row2 = self.decide(self.X[sub], res.jacobian, sub)
        was = self.free[sub][:, self.cand]
        new_loose = torch.zeros_like(nxt)
        if self.precise:
            drop = self.precision(d2, nxt, res, sub)
            nxt = nxt & ~drop
            new_loose = drop & was  # dropped now, fitted until now
        change = (nxt & ~was).any(-1) | new_loose.any(-1)
        if not bool(change.any()):
            return None
        return d2, nxt, row2, change, new_loose

    def advance(self, step, last: bool) -> bool:
        """The changed robots' next fit: imprecise values back to their start, the new set free.
        After the last round a robot that grew is judged, not refitted (as fit_identified), but
        none keeps a value its data cannot pin down."""
        d2, nxt, row2, change, new_loose = step
        todo = self.todo = self.sub[change]
        self.decisions.append((d2, row2[change], todo))
        reset = new_loose[change].any(-1)
        lk = self.in_k(self.loose[todo])
        self.X[todo] = torch.where(lk, self.X0[todo], self.X[todo])
        if last:
            refit = todo[reset]
            if refit.numel():
                self.free[refit] &= ~self.in_k(self.loose[refit])
                self.fit(refit, None)
            return False
        self.free[todo] = self.in_k(nxt[change])
        # a robot whose values were reset starts away from the solution: its Jacobian is computed anew.
        # So is every other robot's then: the LM's iterates depend on where its Jacobians come
        # from, and a parameter the data barely pin down stops wherever they lead (by 1e-7 m)
        self.J = self.res.jacobian[change] if not bool(reset.any()) else None
        return False

    def solution(self) -> FleetSolution:
        _check_ranks(self.decisions, self.names)
        f = self.free[:, self.cand]
        se = self.in_k(standard_errors(self.J_fin, self.r_fin, free=f, rows=3 * self.fd.n_obs))
        return FleetSolution(X=self.X, free=self.free, se=se, r=self.r_fin,
                             reasons=FleetReasons(self.decisions, self.names_c, self.units_c, self.loose,
                                                  self.loose_se, self.loose_noise),
                             solver=FleetSolvers(self.fits, self.fit_of, self.at, self.free))


def _imprecise(d: FleetDecision, kept: Tensor, limit: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
    """``(drop, se)``: ``(B, k)`` the kept candidates each robot's data pin down worse than ``limit``
    (:func:`~torchcal.pipelines.precision.drop_imprecise`) and their standard errors. Only the
    columns some robot keeps take part: the others are outside every robot's set anyway."""
    use = torch.nonzero(kept.any(0)).flatten()
    # the judgement's R factor times the column norms has the Jacobian's Gram matrix in k rows
    J = (d.An * d.norms[:, None, :])[:, :, use]
    step, se = drop_imprecise(J, kept[:, use], limit[use], noise)
    drop = torch.zeros_like(kept).index_copy_(1, use, step >= 0)
    return drop, torch.zeros_like(d.norms).index_copy_(1, use, se)


def _check_ranks(decisions: list, names: list[str]) -> None:
    """:func:`check_rank` of each robot's last decision, one call per judgement."""
    R_ = decisions[0][2].numel()
    last = torch.full((R_,), -1, dtype=torch.long, device=decisions[0][2].device)
    for t, (_, _, who) in enumerate(decisions):
        last[who] = t
    for t, (d, row, who) in enumerate(decisions):
        mine = last[who] == t
        rows, robots = row[mine], who[mine]

        def label(rw, rows=rows, robots=robots):
            return names[int(robots[rows == rw][-1])]
        check_rank(d, torch.unique(rows), label)
