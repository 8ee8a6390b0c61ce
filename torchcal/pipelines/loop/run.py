"""The loop with measured data: calibrate, read the residual, trace it to the physical effect the
model lacks, add it, and report held-out error before and after.

Every decision (which geometric parameters and prior, which effect and which of its modes,
whether the residual ELM helps) is made on the training rows alone, by K-fold cross-validation
under the rule of :mod:`torchcal.pipelines.crossval.scores`. The held-out ``test`` rows never steer anything:
they are only measured.

Stages:

1. *nominal*: the instrument frame registered, nothing else;
2. *noise*: a robust estimate ``σ̂`` of the per-axis noise, which sets the Huber threshold of
   every fit and score (outliers then neither steer the fit nor decide the comparisons);
3. *geometry*: nested parameter sets (base + markers, + joint offsets, + all joint origins); when
   the data cannot support the full set, Gaussian priors on every geometric error with a scale
   in mm and mrad (MAP) chosen by the same rule, counted by their effective number of parameters;
4. *diagnosis*: each candidate effect starts from a linear step around the current model (a
   family's modes chosen one by one), is fitted and cross-validated; the best that passes is
   added, and the diagnosis repeats;
5. *residual ELM*: kept only when it passes the rule;
6. suspect rows (observations beyond ``OUTLIER_K σ̂``) are listed, never dropped.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from torchcal.effects import EFFECTS
from torchcal.measure.checks import check_enough, check_fit_inputs
from torchcal.measure.data import Measurements
from torchcal.measure.observations import Observations
from torchcal.measure.placeholders import constant_orientations, without_constant_orientations
from torchcal.measure.registration import gross_errors
from torchcal.measure.setup import Setup, check_heldout, needs_setup
from torchcal.measure.stats import noise_floor
from torchcal.measure.trust import stage_problems
from torchcal.options import Options
from torchcal.pipelines.precision import check_plausible
from torchcal.pipelines.loop.covariates import derive_code_levels, derive_directions, derive_row_order, fold_groups
from torchcal.pipelines.loop.diagnosis import Diagnosis, diagnose
from torchcal.pipelines.loop.elm_stage import elm_stage
from torchcal.pipelines.loop.findings import state_findings
from torchcal.pipelines.crossval.models import Context, duplicate_groups, folds_of, noise_sigma
from torchcal.pipelines.crossval.evaluate import cv_mean_mm
from torchcal.problems.template import geometric_start
from torchcal.pipelines.loop.geometry import (GEOMETRIC_SETS, GeometryChoice, choose_geometry,
                                              choose_orientation_weight, estimate_noise)
from torchcal.pipelines.loop.leftover import leftover
from torchcal.pipelines.loop.result import LoopResult
from torchcal.pipelines.loop.sessions import check_heldout_rows, hold_session_terms, other_session
from torchcal.pipelines.loop.stages import StageBook, elm_covariates, residual_matrix
from torchcal.pipelines.loop.steps import parameter_table
from torchcal.pipelines.loop.suspects import suspect_rows
from torchcal.threads import threads_by_size

__all__ = ["run_loop", "LoopOptions"]

logger = logging.getLogger("torchcal.loop")


@dataclass(frozen=True)
class LoopOptions(Options):
    """The settings of :func:`run_loop`.

    Attributes:
        candidates: effect names to consider (default: every effect in
            :data:`torchcal.effects.EFFECTS` that the data allows); checked before any fitting.
        folds: K of the K-fold cross-validation (≥ 2); rows with identical commands share a fold.
        seed: seed of the fold assignment and the ELM.
        elm: try the residual ELM stage; ``elm_hidden``: its hidden units (default N/4, 8–64).
        noise_mm: instrument noise (mean Euclidean error a perfect model would leave, mm) for the
            report; used when no command was measured twice (whose pure error comes first), else
            the median of a ``marker_std_mm`` covariate when the data has one
            (:mod:`~torchcal.pipelines.loop.leftover`).
        orientation_weight: m/rad: how a measured orientation error counts against a position error
            (``σ_position / σ_rotation`` of the instruments). Default: estimated from the residuals
            when the rows measure orientations (``<marker>.qw…``); 0: orientations ignored.
        soft: a linear family may be kept whole under a Gaussian prior whose scale CV chooses,
            when that beats choosing its modes one by one (False: modes one by one only).
        plausible: the largest plausible joint error per unit (default
            :data:`~torchcal.pipelines.precision.PLAUSIBLE`, 10 mm and 10 mrad): a geometric set moving
            a joint further is not chosen, and a final model doing so is refused (:meth:`LoopResult.problems`).
        progress: a progress bar over the diagnosis candidates (tqdm).
        log: a print-like function for progress lines (``None`` to stay quiet); lines also go
            to the ``torchcal.loop`` logger.
        reregister: register the instrument frame anew on the held-out rows (a tracker set up
            anew for another session) and report that figure beside the first; held-out rows this
            explains are not refused (:mod:`~torchcal.pipelines.loop.sessions`).
    """
    candidates: list[str] | None = None
    folds: int = 5
    seed: int = 0
    elm: bool = True
    elm_hidden: int | None = None
    noise_mm: float | None = None
    orientation_weight: float | None = None
    soft: bool = True
    plausible: dict | None = None
    progress: bool = False
    log: object = print
    reregister: bool = False


def say_fn(log):
    def out(msg: str) -> None:
        logger.info(msg)
        if log is not None:
            log(msg)
    return out


@threads_by_size("train", "test")
def run_loop(robot, train: Measurements, test: Measurements | None = None, settings: LoopOptions | None = None,
             **kw) -> LoopResult:
    """Registration → noise estimate → geometry (sets and priors chosen by CV) → diagnosis and
    effects → residual ELM (kept only when it helps in CV) → report.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot` (markers declared).
        train: training rows (:class:`~torchcal.measure.io.Measurements`, m and rad); every decision is
            made on them.
        test: held-out rows, only measured (optional).
        settings: a :class:`LoopOptions`; ``kw``: any of its fields, which override it
            (``run_loop(robot, train, folds=10)``).

    Returns:
        A :class:`LoopResult`.
    """
    opt = LoopOptions.build(settings, **kw)
    names = _check(robot, train, test, opt)
    t0 = time.perf_counter()
    say = say_fn(opt.log)
    train, test = _placeholders(train, test, say)
    train, test = _derived_columns(train, test, say)
    as_measured = test
    session, test, held = _session(train, test)
    timings: dict[str, float] = {}

    # 1. nominal: base registration only; the planes and fixed points located from it
    ctx, book, geo0, orientation = _nominal(robot, train, test, opt, say)
    timings["nominal"] = time.perf_counter() - t0

    # 2. noise, then 3. geometry: nested sets, each from the one before, then the full set under priors
    t1 = time.perf_counter()
    ctx, geo = _geometry(ctx, geo0, say)
    timings["geometric"] = time.perf_counter() - t1

    # 4. diagnosis
    t2 = time.perf_counter()
    d = diagnose(ctx, geo.best, names, test, say, opt.progress, as_measured=as_measured)
    ctx, current = d.ctx, d.current
    timings["diagnosis"] = time.perf_counter() - t2
    geo_model = geo.best if d.steps else current
    book.add("geometric", geo_model.k, geo_model.params, [], cv=geo.best.cv_rmse_mm(ctx.n_obs),
             prior_mm=geo.best.prior_mm, k_eff=geo_model.k)
    accepted, evidence, removed = state_findings(book, d.steps, current, train, ctx.n_obs, d.moves)

    # 5. residual ELM
    t3 = time.perf_counter()
    elm_model, elm_line = elm_stage(ctx, current, book, opt.elm_hidden, opt.seed, say) if opt.elm else (None, None)
    if elm_line is not None:
        d.candidates.append(elm_line)
    timings["residual_elm"] = time.perf_counter() - t3

    # 6. suspects: listed, never dropped; the held-out rows: another session, a moved instrument?
    sigma = noise_sigma(ctx, current)
    suspects = suspect_rows(ctx, current, sigma, say)
    heldout = None if book.test is None else check_heldout_rows(
        ctx, current.params, current.effects, elm_model, book.test, geo_model.params, session=session, held_at=held,
        reregister=opt.reregister)
    for line in [] if heldout is None else heldout.words():
        say(line)
    timings["total"] = time.perf_counter() - t0
    res = _result(ctx, d, geo, book, opt, say, elm=elm_model, accepted=accepted, evidence=evidence,
                  removed=removed, suspects=suspects, sigma=sigma, timings=timings, orientation=orientation)
    res.heldout = heldout
    return res


def _check(robot, train: Measurements, test: Measurements | None, opt: LoopOptions) -> list[str]:
    """The door: the inputs, the candidate names and the folds; the candidates to try."""
    check_fit_inputs(robot, train, test, enough=False)
    names = list(EFFECTS) if opt.candidates is None else list(opt.candidates)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {sorted(EFFECTS)}")
    if opt.folds < 2:
        raise ValueError(f"folds must be at least 2, got {opt.folds}")
    return names


def _placeholders(train: Measurements, test: Measurements | None, say):
    """The rows without an orientation that never changes (the instrument's placeholder)."""
    const = constant_orientations(train)
    if not const:
        return train, test
    say(f"the orientation of {', '.join(const)} is the same in every row: the instrument's placeholder (a "
        "position-only tracker), not a measurement; left out")
    return (without_constant_orientations(train, const),
            None if test is None else without_constant_orientations(test, const))


def _session(train: Measurements, test: Measurements | None):
    """Why the held-out rows come from another session (None: the training one); the held-out rows
    with the session drivers (time, row order) held at the training rows' median then, and those values."""
    session = None if test is None else other_session(train, test)
    if session is None:
        return None, test, {}
    return (session, *hold_session_terms(train, test))


def _own(data: Measurements | None) -> Measurements | None:
    """``data`` with a covariate table of its own: the columns the loop derives (directions, row
    order) are added to the run's copy, never to the caller's rows (a second run on the same rows
    would otherwise find them there and derive nothing for its held-out rows)."""
    return None if data is None else data._with(data.q, data.positions, list(data.marker_names), data.quaternions,
                                                dict(data.covariates), data.planes, dict(data.distances))


def _derived_columns(train: Measurements, test: Measurements | None, say) -> tuple[Measurements, Measurements | None]:
    """The run's copies of the rows with the columns the loop derives: directions of approach, the
    row order, the levels of a column of codes."""
    train, test = _own(train), _own(test)
    derived = derive_directions(train)
    if derived is not None:
        if test is not None:
            derive_directions(test)
        say(f"no direction columns: derived dir.<joint> from the time order of '{derived}' (for backlash)")
    if derive_row_order(train, test):
        say("no time column: the row order is a driver ('row'), for what changed during the session")
    codes = derive_code_levels(train, test)
    if codes:
        say(f"few whole numbers in {', '.join(codes)}: read as levels too (codes: a tool, a station by number)")
    return train, test


def _nominal(robot, train: Measurements, test: Measurements | None, opt: LoopOptions, say):
    """The run's context (folds, set-up, orientation weight), its stage book, the nominal model
    (base registration only), whose stage opens the book, and how the orientation weight was chosen."""
    fl = folds_of(len(train), min(opt.folds, len(train)), opt.seed, fold_groups(train, duplicate_groups(train)))
    if test is not None:
        check_heldout(train, test)
    setup = Setup.from_data(robot, train, geometric_start(robot, train, None).values) if needs_setup(train) else None
    if test is not None:
        Observations(robot, test, setup)  # the held-out rows fit this robot and set-up, before any fitting
    check_enough(robot, train)
    if setup is not None:
        say(f"set-up unknowns identified with the robot: planes {setup.planes}, fixed points {setup.pivots}"
            + ("" if int(train.seen.sum()) >= 3 else "; no position measured, so the instrument frame is the "
               "robot base"))
    ctx = Context(robot, train, fl, None, 1.0, setup, soft=opt.soft, plausible=check_plausible(opt.plausible))
    rot_w, orientation = choose_orientation_weight(ctx, robot, train, setup, opt.orientation_weight, say)
    ctx.rot_weight = rot_w
    geo0 = geometric_start(robot, train, GEOMETRIC_SETS[0][1], setup, rot_w is not None)
    book = StageBook(robot, train, test, setup, rot_w)
    book.add("nominal", 0, geo0, [])
    return ctx, book, geo0, orientation


def _geometry(ctx: Context, geo0, say) -> tuple[Context, GeometryChoice]:
    """The noise estimate (the largest identifiable set, refitted under Huber until the scale
    settles), then the geometric model chosen among nested sets and priors."""
    robot, train = ctx.robot, ctx.data
    # the first, plain fits leave gross errors out (a glitch metres off would drag σ̂, and every
    # parameter would look loose); the Huber fits after them keep every row
    clean = train.hide(gross_errors(robot, train, geo0.values[: robot.n_params]))
    ctx, probe, found = estimate_noise(ctx, robot, train, ctx.setup, clean=clean)
    say(f"noise estimate σ̂ = {1e3 * ctx.sigma:.4f} mm per axis; Huber threshold {1e3 * ctx.c:.4f} mm")
    return ctx, choose_geometry(ctx, robot, train, ctx.setup, probe, found, say)


def _result(ctx: Context, d: Diagnosis, geo: GeometryChoice, book: StageBook, opt: LoopOptions, say, *, elm, accepted,
            evidence, removed, suspects, sigma, timings, orientation) -> LoopResult:
    """What is left against the noise floor, the warnings, and the result."""
    train, current = ctx.data, d.current
    noise_mm, noise_source = noise_floor(train, opt.noise_mm)
    left = leftover(train, residual_matrix(ctx.robot, current.params, current.effects, train, ctx.setup),
                    cv_mean_mm(ctx, current), noise_mm, noise_source)
    for line in left.words() + [f"the residual still follows {a.words()}" for a in left.associations[:3]
                                if left.missing]:
        say(line)
    for p in stage_problems(book.stages):
        say("warning: " + p)
    parameters, observability = parameter_table(ctx, current)
    best = geo.best
    return LoopResult(robot=ctx.robot, params=current.params, effects=current.effects, elm=elm, stages=book.stages,
                      accepted=accepted, candidates=d.candidates,
                      geometric={"chosen": best.label, "sets": geo.sets, "prior_mm": best.prior_mm,
                                 "orientation": orientation, "again": d.geometry_again},
                      n_train=len(train), n_test=0 if book.test is None else len(book.test), noise_floor_mm=noise_mm,
                      noise_floor_source=noise_source, timings=timings, errors=book.errors, evidence=evidence,
                      elm_covariates=elm_covariates(train), geometric_fits=geo.fits, noise_sigma_mm=1e3 * sigma,
                      huber_mm=1e3 * ctx.c, suspects=suspects, flags=d.flags, prior_mm=best.prior_mm,
                      parameters=parameters, observability=observability, setup=ctx.setup, leftover=left,
                      removed=removed, plausible=ctx.plausible, breaks_placed=d.breaks)
