"""A fleet whose robots share something: a hierarchical prior, a payload, or both.

**Hierarchical prior.** Each robot's geometric errors (joint origins, offsets, DH errors; not the
instrument frame, nor the marker points) are drawn around the fleet mean ``m``:
``x_rj ~ N(m_j, τ_j²)``. The MAP fit adds the rows ``(σ/τ_j)(x_rj − m_j)`` to every robot and
fits ``m`` with them; a robot with few poses is pulled towards its siblings along the directions its
own data cannot see. The scales ``τ_j`` and the noise ``σ`` are estimated from the fleet by
expectation-maximisation (empirical Bayes): ``τ_j² = mean_r((x_rj − m_j)² + Var_rj)`` and
``σ² = (SSR + σ² Σ_r tr(H_r⁻¹ J_rᵀJ_r)) / n_rows``, until they settle.

**Joint compliance fleet-wide.** Each robot's joints twist with the gravity torque,
``Δq_j = c_rj τ_j(q; μ)`` (:class:`~torchcal.effects.JointCompliance`: URDF inertials plus an
unknown payload ``μ = (m, m·s)``), with its own compliances ``c_r`` and a payload shared by the
fleet or its own. The Jacobian columns of ``c`` and ``μ`` follow from the zero-offset columns of the
analytic kinematic Jacobian (an offset moves the chain exactly as the joint does).

Both are solved by :func:`~torchcal.optim.lm_linear.lm_arrow` over per-robot blocks and the shared
parameters, and judged on the pooled design (one identifiable set for every robot).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.kinematics.robot import Robot
from torchcal.optim import Result
from torchcal.optim.lm_linear import arrow_solve, lm_arrow
from torchcal.params import ParamSet
from torchcal.pipelines.fitting import FitOptions
from torchcal.pipelines.precision import imprecise
from torchcal.pipelines.fleet.coupled_model import CoupledModel, block_layout, fleet_compliance
from torchcal.pipelines.fleet.data import FleetData, check_rows
from torchcal.pipelines.fleet.identify import decide, explain
from torchcal.pipelines.fleet.options import FleetOptions
from torchcal.pipelines.fleet.solution import FleetSolution
from torchcal.pipelines.rounds import fit_rounds
from torchcal.problems.uncertainty import standard_errors

__all__ = ["solve_coupled", "PRIOR_START"]

PRIOR_START = {"m": 1e-3, "rad": 1e-3}  # starting prior scales (m, rad) before they are estimated
_EM_ROUNDS, _EM_RTOL = 100, 1e-3  # scale updates on the linearised fleet: rounds without kinematics
_OUTER, _OUTER_RTOL = 4, 1e-2  # relinearisations: the fit depends little on a scale's last per cent
_TAU_FLOOR = 1e-3  # relative to PRIOR_START: below 1 µm / 1 µrad a scale's relative change is moot
_SIGMA_START = 2e-5  # m: a tracker's noise, only to weigh the first round; EM replaces it
# plausible sizes of effect parameters (one standard error): beyond them the data do not see them
PLAUSIBLE_EFFECT = {"rad/(N*m)": 1e-3, "kg": 50.0, "kg*m": 10.0}


@dataclass
class _Fit:
    """One coupled fit: per-robot blocks ``Z (R, K + T (+4))`` and shared ``s (np + 4)`` values, the
    arrow LM's result, and with a prior its scales ``tau (np,)`` (m, rad), the noise ``sigma`` (m),
    the scale updates run and whether the scales were estimated."""

    Z: Tensor
    s: Tensor
    res: object
    tau: Tensor | None = None
    sigma: float | None = None
    rounds: int = 0
    estimated: bool = False


def _judge(model, Z, pay, cand, names, units, prefer, noise: float):
    """One identifiable set for every robot, judged on the pooled design: all robots' rows at the
    fleet mean, the instrument frame at 0 (the robot base frame). Effect parameters the pooled
    data determine worse than their plausible size (:data:`PLAUSIBLE_EFFECT`, one standard error
    at ``noise`` m) are dropped too: a twist about an axis gravity hardly loads is noise."""
    Zm = Z.mean(0, keepdim=True).expand_as(Z).clone()
    Zm[:, :6] = 0.0
    _, Jz, Jpay = model.data(Zm, pay)
    J = torch.cat([Jz, Jpay], -1)
    J = J.reshape(1, -1, J.shape[-1])[:, :, cand]
    nm, un = [names[i] for i in cand.tolist()], [units[i] for i in cand.tolist()]
    d = decide(J, nm, model.robot.marker_names, prefer)
    why = explain(d, nm, un)[0]
    keep = torch.nonzero(d.kept[0]).flatten().tolist()
    loose = imprecise(J[0][:, keep], [nm[i] for i in keep], [un[i] for i in keep], noise, PLAUSIBLE_EFFECT)
    for n, se in loose.items():
        d.kept[0, nm.index(n)] = False
        why[n] = (f"{n} is determined only to ±{se:.3g} {un[nm.index(n)]} by the fleet's poses (noise "
                  f"{noise * 1e3:.3g} mm), more than it can plausibly be")
    kept = torch.zeros(len(names), dtype=torch.bool, device=Z.device)
    kept[cand] = d.kept[0]
    return kept, why


def solve_coupled(robot: Robot, fd: FleetData, template: ParamSet, X0: Tensor, names: list[str],
                  opt: FleetOptions) -> FleetSolution:
    """Fit the fleet with a hierarchical prior and/or joint compliance (see the module docstring):
    ``opt.prior``, ``opt.prior_scale``, ``opt.effects``, ``opt.payload``, ``opt.prefer`` and the
    LM's ``opt.options`` (:class:`~torchcal.pipelines.fleet.options.FleetOptions`), in the rounds of
    :func:`~torchcal.pipelines.rounds.fit_rounds`: judge, fit, judge again at the solution while
    the set changes; the payload's columns vanish while the compliances are 0, so it enters in the
    second round."""
    fleet = _Coupled(robot, fd, template, X0, names, opt)
    fit_rounds(fleet, FitOptions().rounds)
    return _finish(fleet.model, fleet.fit, fleet.free, fleet.why, template, *fleet.layout, opt.prior)


class _Coupled:
    """The pieces of a round (:class:`~torchcal.pipelines.rounds.Rounds`) for a coupled fleet: one
    identifiable set for every robot, judged on the pooled design at the noise of the last fit
    (effect parameters too imprecise leave in the same judgement), and the arrow LM over every
    robot's block and the shared parameters (with a prior, its scales by EM)."""

    def __init__(self, robot: Robot, fd: FleetData, template: ParamSet, X0: Tensor, names: list[str],
                 opt: FleetOptions):
        self.fd, self.template, self.names = fd, template, names
        self.prior, self.prior_scale, self.prefer = opt.prior, opt.prior_scale, opt.prefer
        self.lm = {k: v for k, v in (opt.options or {}).items() if k in ("max_iter", "tau", "gtol", "xtol", "ftol")}
        R_, K = X0.shape
        dev = X0.device
        comp = fleet_compliance(robot, list(opt.effects or []), opt.payload)
        model = self.model = CoupledModel(robot, fd, comp, opt.payload)
        self.layout = block_layout(robot, template, model)
        self.geo = torch.tensor([not n.startswith("base.") and n.split(".")[0] not in robot.marker_names
                                 for n in template.names], device=dev)
        self.cand = torch.nonzero(torch.cat([template.free, torch.ones(model.kz - K + model.n_pay, dtype=torch.bool,
                                                                        device=dev)])).flatten()
        self.Z = torch.cat([X0, X0.new_zeros(R_, model.kz - K)], 1)
        self.pay = X0.new_zeros(model.n_pay)
        self.noise = _SIGMA_START
        self.free, self.why, self.fit = None, {}, None

    def judge_here(self) -> tuple[Tensor, dict]:
        names_z, units_z, names_p, units_p = self.layout
        return _judge(self.model, self.Z, self.pay, self.cand, names_z + names_p, units_z + units_p, self.prefer,
                      self.noise)

    # ------------------------------------------------------------------ the Rounds hooks
    def start(self) -> None:
        self.advance(self.judge_here(), last=False)

    def solve(self) -> None:
        model, free, R_ = self.model, self.free, self.Z.shape[0]
        s = torch.cat([self.Z[:, model.P].mean(0) if self.prior else self.pay[:0], self.pay])
        fit = self.fit = _fit(model, self.Z, s, free[: model.kz], free[model.kz:], self.prior, self.prior_scale,
                              self.template, self.lm)
        self.Z, self.pay = fit.Z, fit.s[model.np:]
        md = self.fd.n_obs.sum() * 3
        ssr = (fit.res.r[:, : model.md] ** 2).sum()
        self.noise = fit.sigma or float(ssr / (md - free.sum() * R_).clamp(min=1)) ** 0.5

    def judge(self, last: bool):
        """The set judged at the solution when it differs from the one fitted; none after the last fit."""
        if last:
            return None
        kept, why = self.judge_here()
        return None if bool((kept == self.free).all()) else (kept, why)

    def advance(self, change, last: bool) -> bool:
        self.free, self.why = change
        K, R_ = self.model.K, self.Z.shape[0]
        if not self.prior:
            check_rows(self.fd, self.free[None, :K].expand(R_, -1), self.names)
        self.model.P = torch.nonzero(self.free[:K] & self.geo).flatten() if self.prior else None
        return False


