"""Geometric calibration end to end: base registration, identifiability reduction, the fit,
standard errors, and error statistics on training and held-out data."""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.measure.checks import check_enough, check_fit_inputs
from torchcal.measure.data import Measurements
from torchcal.measure.details import error_details
from torchcal.measure.loss import Loss
from torchcal.measure.noise import mad_sigma
from torchcal.measure.observations import Observations
from torchcal.measure.records import ErrorStats, Stage, StageErrors
from torchcal.measure.registration import leave_out_gross, register_base, register_marker_rotations
from torchcal.measure.stats import errors_by_marker
from torchcal.optim import Result, get_solver, is_population
from torchcal.optim.hybrid import Hybrid
from torchcal.optim.lm import LevenbergMarquardt
from torchcal.options import Options
from torchcal.params import ParamSet
from torchcal.pipelines.calibrate_prior import PriorChoice, choose_prior
from torchcal.pipelines.calibration_result import CalibrationResult
from torchcal.pipelines.fitting import fit_identified, is_small, nothing_left, reduce_free
from torchcal.pipelines.precision import check_plausible, implausible_values
from torchcal.problems.calibration import CalibrationProblem
from torchcal.problems.template import candidate_template
from torchcal.problems.uncertainty import standard_errors
from torchcal.threads import threads_by_size

__all__ = ["calibrate", "CalibrateOptions", "position_stats"]

_SEARCH = {"m": 5e-3, "rad": 0.05}  # default swarm search box around the start (± per unit)
_BASE = ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")


@dataclass(frozen=True)
class CalibrateOptions(Options):
    """The settings of :func:`calibrate`.

    Attributes:
        method: the solver: "lm", "gn", "lbfgs", "adam", "pso", "ldpso-bt", "cpso", "ga", "ma",
            "mma", "hybrid" (any name :func:`torchcal.optim.available` lists).
        params: the start (default: the robot's nominal parameters with its free flags).
        options: the solver's own settings (``{"max_iter": 200}``).
        seed, progress: the solver's seed and progress bar.
        register: register the base by Kabsch first (when the base parameters are free); for a
            population method, also fit the base and the marker points by LM before the search.
        reduce: reduce the free set to an identifiable subset (column-pivoted QR of the Jacobian).
        prefer: parameter names kept first when the reduction must choose among tied ones.
        rot_weight: m/rad: how an orientation error counts against a position error (``kind="pose"``).
        fitness: what a swarm minimises, "sse" (the default) or another fitness of the problem.
        free: glob patterns of parameters to identify (default: the ParamSet's free flags:
            base, joint origins/DH errors, offsets, marker positions).
        kind: "position" or "pose" (needs orientation columns).
        loss: "l2", "huber" or "cauchy"; ``loss_scale`` (m) defaults to 2.5 × a robust σ of the
            residuals, re-estimated over three rounds (iteratively reweighted fits).
        search_radius: swarm search box half-widths around the start, per unit
            (default ``{"m": 5e-3, "rad": 0.05}``), intersected with the ParamSet bounds.
        polish: run LM after a swarm method (default: no, so swarm results are reported as
            they are).
        plausible: the largest plausible error per unit (default
            :data:`~torchcal.pipelines.precision.PLAUSIBLE`: 10 mm, 10 mrad). With position data and
            a gradient method, a parameter whose standard error (at the noise the fit's residuals
            show) exceeds it is fixed at its start and the fit repeated; ``{}`` keeps every
            parameter of full rank. A joint moved or turned by more than it in the final model
            makes the result one :meth:`CalibrationResult.problems` refuses to save or deploy.
        prior: a Gaussian prior on every geometric error (gradient methods, position data):
            ``"auto"`` chooses its scale by cross-validation, against no prior, on small data
            (:func:`~torchcal.pipelines.calibrate_prior.is_small`) and when the plain fit leaves a
            joint error beyond its plausible size; ``"cv"`` always chooses it so; None: no prior
            (the identifiable subset alone, as a fleet without a prior fits each robot).
    """
    method: str = "lm"
    params: ParamSet | None = None
    free: str | list[str] | None = None
    kind: str = "position"
    rot_weight: float = 0.1
    loss: str = "l2"
    loss_scale: float | None = None
    register: bool = True
    reduce: bool = True
    prefer: list[str] | None = None
    fitness: str = "sse"
    search_radius: dict | None = None
    options: dict | None = None
    seed: int = 0
    progress: bool = False
    polish: bool | None = None
    plausible: dict | None = None
    prior: str | None = "auto"


