"""Geometric calibration end to end: base registration, identifiability reduction, the fit,
standard errors, and error statistics on training and held-out data."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from torchcal.kinematics.transforms import matrix_to_quat, so3_exp
from torchcal.measure.blocks import Loss, PoseResidual, PositionResidual
from torchcal.measure.checks import check_enough, check_fit_inputs
from torchcal.measure.data import Measurements
from torchcal.measure.registration import leave_out_gross, register_base, register_marker_rotations
from torchcal.measure.stats import errors_by_marker
from torchcal.optim import Result, get_solver, is_population
from torchcal.optim.hybrid import Hybrid
from torchcal.outputs import staged_dir
from torchcal.params import ParamSet
from torchcal.pipelines.calibrate_prior import choose_prior
from torchcal.pipelines.fitting import (PLAUSIBLE, check_plausible, fit_identified, implausible_reason,
                                        implausible_values, is_small, reduce_free)
from torchcal.problems.calibration import CalibrationProblem
from torchcal.problems.uncertainty import standard_errors
from torchcal.report.calibration import (calibration_markdown, error_details, stage_problems,
                                         write_calibration_report, write_json)
from torchcal.threads import threads_by_size

__all__ = ["calibrate", "CalibrationResult", "stage_stats"]

_SEARCH = {"m": 5e-3, "rad": 0.05}  # default swarm search box around the start (± per unit)


def stage_stats(robot, params: Tensor, data: Measurements | None) -> dict | None:
    """Position-error statistics (mm) of ``params`` on ``data``, overall and per marker."""
    if data is None or len(data) == 0:
        return None
    blk = PositionResidual(robot, data)
    return errors_by_marker(blk.errors(params[None])[0], blk.obs_index[:, 1], data.marker_names)


def _position_errors(robot, params: Tensor, data: Measurements | None) -> Tensor:
    if data is None or len(data) == 0:
        return torch.zeros(0)
    return PositionResidual(robot, data).errors(params[None])[0]


def _errors(robot, params: Tensor, train: Measurements, test: Measurements | None) -> dict:
    out = {}
    for split, d in (("train", train), ("test", test)):
        det = error_details(robot, params, d) if d is not None and len(d) else None
        out[split] = _position_errors(robot, params, d)
        if det is not None:
            out[f"{split}_details"] = det
    return out


def write_instrument(robot, params: ParamSet, path) -> None:
    """The instrument registration (instrument frame <- robot base) as JSON: translation in
    metres and rotation as a unit quaternion (w, x, y, z)."""
    b = params.values[:6]
    R = so3_exp(b[3:])
    write_json(path, {"frame": "instrument <- robot base: p_instrument = R p_base + t",
                      "translation_m": b[:3].tolist(), "quaternion_wxyz": matrix_to_quat(R).tolist(),
                      "rotation_vector_rad": b[3:].tolist(),
                      "note": "the calibrated URDF is in the robot's own base frame; this is where the instrument "
                              "saw it"})


@dataclass
class CalibrationResult:
    """What :func:`calibrate` found.

    Attributes:
        params: identified values (full ParamSet; its free flags mark what was fitted).
        std_errors: standard error of every fitted parameter (m or rad), from
            ``σ² (JᵀJ)⁻¹`` with ``σ² = SSR / (m − k)``.
        unidentifiable: parameters that were free but could not be identified, with reasons.
        stages: ``[{"name", "n_params", "train", "test"}]``: "nominal" (base registration only)
            and "geometric".
        solver: the optimiser's :class:`~torchcal.optim.Result`.
    """

    robot: object
    params: ParamSet
    std_errors: dict[str, float]
    unidentifiable: dict[str, str]
    stages: list[dict]
    solver: Result
    method: str
    n_train: int
    n_test: int
    start: ParamSet
    identifiability: object = None
    loss: str = "l2"
    wall_time_s: float = 0.0
    errors: dict = field(default_factory=dict)  # stage -> {"train": Tensor, "test": Tensor} (m)
    prior_mm: float | None = None  # Gaussian prior on the geometric errors (mm and mrad), None: none
    prior_reason: str = ""         # why that prior (or none), in words
    prior_tried: list = field(default_factory=list)
    implausible: dict = field(default_factory=dict)  # joint errors beyond their plausible size: name -> value
    plausible: dict = field(default_factory=dict)
    held_by_prior: dict = field(default_factory=dict)  # fitted, but tied: the prior's share, and why
    suspects: list = field(default_factory=list)  # gross errors left out of the fit: {"row", "marker", "error_mm"}

    def __repr__(self) -> str:
        last = self.stages[-1]
        te = f", held-out mean {last['test']['mean_mm']:.4f} mm" if last.get("test") else ""
        return (f"CalibrationResult({self.robot.name}, {self.method}: {len(self.std_errors)} parameters fitted, "
                f"{len(self.unidentifiable)} not identifiable; training mean {last['train']['mean_mm']:.4f} mm{te})")

    def problems(self) -> list[str]:
        """Reasons not to trust this calibration, in words (empty when none): worse than the
        nominal model on its own training rows, held-out rows that do not fit this robot, or joints
        moved or turned by more than a plausible error."""
        out = stage_problems(self.stages)
        if self.implausible:
            out.append(implausible_reason(self.implausible, dict(zip(self.params.names, self.params.units)),
                                          self.plausible or PLAUSIBLE))
        return out

    def statuses(self) -> dict[str, tuple[str, str]]:
        """Every candidate parameter's one status: ``"identified"``, ``"tied"`` (the data cannot
        tell it from others) or ``"fixed"`` (not seen, or pinned down worse than a plausible
        error), with the reason for the latter two."""
        imp = set(getattr(self.identifiability, "imprecise", []) or [])
        out = {n: ("identified", "") for n in self.params.free_names if n not in self.held_by_prior}
        out.update({n: ("tied", why) for n, why in self.held_by_prior.items()})
        for n, why in self.unidentifiable.items():
            fixed = n in imp or "does not move" in why or "not fitted" in why
            out[n] = ("fixed" if fixed else "tied", why)
        return out

    def report(self) -> dict:
        """The JSON-serialisable report (shape shared with ``torchcal loop``)."""
        ident = self.params.free_names
        return {
            "robot": self.robot.name, "method": self.method, "loss": self.loss,
            "n_train": self.n_train, "n_test": self.n_test,
            "stages": self.stages,
            "unidentifiable": sorted(self.unidentifiable),
            "unidentifiable_reasons": self.unidentifiable,
            "parameters": {n: {"value": v, "std_error": self.std_errors.get(n),
                               "unit": u} for n, v, u in zip(self.params.names, self.params.values.tolist(),
                                                            self.params.units) if n in ident},
            "solver": {"method": self.solver.method, "fun": self.solver.fun, "n_iter": self.solver.n_iter,
                       "n_evals": self.solver.n_evals, "wall_time_s": self.solver.wall_time_s,
                       "converged": self.solver.converged, "message": self.solver.message},
            "wall_time_s": self.wall_time_s, "problems": self.problems(), "suspects": self.suspects,
            "prior_mm": self.prior_mm, "prior_reason": self.prior_reason, "prior_tried": self.prior_tried,
            "status": {n: st for n, (st, _) in self.statuses().items()},
        }

    def markdown(self) -> str:
        """``report.md`` (:func:`~torchcal.report.calibration.calibration_markdown`)."""
        return calibration_markdown(self)

    def save(self, out_dir, *, force: bool = False, with_instrument: bool = False, extra=None) -> Path:
        """Write ``calibrated.urdf`` (in the robot's own base frame; ``with_instrument``: the
        instrument frame as its root) and ``calibration.yaml``, ``instrument.json``, ``params.json``,
        ``report.json``, ``report.md``, ``report.html`` and the error figures into ``out_dir``, built
        under a temporary name.
        Refused when ``out_dir`` holds anything (unless ``force``) and when :meth:`problems`
        says the result cannot be trusted. ``extra(tmp_dir)`` may add files before the rename."""
        if self.problems():
            raise ValueError("not saved, this calibration is not fit to use: " + "; ".join(self.problems()))
        with staged_dir(out_dir, force) as out:
            self.robot.export_calibration(self.params, out, with_instrument=with_instrument)
            write_instrument(self.robot, self.params, out / "instrument.json")
            write_json(out / "params.json", {"names": self.params.names, "units": self.params.units,
                                             "values": self.params.values.tolist(),
                                             "free": self.params.free.tolist(),
                                             "std_errors": self.std_errors})
            write_json(out / "report.json", self.report())
            write_calibration_report(self, out)
            if extra is not None:
                extra(out)
        return Path(out_dir)


def _select_free(params: ParamSet, free) -> ParamSet:
    params = params.clone()
    if free is None:
        return params
    if isinstance(free, str):
        free = [free]
    return params.only(*free)


def _search_box(params: ParamSet, radius: dict) -> ParamSet:
    p = params.clone()
    r = torch.tensor([radius.get(u, 0.05) for u in p.units], dtype=p.values.dtype, device=p.values.device)
    p.lower = torch.maximum(p.lower, p.values - r)
    p.upper = torch.minimum(p.upper, p.values + r)
    return p


@threads_by_size("data", "test")
def calibrate(robot, data: Measurements, *, test: Measurements | None = None, method: str = "lm",
              params: ParamSet | None = None, free=None, kind: str = "position", rot_weight: float = 0.1,
              loss: str = "l2", loss_scale: float | None = None, register: bool = True,
              reduce: bool = True, prefer=None, fitness: str = "sse", search_radius: dict | None = None,
              options: dict | None = None, seed: int = 0, progress: bool = False,
              polish: bool | None = None, plausible: dict | None = None,
              prior: str | float | None = "auto") -> CalibrationResult:
    """Identify geometric errors from measurements.

    Steps: (1) base registration by Kabsch (when the base parameters are free and ``register``);
    (2) identifiability: the free set is reduced to a base subset by column-pivoted QR of the
    Jacobian at the start, every dropped parameter reported with a reason; (3) the fit with
    ``method`` ("lm", "gn", "lbfgs", "adam", "pso", "ldpso-bt", "cpso", "ga", "ma", "mma",
    "hybrid"); (4) standard errors and error statistics on ``data`` and ``test``.

    Args:
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
            :data:`~torchcal.pipelines.fitting.PLAUSIBLE`: 10 mm, 10 mrad). With position data and
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
    t0 = time.perf_counter()
    check_fit_inputs(robot, data, test, enough=False)
    if kind not in ("position", "pose"):
        raise ValueError(f"kind must be 'position' or 'pose', got {kind!r}")
    if len(data) == 0:
        raise ValueError("no training rows")
    plausible = check_plausible(plausible)
    if not (prior is None or prior in ("auto", "cv")):
        raise ValueError(f"prior must be 'auto', 'cv' or None, got {prior!r}")
    for d, what in ((data, "training"), (test, "held-out")):
        if d is not None and (d.distances or (d.planes is not None and bool((d.planes >= 0).any()))):
            raise ValueError(f"the {what} rows hold plane contacts or distances, which calibrate() does not fit (it "
                             "fits positions, partial ones included): use torchcal.run_loop / 'torchcal loop', which "
                             "identifies the planes' poses and the fixed points with the robot")
    check_enough(robot, data)
    p = _select_free(params if params is not None else robot.params(), free)
    if not (set(data.marker_names) <= set(robot.marker_names)):
        raise ValueError(f"the data has markers {data.marker_names} but the robot has {robot.marker_names}")
    # markers the data never sees cannot be identified: fix their offsets
    for m in robot.marker_names:
        if m not in data.marker_names:
            p.fix(f"{m}.*")
    if kind == "position":
        for m in robot.marker_names:
            p.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
    base_free = bool(p.free[[p.index(n) for n in ("base.x", "base.y", "base.z", "base.rx", "base.ry", "base.rz")]].any())
    if register and base_free:
        p = register_base(robot, data, p)
    if kind == "pose" and free is None:
        # the measured frames' rotation on their links is as unknown as the points: free it,
        # started from the mean measured rotation
        p = register_marker_rotations(robot, data, p)
    start = p.clone()
    # a gross error (a glitch metres off) is left out of the fit and listed; the statistics keep it
    fit_data, suspects = leave_out_gross(robot, data, start)

    def p_cand(cur: ParamSet) -> ParamSet:
        nxt = start.clone()
        nxt.values = cur.values.clone()
        return nxt

    def blocks(loss_obj):
        if kind == "pose":
            return [PoseResidual(robot, fit_data, rot_weight=rot_weight, loss=loss_obj)]
        return [PositionResidual(robot, fit_data, loss=loss_obj)]

    nominal = start.values
    stages = [{"name": "nominal", "n_params": 0, "train": stage_stats(robot, nominal, data)}]
    if test is not None:
        stages[0]["test"] = stage_stats(robot, nominal, test)

    swarm = is_population(method)  # a population searches a box around the start
    loss_obj = None

    def make_problem(q: ParamSet, lo=None) -> CalibrationProblem:
        box = _search_box(q, search_radius or _SEARCH) if swarm else q
        return CalibrationProblem(robot, box, blocks(lo), fitness=fitness)

    opts = dict(options or {})
    if method.lower() in ("lm", "levenberg-marquardt"):
        # the registered start is close to the solution: little initial damping, fewer Jacobians
        opts.setdefault("tau", 1e-6)

    def solve(prob):
        s = get_solver(method, seed=seed, progress=progress, **opts).minimize(prob)
        if polish and swarm and not isinstance(get_solver(method), Hybrid):  # a hybrid polishes itself
            prob.x0 = s.x.clone()
            s2 = get_solver("lm").minimize(prob)
            s2.history, s2.method = s.history + s2.history, f"{s.method}+lm"
            s = s2
        return s

    # a parameter the data pin down worse than its plausible size is fixed (fit_identified), judged
    # at the noise the fit's own position residuals show; a swarm's search box bounds it already
    noise = "residuals" if kind == "position" and not swarm else None
    # robust losses: the scale is re-estimated from the residuals until it settles (IRLS-style);
    # the first estimate comes from a start millimetres off, so it shrinks over several rounds
    report = None
    scale_prev = None
    for rnd in range(1 if loss == "l2" or loss_scale is not None else 12):
        if loss != "l2":
            scale = float(loss_scale) if loss_scale is not None else max(
                2.5 * 1.4826 * float(PositionResidual(robot, fit_data).errors(p.values[None])[0].median()), 1e-9)
            if scale_prev is not None and abs(scale - scale_prev) <= 0.05 * scale_prev:
                break
            scale_prev = scale
            loss_obj = Loss(loss, scale)
        p, s, rep = fit_identified(lambda q: make_problem(q, loss_obj), p if rnd == 0 else p_cand(p),
                                   solve=solve, markers=robot.marker_names, kind=kind, prefer=prefer,
                                   reduce=reduce, noise=noise, plausible=plausible)
        report = rep or report
    unident = {n: report.reasons.get(n, "not identifiable") for n in report.dropped} if report else {}

    # standard errors on the fitted (identifiable) set
    prob = CalibrationProblem(robot, p, blocks(loss_obj), fitness="sse")
    x = p.values[p.free_index]
    J = prob.jacobian(x)
    r = prob.residuals(x[None])[0]
    se = standard_errors(J, r)
    std_errors = dict(zip(p.free_names, se.tolist()))

    # on small data (or when the plain fit moves a joint implausibly far) the loop's CV-chosen prior
    choice, why, held = None, "", {}
    gradient = not swarm and kind == "position" and reduce
    wanted = prior == "cv" or (prior == "auto" and (is_small(fit_data, len(start.free_names))
                                                   or implausible_values(p, robot, plausible)))
    if gradient and wanted:
        choice = choose_prior(robot, fit_data, start, p, None if loss_obj is None else loss_obj.scale, seed=seed,
                              plausible=plausible)
        why = choice.reason
        if choice.prior_mm is not None:
            p, std_errors = choice.params, {n: choice.std_errors.get(n, float("nan")) for n in choice.params.free_names}
            # what the data alone cannot tell apart, the prior holds: tied, fitted to the prior's share
            cand = start.clone()
            cand.values = p.values.clone()
            _, rank = reduce_free(lambda q: make_problem(q, loss_obj), cand, markers=robot.marker_names, kind=kind,
                                  prefer=prefer)
            held = {n: rank.reasons[n] + "; held by the prior at its share of the tie" for n in rank.dropped
                    if n in p.free_names}
            unident = {n: rank.reasons[n] for n in rank.dropped if n not in p.free_names}
    elif prior is not None and gradient:
        why = (f"no prior: {data.n_values} measured values for {len(start.free_names)} candidate parameters are "
               "enough to fit the identifiable ones alone")
    elif prior is not None:
        why = (f"no prior: method {method!r} keeps its search box" if swarm else
               "no prior: pose data are fitted without one")

    geo = {"name": "geometric", "n_params": int(p.free.sum()), "train": stage_stats(robot, p.values, data)}
    if test is not None:
        geo["test"] = stage_stats(robot, p.values, test)
    stages.append(geo)
    errors = {"nominal": _errors(robot, nominal, data, test), "geometric": _errors(robot, p.values, data, test)}
    if choice is None or choice.prior_mm is None:
        unident = {n: why_ for n, why_ in unident.items() if n not in p.free_names}  # one status per parameter
    return CalibrationResult(robot=robot, params=p, std_errors=std_errors, unidentifiable=unident, stages=stages,
                             solver=s, method=method, n_train=len(data), n_test=0 if test is None else len(test),
                             start=start, identifiability=report, loss=loss if loss_obj is None else repr(loss_obj),
                             wall_time_s=time.perf_counter() - t0, errors=errors, suspects=suspects,
                             prior_mm=None if choice is None else choice.prior_mm, prior_reason=why,
                             prior_tried=[] if choice is None else choice.tried,
                             implausible=implausible_values(p, robot, plausible), plausible=plausible,
                             held_by_prior=held)