def _fit(model, Z, s, free_z, free_s, prior, prior_scale, template, opts) -> _Fit:
    """One fit; with a prior, its scales and the noise by EM until they settle."""
    R_ = Z.shape[0]
    zfree = free_z.expand(R_, -1)
    if not prior:
        res = lm_arrow(model, Z, s, zfree, free_s, **opts)
        return _Fit(res.Z, res.s, res)
    P = model.P
    names = [template.names[i] for i in P.tolist()]
    units = [template.units[i] for i in P.tolist()]
    # an earlier identifiability round's estimates are the best start
    tau = torch.tensor([model.scales.get(n, (prior_scale or PRIOR_START)[u]) for n, u in zip(names, units)],
                       dtype=Z.dtype, device=Z.device)
    floor = torch.tensor([_TAU_FLOOR * PRIOR_START[u] for u in units], dtype=Z.dtype, device=Z.device)
    sfree = torch.cat([torch.ones(model.np, dtype=torch.bool, device=Z.device), free_s])
    n_rows = float(model.fd.n_obs.sum()) * 3
    sigma, rounds = model.scales.get("sigma", _SIGMA_START), 0
    for _ in range(_OUTER):
        model.w = sigma / tau
        res = lm_arrow(model, Z, s, zfree, sfree, **opts)
        Z, s = res.Z, res.s
        tau0, sigma0 = tau, sigma
        tau, sigma, n = _scales(model, Z, s, zfree, sfree, tau, sigma, floor, prior_scale is None, n_rows)
        rounds += n
        if max(abs(sigma / sigma0 - 1), _rel(tau, tau0, floor)) < _OUTER_RTOL:
            break
    model.scales = {"sigma": sigma, **dict(zip(names, tau.tolist()))}
    model.w = sigma / tau
    res = lm_arrow(model, Z, s, zfree, sfree, **opts)
    return _Fit(res.Z, res.s, res, tau, sigma, rounds, prior_scale is None)


