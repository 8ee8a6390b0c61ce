"""The fleet's robots solved as independent problems in one batch: each robot's identifiable set
judged, its parameters fitted by the block-diagonal Levenberg-Marquardt, judged again at the
solution, and refitted while the set grows or a parameter its data pin down worse than its
plausible size leaves, as :func:`~torchcal.pipelines.fitting.fit_identified` does for one robot."""
from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.optim.lm_batched import lm_batched
from torchcal.pipelines.fitting import drop_imprecise
from torchcal.pipelines.fleet.data import BASE_NAMES, FleetData, check_rows
from torchcal.pipelines.fleet.identify import FleetDecision, check_rank, decide
from torchcal.params import ParamSet
from torchcal.pipelines.fleet.options import FleetOptions
from torchcal.pipelines.fleet.solution import FleetSolution
from torchcal.pipelines.fleet.views import FleetReasons, FleetSolvers
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
    """Rounds of judge -> batched LM -> judge again at the solution, per robot, as
    :func:`torchcal.pipelines.fitting.fit_identified` does for one robot (with ``noise="residuals"``,
    as :func:`~torchcal.pipelines.calibrate.calibrate` calls it): a parameter that grows identifiable
    is fitted in the next round; one the robot's data pin down worse than its plausible size is
    fixed at its start for good and the robot refitted without it. The LM's Jacobian at its
    solution serves the next judgement and the next round's start.

    Every decision is a batched tensor over the candidate parameters; a round waits for the device
    only to learn which robots go on. The reasons in words and each robot's solver record are
    views, written when read (:mod:`torchcal.pipelines.fleet.views`)."""
    identify, prefer, opts, plausible = opt.identify, opt.prefer, opt.options, opt.plausible
    R_, K = X0.shape
    dev = X0.device
    cand = template.free_index
    in_k = lambda t: torch.zeros(t.shape[0], K, dtype=t.dtype, device=dev).index_copy_(1, cand, t)  # noqa: E731
    names_c = [template.names[i] for i in cand.tolist()]
    units_c = [template.units[i] for i in cand.tolist()]
    limit = torch.tensor([plausible.get(u, float("inf")) for u in units_c], dtype=X0.dtype, device=dev)
    everyone = torch.arange(R_, device=dev)
    precise = identify != "pooled"  # a pooled design pins every robot's parameters down together
    loose = torch.zeros(R_, cand.numel(), dtype=torch.bool, device=dev)  # fixed for imprecision, for good
    loose_se, loose_noise = X0.new_zeros(loose.shape), X0.new_zeros(loose.shape)

    cand_list = cand.tolist()

    def jacobian(Xb, idx):
        return fd.jacobian(robot, Xb, idx, cols=cand_list)

    def judge(X, J, idx):
        if identify == "pooled":
            d = pooled_decision(robot, fd, X, cand, names_c, prefer)
            return d, d.kept.expand(idx.numel(), -1), torch.zeros(idx.numel(), dtype=torch.long, device=dev)
        # a parameter already fixed for imprecision is no candidate: its column is left out (zero)
        d = decide(J, names_c, robot.marker_names, prefer, out=loose[idx])
        return d, d.kept, torch.arange(idx.numel(), device=dev)

    J = jacobian(X0, everyone)
    dec, kept, row = judge(X0, J, everyone)
    decisions = [(dec, row, everyone)]  # (decision, its row per robot, robots): later entries win
    free = in_k(kept)
    check_rows(fd, free, names)
    X = X0.clone()
    r_fin, J_fin = X.new_zeros(R_, J.shape[1]), torch.zeros_like(J)
    fits: list = []
    fit_of, at = torch.zeros(R_, dtype=torch.long, device=dev), torch.zeros(R_, dtype=torch.long, device=dev)
    todo = everyone
    rounds = 3

    def fit(sub, J0):
        res = lm_batched(lambda Xb, i: fd.residuals(robot, Xb, sub[i]), lambda Xb, i: jacobian(Xb, sub[i]), X[sub],
                         free[sub], template.lower, template.upper, jac0=J0, columns=cand, **opts)
        X[sub], r_fin[sub], J_fin[sub] = res.x, res.residuals, res.jacobian
        fit_of[sub], at[sub] = len(fits), torch.arange(sub.numel(), device=dev)
        # a record needs neither the residuals nor the (b, m, k) Jacobian: keep copies of nothing, not views
        fits.append(replace(res, residuals=res.residuals.new_zeros(0), jacobian=res.jacobian.new_zeros(0)))
        return res

    for i in range(rounds):
        sub = todo
        res = fit(sub, J)
        d2, nxt, row2 = judge(X[sub], res.jacobian, sub)
        was = free[sub][:, cand]
        new_loose = torch.zeros_like(nxt)
        if precise:
            noise = residual_noise(res.residuals, free[sub].sum(-1))
            drop, se = _imprecise(d2, nxt, limit, noise)
            nxt = nxt & ~drop
            loose_se[sub] = torch.where(drop, se, loose_se[sub])
            loose_noise[sub] = torch.where(drop, noise[:, None], loose_noise[sub])
            loose[sub] |= drop
            new_loose = drop & was  # dropped now, fitted until now
        change = (nxt & ~was).any(-1) | new_loose.any(-1)
        if not bool(change.any()):
            break
        todo = sub[change]
        decisions.append((d2, row2[change], todo))
        reset = new_loose[change].any(-1)
        lk = in_k(loose[todo])
        X[todo] = torch.where(lk, X0[todo], X[todo])  # imprecise values back to their start
        if i == rounds - 1:
            # a robot that grows after the last round is judged, not refitted (as fit_identified),
            # but none keeps a value its data cannot pin down
            refit = todo[reset]
            if refit.numel():
                free[refit] &= ~in_k(loose[refit])
                fit(refit, None)
            break
        free[todo] = in_k(nxt[change])
        # a robot whose values were reset starts away from the solution: its Jacobian is computed anew.
        # So is every other robot's then: the LM's iterates depend on where its Jacobians come
        # from, and a parameter the data barely pin down stops wherever they lead (by 1e-7 m)
        J = res.jacobian[change] if not bool(reset.any()) else None
    _check_ranks(decisions, names)
    f = free[:, cand]
    se = in_k(standard_errors(J_fin, r_fin, free=f, rows=3 * fd.n_obs))
    return FleetSolution(X=X, free=free, se=se, r=r_fin,
                         reasons=FleetReasons(decisions, names_c, units_c, loose, loose_se, loose_noise),
                         solver=FleetSolvers(fits, fit_of, at, free))


def _imprecise(d: FleetDecision, kept: Tensor, limit: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
    """``(drop, se)``: ``(B, k)`` the kept candidates each robot's data pin down worse than ``limit``
    (:func:`~torchcal.pipelines.fitting.drop_imprecise`) and their standard errors. Only the
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