def position_stats(robot, params: Tensor, data: Measurements | None) -> ErrorStats | None:
    """Position-error statistics (mm) of ``params (K,)`` on ``data``, overall and per marker."""
    if data is None or len(data) == 0:
        return None
    e, obs = _position_errors(robot, params, data)
    return errors_by_marker(e, obs.data_marker, data.marker_names)


def _position_errors(robot, params: Tensor, data: Measurements) -> tuple[Tensor, Observations]:
    """``(n,)`` Euclidean error (m) of every observed marker position (its measured axes) at
    ``params (K,)``, and the observations they belong to."""
    obs = Observations(robot, data)
    return obs.residuals(robot.positions(data.q, params[None], check=False))[0].norm(dim=-1), obs


def stage(name: str, n_params: int, robot, params: Tensor, train: Measurements,
          test: Measurements | None) -> tuple[Stage, StageErrors]:
    """The :class:`Stage` of ``params (K,)`` on the training and held-out rows, and its errors."""
    st = Stage(name, n_params, position_stats(robot, params, train),
               None if test is None else position_stats(robot, params, test))
    details = [error_details(robot, params, d) if d is not None and len(d) else None for d in (train, test)]
    return st, StageErrors(*details)


@threads_by_size("data", "test")
def calibrate(robot, data: Measurements, *, test: Measurements | None = None,
              settings: CalibrateOptions | None = None, **kw) -> CalibrationResult:
    """Identify geometric errors from measurements.

    Steps: (1) base registration by Kabsch (when the base parameters are free and ``register``);
    (2) identifiability: the free set is reduced to a base subset by column-pivoted QR of the
    Jacobian at the start, every dropped parameter reported with a reason; (3) the fit with
    ``method``; (4) on small data, the CV-chosen prior against none; (5) standard errors and
    error statistics on ``data`` and ``test``.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot` (markers declared).
        data: training rows (m and rad); test: held-out rows, only measured.
        settings: a :class:`CalibrateOptions`; ``kw``: any of its fields, which override it
            (``calibrate(robot, data, method="pso")``).
    """
    t0 = time.perf_counter()
    opt = CalibrateOptions.build(settings, **kw)
    plausible = _check(robot, data, test, opt)
    start = _start(robot, data, opt)
    # a gross error (a glitch metres off) is left out of the fit and listed; the statistics keep it
    fit_data, suspects = leave_out_gross(robot, data, start)
    swarm_start = is_population(opt.method) and opt.register
    fitter = _Fitter(robot, fit_data, _register_points(robot, fit_data, start) if swarm_start else start, opt, plausible)
    p, s, report, loss_obj = fitter.rounds()
    unident = {n: report.reasons.get(n, "not identifiable") for n in report.dropped} if report else {}
    std_errors = fitter.std_errors(p, loss_obj)
    short = fitter.short_of_optimum(p, loss_obj)
    choice, why = _prior(fitter, p, loss_obj, data)
    held = {}
    if choice is not None and choice.prior_mm is not None:
        p, std_errors = choice.params, {n: choice.std_errors.get(n, float("nan")) for n in choice.params.free_names}
        held, unident = fitter.held_by_prior(p, loss_obj)
    else:
        unident = {n: why_ for n, why_ in unident.items() if n not in p.free_names}  # one status per parameter
    (nom, e_nom), (geo, e_geo) = (stage("nominal", 0, robot, start.values, data, test),
                                  stage("geometric", int(p.free.sum()), robot, p.values, data, test))
    return CalibrationResult(robot=robot, params=p, std_errors=std_errors, unidentifiable=unident, stages=[nom, geo],
                             solver=s, method=opt.method, n_train=len(data), n_test=0 if test is None else len(test),
                             start=start, identifiability=report,
                             loss=opt.loss if loss_obj is None else repr(loss_obj),
                             wall_time_s=time.perf_counter() - t0, errors={"nominal": e_nom, "geometric": e_geo},
                             suspects=suspects, prior_mm=None if choice is None else choice.prior_mm,
                             prior_reason=why, prior_tried=[] if choice is None else choice.tried,
                             implausible=implausible_values(p, robot, plausible), plausible=plausible,
                             held_by_prior=held, not_converged=short)