def _scales(model, Z, s, zfree, sfree, tau, sigma, floor, estimate_tau: bool, n_rows: float):
    """The noise σ and the prior scales τ that the fleet's data support, on the model linearised
    at ``(Z, s)``: each round one exact solve of the linear MAP problem, then MacKay's evidence
    updates ``σ² = SSR / (n − Σ edf)`` and ``τ_j² = Σ_r (x_rj − m_j)² / Σ_r γ_rj``, where
    ``γ = 1 − Var / τ²`` counts how much a robot's own data, not the prior, determine ``x_rj``."""
    n, P = model.np, model.P
    cols = torch.nonzero(zfree.any(0)).flatten()
    zc, f = zfree[:, cols], zfree[:, cols].to(Z.dtype)
    Pc = torch.searchsorted(cols, P)
    d0, Jd, Jpay = model.data(Z, s[n:])
    Jd = Jd[:, :, cols] * f[:, None, :]
    JdT = Jd.transpose(-1, -2)
    Hd, Hdp, gd = torch.bmm(JdT, Jd), torch.bmm(JdT, Jpay), torch.bmm(JdT, d0[..., None])[..., 0]
    Hpp, gp = torch.einsum("rmi,rmj->ij", Jpay, Jpay), torch.einsum("rmi,rm->i", Jpay, d0)
    e0 = Z[:, P] - s[:n]
    R_, ar = Z.shape[0], torch.arange(n, device=Z.device)
    rounds = 0
    for rounds in range(1, _EM_ROUNDS + 1):
        w2 = (sigma / tau) ** 2
        Hzz = Hd.clone()
        Hzz[:, Pc, Pc] += w2
        Hzs = torch.cat([Z.new_zeros(R_, cols.numel(), n), Hdp], -1)
        Hzs[:, Pc, ar] = -w2
        Hss = torch.block_diag(torch.diag(R_ * w2), Hpp)
        gz = gd.clone()
        gz[:, Pc] += w2 * e0
        gs = torch.cat([-(w2 * e0).sum(0), gp])
        dz, ds, L = arrow_solve(Hzz, Hzs, Hss, gz, gs, zc, sfree)
        Hinv = torch.cholesky_inverse(L)
        d = d0 + torch.bmm(Jd, dz[..., None])[..., 0] + Jpay @ ds[n:]
        edf = float(torch.einsum("rij,rji->", Hinv, Hd))
        sigma_new = (float((d * d).sum()) / max(n_rows - edf, 1.0)) ** 0.5
        tau_new = tau
        if estimate_tau:
            gamma = (1 - sigma ** 2 * Hinv[:, Pc, Pc] / tau ** 2).clamp(min=1e-6)
            dev = (e0 + dz[:, Pc] - ds[:n]) ** 2
            tau_new = (dev.sum(0) / gamma.sum(0)).sqrt().clamp(min=1e-12)
        change = max(abs(sigma_new / sigma - 1), _rel(tau_new, tau, floor))
        sigma, tau = sigma_new, tau_new
        if change < _EM_RTOL:
            break
    return tau, sigma, rounds