def _check(robot, data: Measurements, test: Measurements | None, opt: CalibrateOptions) -> dict:
    """The door: inputs, settings and data calibrate can fit; the plausible sizes to judge by."""
    check_fit_inputs(robot, data, test, enough=False)
    if opt.kind not in ("position", "pose"):
        raise ValueError(f"kind must be 'position' or 'pose', got {opt.kind!r}")
    if len(data) == 0:
        raise ValueError("no training rows")
    plausible = check_plausible(opt.plausible)
    if not (opt.prior is None or opt.prior in ("auto", "cv")):
        raise ValueError(f"prior must be 'auto', 'cv' or None, got {opt.prior!r}")
    for d, what in ((data, "training"), (test, "held-out")):
        if d is not None and (d.distances or (d.planes is not None and bool((d.planes >= 0).any()))):
            raise ValueError(f"the {what} rows hold plane contacts or distances, which calibrate() does not fit (it "
                             "fits positions, partial ones included): use torchcal.run_loop / 'torchcal loop', which "
                             "identifies the planes' poses and the fixed points with the robot")
    check_enough(robot, data)
    if not (set(data.marker_names) <= set(robot.marker_names)):
        raise ValueError(f"the data has markers {data.marker_names} but the robot has {robot.marker_names}")
    return plausible


def _start(robot, data: Measurements, opt: CalibrateOptions) -> ParamSet:
    """The start: the candidate parameters (:func:`~torchcal.problems.template.candidate_template`),
    the base registered and, for poses, the measured frames' rotation freed."""
    p = candidate_template(robot, data.marker_names, opt.params, opt.free, opt.kind)
    if opt.register and bool(p.free[[p.index(n) for n in _BASE]].any()):
        p = register_base(robot, data, p)
    if opt.kind == "pose" and opt.free is None:
        # the measured frames' rotation on their links is as unknown as the points: free it,
        # started from the mean measured rotation
        p = register_marker_rotations(robot, data, p)
    return p


def _register_points(robot, data: Measurements, p: ParamSet) -> ParamSet:
    """A population method's start: the instrument frame and the marker points fitted by LM with
    every robot error held at its start. They say where the instrument and the reflector sit,
    not what is wrong with the robot, and a reflector centimetres from its guess lies outside
    any box a swarm can search well (:data:`_SEARCH`); the swarm then searches the robot's
    errors around them."""
    own = [n for n in p.free_names if n.startswith("base.") or n.split(".", 1)[0] in robot.marker_names]
    if not own:
        return p
    reg = p.clone()
    reg.free[:] = False
    reg.free[[reg.index(n) for n in own]] = True
    prob = CalibrationProblem(robot, reg, data)
    out = p.clone()
    out.values = prob.full(get_solver("lm").minimize(prob).x).detach()
    return out