def _rel(a: Tensor, b: Tensor, floor: Tensor) -> float:
    """Largest relative change; a scale on its way to 0 need not settle in relative terms."""
    return float(((a - b).abs() / torch.maximum(b, floor)).max()) if a.numel() else 0.0


def _finish(model, fit: _Fit, free, why, template, names_z, units_z, names_p, units_p, prior) -> FleetSolution:
    """The coupled fit as a fleet solution: standard errors at the fitted noise (the prior's σ, or
    each robot's own as :func:`~torchcal.pipelines.calibrate.calibrate` estimates it), a solver
    record per robot, the effects' and the prior's parameters."""
    res, K, Z = fit.res, model.K, fit.Z
    R_ = Z.shape[0]
    fz = free[: model.kz].expand(R_, -1).clone()
    se = standard_errors(res.Jz, res.r[:, : model.md], fit.sigma if prior else None, free=fz, rows=3 * model.fd.n_obs)
    se = torch.where(fz, se, float("nan"))
    solver = [Result(x=Z[b, fz[b]], fun=float((res.r[b] ** 2).sum()), n_evals=res.n_iter + 1, n_iter=res.n_iter,
                     wall_time_s=res.wall_time_s, converged=res.converged, message=res.message, method="lm-arrow")
              for b in range(R_)]
    effects = test_errors = None
    if model.comp is not None:
        effects = _effects(model, fit, fz, se, free, names_z, units_z, names_p, units_p)
        test_errors = _held_out(model, fit)
    return FleetSolution(X=Z[:, :K], free=fz, se=se, r=res.r[:, : model.md], reasons=[dict(why) for _ in range(R_)],
                         solver=solver, stage="geometric + joint_compliance" if model.comp is not None else "geometric",
                         n_extra=fz[:, K:].sum(-1), effects=effects, test_errors=test_errors,
                         prior=_prior_info(model, fit, template) if prior else None)


def _effects(model, fit: _Fit, fz, se, free, names_z, units_z, names_p, units_p) -> dict:
    """The effects' parameters per robot (None where not fitted) and the payload the fleet shares."""
    K, pay = model.K, fit.s[model.np:]
    vals = [[v if ok else None for v, ok in zip(row, fr)] for row, fr in zip(fit.Z[:, K:].tolist(), fz[:, K:].tolist())]
    return {"names": names_z[K:], "units": units_z[K:], "values": vals, "free": fz[:, K:].tolist(),
            "std_errors": se[:, K:].tolist(),
            "shared": {n: float(v) for n, v, ok in zip(names_p, pay.tolist(), free[model.kz:].tolist()) if ok},
            "shared_units": dict(zip(names_p, units_p)), "payload": "per_robot" if model.own_mu else "shared"}


def _held_out(model, fit: _Fit):
    """``FleetData -> (R, N', M, 3)`` held-out error vectors (m) of the model with its effects."""
    Z, pay, K = fit.Z, fit.s[model.np:], model.K

    def test_errors(fd_test):
        qe, _ = model.joints(Z, pay, model.torque_features(fd_test), fd_test.q)
        idx = torch.arange(Z.shape[0], device=Z.device)
        return fd_test.positions(model.robot, Z[:, :K], idx, q=qe) - fd_test.measured
    return test_errors


def _prior_info(model, fit: _Fit, template) -> dict:
    """The hierarchical prior as fitted: its parameters, fleet mean, scales and noise."""
    P = model.P
    return {"parameters": [template.names[i] for i in P.tolist()], "mean": fit.s[: model.np].tolist(),
            "tau": fit.tau.tolist(), "units": [template.units[i] for i in P.tolist()], "sigma_m": fit.sigma,
            "n_outer": fit.rounds, "scales_estimated": fit.estimated}