def _prior(fitter: "_Fitter", p: ParamSet, loss_obj: Loss | None,
           data: Measurements) -> tuple[PriorChoice | None, str]:
    """On small data (or when the plain fit moves a joint implausibly far) the loop's CV-chosen
    prior against none; the choice (None: not tried) and why, in words."""
    opt, start = fitter.opt, fitter.start
    gradient = not fitter.swarm and opt.kind == "position" and opt.reduce
    wanted = opt.prior == "cv" or (opt.prior == "auto" and (is_small(fitter.data, len(start.free_names))
                                                            or implausible_values(p, fitter.robot, fitter.plausible)))
    if gradient and wanted:
        choice = choose_prior(fitter.robot, fitter.data, start, p, None if loss_obj is None else loss_obj.scale,
                              seed=opt.seed, plausible=fitter.plausible)
        return choice, choice.reason
    if opt.prior is None:
        return None, ""
    if gradient:
        return None, (f"no prior: {data.n_values} measured values for {len(start.free_names)} candidate parameters "
                      "are enough to fit the identifiable ones alone")
    return None, (f"no prior: method {opt.method!r} keeps its search box" if fitter.swarm else
                  "no prior: pose data are fitted without one")


class _Fitter:
    """The fit of one calibration: its problems (the data's observations, a swarm's search box), its
    solver, and the rounds of a robust loss whose scale follows the residuals."""

    def __init__(self, robot, data: Measurements, start: ParamSet, opt: CalibrateOptions, plausible: dict):
        self.robot, self.data, self.start, self.opt, self.plausible = robot, data, start, opt, plausible
        self.swarm = is_population(opt.method)  # a population searches a box around the start
        self.lm = isinstance(get_solver(opt.method), LevenbergMarquardt)  # takes fit_identified's checkpoint
        self.solver_options = dict(opt.options or {})

    def problem(self, q: ParamSet, loss: Loss | None) -> CalibrationProblem:
        """The fit's problem from ``q`` under ``loss`` (a swarm's: in its search box)."""
        box = _search_box(q, self.opt.search_radius or _SEARCH) if self.swarm else q
        return self.least_squares(box, loss, self.opt.fitness)

    def least_squares(self, q: ParamSet, loss: Loss | None, fitness: str = "sse") -> CalibrationProblem:
        """The data's observations (poses for ``kind="pose"``) against ``q`` under ``loss``."""
        return CalibrationProblem(self.robot, q, self.data, fitness=fitness, loss=loss,
                                  rot_weight=self.opt.rot_weight if self.opt.kind == "pose" else None)

    def solve(self, prob, **creep) -> Result:
        """``prob`` solved by the chosen method; ``creep``: :func:`fit_identified`'s precision checkpoint,
        which Levenberg-Marquardt takes (a fit creeping along a valley the data barely see is judged
        while it creeps, not after its whole step budget)."""
        o = self.opt
        s = get_solver(o.method, seed=o.seed, progress=o.progress, **self.solver_options,
                       **(creep if self.lm else {})).minimize(prob)
        if o.polish and self.swarm and not isinstance(get_solver(o.method), Hybrid):  # a hybrid polishes itself
            prob.x0 = s.x.clone()
            s2 = get_solver("lm").minimize(prob)
            s2.history, s2.method = s.history + s2.history, f"{s.method}+lm"
            s = s2
        return s

    def rounds(self) -> tuple[ParamSet, Result, object, Loss | None]:
        """The identifiable fit; with a robust loss, refitted while its scale (2.5 × a robust σ of
        the residuals, unless given) moves by more than 5 %: the first estimate comes from a start
        millimetres off, so it shrinks over several rounds."""
        o, p = self.opt, self.start
        # a parameter the data pin down worse than its plausible size is fixed (fit_identified), judged
        # at the noise the fit's own position residuals show; a swarm's search box bounds it already
        noise = "residuals" if o.kind == "position" and not self.swarm else None
        report, scale_prev, loss_obj, s = None, None, None, None
        for rnd in range(1 if o.loss == "l2" or o.loss_scale is not None else 12):
            if o.loss != "l2":
                scale = float(o.loss_scale) if o.loss_scale is not None else max(
                    2.5 * mad_sigma(_position_errors(self.robot, p.values, self.data)[0], center=0.0),
                    1e-9)
                if scale_prev is not None and abs(scale - scale_prev) <= 0.05 * scale_prev:
                    break
                scale_prev, loss_obj = scale, Loss(o.loss, scale)
            p, s, rep = fit_identified(lambda q, lo=loss_obj: self.problem(q, lo), p if rnd == 0 else self._at(p),
                                       solve=self.solve, markers=self.robot.marker_names, kind=o.kind,
                                       prefer=o.prefer, reduce=o.reduce, noise=noise, plausible=self.plausible)
            report = rep or report
            if rep is not None and rep.imprecise and all(n.startswith("base.") for n in p.free_names):
                # the instrument frame is never fixed for imprecision (it has no plausible size); a
                # calibration left with it alone has found nothing of the robot
                raise ValueError(nothing_left({n: rep.reasons[n] for n in rep.imprecise}))
        return p, s, report, loss_obj

    def _at(self, cur: ParamSet) -> ParamSet:
        """The start's free set at ``cur``'s values: every candidate judged again."""
        nxt = self.start.clone()
        nxt.values = cur.values.clone()
        return nxt

    def std_errors(self, p: ParamSet, loss: Loss | None) -> dict[str, float]:
        """Standard errors of the fitted (identifiable) set, σ from the residuals."""
        prob = self.least_squares(p, loss)
        x = p.values[p.free_index]
        se = standard_errors(prob.jacobian(x), prob.residuals(x[None])[0])
        return dict(zip(p.free_names, se.tolist()))

    def short_of_optimum(self, p: ParamSet, loss: Loss | None) -> str | None:
        """For a population method, why its best is not the least-squares optimum beside it, or
        None when it is. One Gauss-Newton step from the best is taken on the real residuals: when
        it lowers the sum of squares by more than σ̂² (the residual variance), the best lies more
        than one standard error, in the metric of the parameters' own covariance, from that
        optimum, and the search stopped short of it. LM polishes to the optimum (``polish``)."""
        if not self.swarm:
            return None
        prob = self.least_squares(p, loss)
        x = p.values[p.free_index]
        r, J = prob.residuals(x[None])[0], prob.jacobian(x)
        step = -(torch.linalg.pinv(J) @ r)
        sse, after = float(r.square().sum()), float(prob.residuals((x + step)[None])[0].square().sum())
        var = min(sse, after) / max(r.numel() - x.numel(), 1)
        if not sse - after > var:
            return None
        return (f"{self.opt.method} did not converge: its best lies {((sse - after) / var) ** 0.5:.3g} standard errors "
                f"from the least-squares optimum beside it (one Gauss-Newton step from it lowers the sum of squares by "
                f"{100 * (sse - after) / sse:.2g} %). That is the search's shortfall, not the data's: polish its best with LM ("
                + advice("polish=True", "--polish") + ") or use " + advice('method="lm"', "--method lm")
                + ", which reaches that optimum")

    def held_by_prior(self, p: ParamSet, loss: Loss | None) -> tuple[dict[str, str], dict[str, str]]:
        """What the data alone cannot tell apart, the prior holds: tied, fitted to the prior's
        share (``held``); the rest of the rank's dropped parameters stay unidentifiable."""
        _, rank = reduce_free(lambda q: self.problem(q, loss), self._at(p), markers=self.robot.marker_names,
                              kind=self.opt.kind, prefer=self.opt.prefer)
        held = {n: rank.reasons[n] + "; held by the prior at its share of the tie" for n in rank.dropped
                if n in p.free_names}
        return held, {n: rank.reasons[n] for n in rank.dropped if n not in p.free_names}


def _search_box(params: ParamSet, radius: dict) -> ParamSet:
    p = params.clone()
    r = torch.tensor([radius.get(u, 0.05) for u in p.units], dtype=p.values.dtype, device=p.values.device)
    p.lower = torch.maximum(p.lower, p.values - r)
    p.upper = torch.minimum(p.upper, p.values + r)
    return p
