"""The loop with measured data: calibrate, read the residual, trace it to the physical effect the
model lacks, add it, and report held-out error before and after.

Every decision (which geometric parameters and prior, which effect and which of its modes,
whether the residual ELM helps) is made on the training rows alone, by K-fold cross-validation
under the rule of :mod:`torchcal.pipelines.loop.selection`. The held-out ``test`` rows never steer anything:
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
import math
import time

import torch

from torchcal.elm import ELM
from torchcal.effects import EFFECTS, build_effect
from torchcal.measure.checks import check_enough, check_fit_inputs
from torchcal.measure.data import Measurements
from torchcal.measure.observations import KIND_NAMES, Observations
from torchcal.measure.setup import Setup, check_heldout, needs_setup
from torchcal.measure.registration import gross_errors
from torchcal.measure.stats import noise_floor
from torchcal.pipelines.fitting import check_plausible
from torchcal.pipelines.loop.evidence import evidence_for
from torchcal.pipelines.loop.fit import (PRIOR_SCALES_MM, Context, Model, cv_mean_mm, duplicate_groups, folds_of,
                                         geometric_start, noise_sigma, observation_model, split_params)
from torchcal.pipelines.loop.leftover import leftover
from torchcal.pipelines.loop.prune import prune
from torchcal.pipelines.loop.covariates import derive_directions, extrapolation
from torchcal.pipelines.loop.geometry import GEOMETRIC_SETS, choose_geometry, choose_orientation_weight, estimate_noise
from torchcal.pipelines.loop.result import LoopResult
from torchcal.pipelines.loop.selection import HUBER_K, OUTLIER_K, T_ACCEPT, compare, penalised, rmse_mm
from torchcal.pipelines.loop.stages import elm_covariates, elm_inputs, residual_matrix, stage_details
from torchcal.pipelines.loop.steps import (clipped, elm_cv, parameter_table, progress_bar, refit,
                                           refresh, test_gain, try_candidate)
from torchcal.report.calibration import stage_problems
from torchcal.threads import threads_by_size

__all__ = ["run_loop", "T_ACCEPT", "GEOMETRIC_SETS", "PRIOR_SCALES_MM", "derive_directions"]

logger = logging.getLogger("torchcal.loop")

MAX_ROUNDS = 20  # diagnosis rounds at most: each accepts one effect (or modes of one family)



def say_fn(log):
    def out(msg: str) -> None:
        logger.info(msg)
        if log is not None:
            log(msg)
    return out


@threads_by_size("train", "test")
def run_loop(robot, train: Measurements, test: Measurements | None = None, *, candidates: list[str] | None = None,
             folds: int = 5, seed: int = 0, elm: bool = True, elm_hidden: int | None = None,
             noise_mm: float | None = None, orientation_weight: float | None = None, soft: bool = True,
             plausible: dict | None = None, progress: bool = False, log=print) -> LoopResult:
    """Registration → noise estimate → geometry (sets and priors chosen by CV) → diagnosis and
    effects → residual ELM (kept only when it helps in CV) → report.

    Args:
        robot: the :class:`~torchcal.kinematics.robot.Robot` (markers declared).
        train: training rows (:class:`~torchcal.measure.io.Measurements`, m and rad); every decision is
            made on them.
        test: held-out rows, only measured (optional).
        candidates: effect names to consider (default: every effect in
            :data:`torchcal.effects.EFFECTS` that the data allows); checked before any fitting.
        folds: K of the K-fold cross-validation (≥ 2); rows with identical commands share a fold.
        seed: seed of the fold assignment and the ELM.
        elm: try the residual ELM stage; ``elm_hidden``: its hidden units (default N/4, 8–64).
        orientation_weight: m/rad: how a measured orientation error counts against a position error
            (``σ_position / σ_rotation`` of the instruments). Default: estimated from the residuals
            when the rows measure orientations (``<marker>.qw…``); 0: orientations ignored.
        plausible: the largest plausible joint error per unit (default
            :data:`~torchcal.pipelines.fitting.PLAUSIBLE`, 10 mm and 10 mrad): a geometric set moving
            a joint further is not chosen, and a final model doing so is refused (:meth:`LoopResult.problems`).
        soft: a linear family may be kept whole under a Gaussian prior whose scale CV chooses,
            when that beats choosing its modes one by one (False: modes one by one only).
        noise_mm: instrument noise (mean Euclidean error a perfect model would leave, mm) for the
            report; used when no command was measured twice (whose pure error comes first), else
            the median of a ``marker_std_mm`` covariate when the data has one
            (:mod:`~torchcal.pipelines.loop.leftover`).
        progress: a progress bar over the diagnosis candidates (tqdm).
        log: a print-like function for progress lines (``None`` to stay quiet); lines also go
            to the ``torchcal.pipelines.loop.run`` logger.

    Returns:
        A :class:`LoopResult`.
    """
    check_fit_inputs(robot, train, test, enough=False)
    names = list(EFFECTS) if candidates is None else list(candidates)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {sorted(EFFECTS)}")
    if folds < 2:
        raise ValueError(f"folds must be at least 2, got {folds}")
    t0 = time.perf_counter()
    say = say_fn(log)
    derived = derive_directions(train)
    if derived is not None:
        if test is not None:
            derive_directions(test)
        say(f"no direction columns: derived dir.<joint> from the time order of '{derived}' (for backlash)")
    timings: dict[str, float] = {}
    fl = folds_of(len(train), min(folds, len(train)), seed, duplicate_groups(train))

    # 1. nominal: base registration only; the planes and fixed points located from it
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
    ctx = Context(robot, train, fl, None, 1.0, setup, soft=soft, plausible=check_plausible(plausible))
    rot_w = ctx.rot_weight = choose_orientation_weight(ctx, robot, train, setup, orientation_weight, say)
    n_obs = ctx.n_obs
    geo0 = geometric_start(robot, train, GEOMETRIC_SETS[0][1], setup, rot_w is not None)
    stages, errors = [], {}

    def add_stage(name: str, k: float, params, effects, elm_model=None, cv=None, extra=None):
        st_tr, e_tr = stage_details(robot, params, effects, train, elm_model, setup, rot_w)
        st_te, e_te = stage_details(robot, params, effects, test, elm_model, setup, rot_w)
        s = {"name": name, "n_params": int(round(k)), "train": st_tr}
        if st_te is not None:
            s["test"] = st_te
        if cv is not None:
            s["cv_rmse_mm"] = cv
        s.update(extra or {})
        stages.append(s)
        errors[name] = {"train": e_tr["e"], "test": e_te["e"], "train_details": e_tr, "test_details": e_te}
        return s

    add_stage("nominal", 0, geo0, [])
    timings["nominal"] = time.perf_counter() - t0

    # 2. noise: the largest identifiable set, refitted under Huber until the scale settles
    t1 = time.perf_counter()
    # the first, plain fits leave gross errors out (a glitch metres off would drag σ̂, and every
    # parameter would look loose); the Huber fits after them keep every row
    clean = train.hide(gross_errors(robot, train, geo0.values[: robot.n_params]))
    ctx, probe, found = estimate_noise(ctx, robot, train, setup, clean=clean)
    say(f"noise estimate σ̂ = {1e3 * ctx.sigma:.4f} mm per axis; Huber threshold {1e3 * ctx.c:.4f} mm")

    # 3. geometry: nested sets, each from the one before, then the full set under priors
    geo = choose_geometry(ctx, robot, train, setup, probe, found, say)
    best, geo_choice, geo_fits = geo.best, geo.sets, geo.fits
    timings["geometric"] = time.perf_counter() - t1

    # 4. diagnosis
    t2 = time.perf_counter()
    current = best
    cand_report: list[dict] = []
    flags: list[dict] = []
    pool = []
    for n in names:
        eff = build_effect(n, robot, train, geometry=current.params.values[: robot.n_params])
        ok, why = eff.applicable(train)
        if not ok or eff.n_params == 0:
            cand_report.append({"name": n, "accepted": False, "applicable": False, "reason": why or "no parameters"})
            continue
        pool.append(n)
        # whatever the selection decides, the held-out rows cannot check a candidate whose
        # covariates they leave: say so for every candidate tried
        flags += extrapolation(eff, test)
    accepted_steps: list[tuple[str, Model, dict]] = []
    bar = progress_bar(progress)
    rnd = 0
    tabu: dict[str, set[str]] = {}  # effect -> modes pruned in this run
    while pool and rnd < MAX_ROUNDS:
        rnd += 1
        sigma = noise_sigma(ctx, current)
        if abs(HUBER_K * sigma - ctx.c) > 0.1 * ctx.c:
            # the model explains more: tighten the threshold and refit it under it, so that no
            # candidate is credited with what the tighter threshold alone gains
            ctx = ctx.at(HUBER_K * sigma)
            current = refit(ctx, current)
            if accepted_steps:
                accepted_steps[-1] = accepted_steps[-1][:1] + (current,) + accepted_steps[-1][2:]
        results = []
        # the general families only when no physical effect passes: they take what the catalogue leaves
        for tier in ([n for n in pool if not EFFECTS[n].fallback], [n for n in pool if EFFECTS[n].fallback]):
            if any(r.get("ok") for r in results):
                break
            for n in tier:
                if bar is not None:
                    bar.set_description(f"round {rnd}: {n}")
                res = try_candidate(ctx, current, n, robot, train, test, n_obs, say, rnd, tabu.get(n, set()))
                if bar is not None:
                    bar.update(1)
                if res.get("covered"):
                    pool.remove(n)
                results.append(res)
        passing = [r for r in results if r.get("ok")]
        winner = min(passing, key=lambda r: penalised(r["model"].scores, r["model"].k, n_obs)) if passing else None
        if winner is not None:
            # candidates gaining within 2 % of the winner's gain are ties: the fewest parameters,
            # then the registry's order (the plainer effect) takes the round
            gain = float(current.scores.mean() - winner["model"].scores.mean())
            ties = [r for r in passing if float(current.scores.mean() - r["model"].scores.mean()) >= 0.98 * gain]
            winner = min(ties, key=lambda r: (r["model"].k, names.index(r["name"])))
        for r in results:
            entry = dict(r["entry"], round=rnd, accepted=bool(winner is r))
            if "model" in r:
                entry["test_gain_mm"] = test_gain(robot, current, r["model"], test, setup, rot_w)
            cand_report.append(entry)
        if winner is None:
            break
        current = refresh(ctx, winner["model"], n_obs)
        new_modes = winner["entry"].get("added_modes") or [lab for lab, _ in current.effects[-1].modes()]
        current, gone = prune(ctx, current, {(winner["name"], lab) for lab in new_modes}, say)
        if gone:
            winner["entry"]["pruned"] = gone
            for g in gone:
                tabu.setdefault(g["effect"], set()).add(g["mode"])
            pool = list(dict.fromkeys(pool + [g["effect"] for g in gone]))  # its other modes may still come
        accepted_steps.append((winner["name"], current, winner["entry"]))
        if not current.effects[-1].selectable:  # a family stays a candidate: it may gain modes later
            pool.remove(winner["name"])
        say(f"accepted {winner['name']}" + (f" ({', '.join(winner['entry'].get('added_modes', []))})"
                                            if winner["entry"].get("added_modes") else ""))
    if bar is not None:
        bar.close()
    # the final model, refitted until the Huber threshold has followed its own residual: rows it
    # now explains to the noise shrink the threshold, and outliers pull less
    for _ in range(3):
        sigma = noise_sigma(ctx, current)
        if abs(HUBER_K * sigma - ctx.c) <= 0.1 * ctx.c:
            break
        ctx = ctx.at(HUBER_K * sigma)
        current = refit(ctx, current)
    timings["diagnosis"] = time.perf_counter() - t2
    if accepted_steps:
        accepted_steps[-1] = accepted_steps[-1][:1] + (current,) + accepted_steps[-1][2:]
    geo_model = best if accepted_steps else current
    add_stage("geometric", geo_model.k, geo_model.params, [], cv=best.cv_rmse_mm(n_obs),
              extra={"prior_mm": best.prior_mm, "k_eff": geo_model.k})

    accepted, removed = [], []
    evidence = {}
    seen_names: set[str] = set()
    final = {e.name: {lab for lab, _ in e.modes()} for e in current.effects}
    for e in current.effects:  # an extension carries the modes of what it extends: those stay found
        for name in e.supersedes:
            final.setdefault(name, set()).update(final[e.name])
    for name, m, entry in accepted_steps:
        eff = m.effects[-1]
        _, parts = split_params(m.params, robot, m.effects)
        for e, p in zip(m.effects, parts):
            e.theta = p.values.clone()
        stage = f"+{name}" if name not in seen_names else f"+{name} ({', '.join(entry.get('added_modes', []))})"
        seen_names.add(name)
        s = add_stage(stage, m.k, m.params, m.effects, cv=m.cv_rmse_mm(n_obs))
        prev = stages[-2]
        gain = None if "test" not in s or "test" not in prev else prev["test"]["mean_mm"] - s["test"]["mean_mm"]
        removed += entry.get("pruned", [])
        if name not in final:  # a later round's findings explained it away
            continue
        ev_text, ev_data = evidence_for(robot, m, train, setup)
        evidence[stage.lstrip("+")] = ev_data
        kept = m.params.free[len(m.params) - eff.n_params:].clone()
        for lab, idx in eff.modes():
            if lab not in final[name] and eff.selectable:
                kept[[i for i in idx if i not in set(eff.shared())]] = False
        accepted.append({"name": name, "stage": stage, "joints": list(eff.joints), "n_params": eff.n_params,
                         "modes": [lab for lab, _ in eff.modes() if lab in final[name] or not eff.selectable],
                         "added_modes": [lab for lab in entry.get("added_modes", []) if lab in final[name]],
                         "extends": entry.get("extends", []), "cv_gain_mm": entry["cv_gain_mm"],
                         "test_gain_mm": gain, "evidence": ev_text,
                         "found": eff.describe(free=kept)
                         + [f"{a} cannot be told from {', '.join(b)} by these data: one finding, either of them"
                            for a, b in entry.get("aliases", {}).items()]
                         + ([f"all {len(eff.modes())} modes kept under a Gaussian prior of {eff.ridge_mm:.3g} mm RMS at "
                             "the markers per mode (its scale chosen by CV): together they explain what no single "
                             "mode shows clearly"] if eff.ridge is not None else []),
                         "soft_prior_mm": eff.ridge_mm,
                         "aliases": entry.get("aliases", {}),
                         "params": {n: float(v) for n, v, f in zip(m.params.names, m.params.values.tolist(),
                                                                     m.params.free.tolist())
                                    if n.startswith(eff.name + ".") and f},
                         "standard_errors": {n: v for n, v in m.info.get("se", {}).items() if n.startswith(eff.name + ".")},
                         "units": dict(zip(eff.param_names, eff.param_units))})

    # 5. residual ELM
    t3 = time.perf_counter()
    elm_model = None
    if elm and not (train.positions_only and (test is None or test.positions_only)):
        say("residual ELM not tried: it learns 3-D position errors, and these rows hold partial positions, plane "
            "contacts or distances")
    elif elm and len(train) >= 20:
        H = elm_hidden or max(8, min(64, len(train) // 4))
        sc_elm, sq_elm = elm_cv(ctx, current, H, seed)
        k_elm = H * 3 * len(train.marker_names)
        t, pen_ok, ok = compare(current.scores, sc_elm, current.k, current.k + k_elm, n_obs)
        gain = current.cv_rmse_mm(n_obs) - rmse_mm(sq_elm, n_obs)
        cand_report.append({"name": "residual_elm", "n_params": k_elm, "cv_rmse_mm": rmse_mm(sq_elm, n_obs),
                            "cv_gain_mm": gain, "t": t, "penalised_ok": pen_ok, "accepted": ok})
        say(f"residual ELM ({H} hidden): CV {rmse_mm(sq_elm, n_obs):.4f} mm  gain {gain:+.4f} mm  t = {t:.1f}"
            f"  {'kept' if ok else 'not kept'}")
        if ok:
            r = clipped(residual_matrix(robot, current.params, current.effects, train, setup), ctx.c)
            elm_model = ELM(n_hidden=H, ridge=1e-3, seed=seed).fit(elm_inputs(train), r)
            add_stage("+residual_elm", current.k + k_elm, current.params, current.effects, elm_model)
    timings["residual_elm"] = time.perf_counter() - t3

    # 6. suspects: listed, never dropped
    sigma = noise_sigma(ctx, current)
    prob = observation_model(ctx, current.params, current.effects, train)
    err = prob.errors(current.params.values[None])[0]
    obs = prob.obs
    # a 3-D error reaches √3 σ̂ typically; an observation of fewer components proportionally less
    bad = torch.nonzero(err > OUTLIER_K * obs.dims.sqrt() * sigma).flatten()
    suspects = [{"row": int(obs.rows[i]), "marker": train.marker_names[int(obs.data_marker[i])],
                 "kind": KIND_NAMES[int(obs.kind[i])], "error_mm": float(err[i] * 1e3)}
                for i in bad[torch.argsort(err[bad], descending=True)].tolist()]
    if suspects:
        say(f"{len(suspects)} suspect observation(s) beyond {OUTLIER_K:g}·√3·σ̂ = "
            f"{1e3 * OUTLIER_K * math.sqrt(3) * sigma:.3f} mm (down-weighted by the Huber loss, kept): rows "
            + ", ".join(str(s["row"]) for s in suspects[:10]) + (" …" if len(suspects) > 10 else ""))
    timings["total"] = time.perf_counter() - t0

    noise_mm, noise_source = noise_floor(train, noise_mm)
    left = leftover(train, residual_matrix(robot, current.params, current.effects, train, setup),
                    cv_mean_mm(ctx, current), noise_mm, noise_source)
    for line in left.words() + [f"the residual still follows {a.words()}" for a in left.associations[:3]
                                if left.missing]:
        say(line)
    for p in stage_problems(stages):
        say("warning: " + p)
    parameters, observability = parameter_table(ctx, current)
    return LoopResult(robot=robot, params=current.params, effects=current.effects, elm=elm_model, stages=stages,
                      accepted=accepted, candidates=cand_report,
                      geometric={"chosen": best.label, "sets": geo_choice, "prior_mm": best.prior_mm},
                      n_train=len(train), n_test=0 if test is None else len(test), noise_floor_mm=noise_mm,
                      noise_floor_source=noise_source,
                      timings=timings, errors=errors, evidence=evidence, elm_covariates=elm_covariates(train),
                      geometric_fits=geo_fits, noise_sigma_mm=1e3 * sigma, huber_mm=1e3 * ctx.c,
                      suspects=suspects, flags=flags, prior_mm=best.prior_mm, parameters=parameters,
                      observability=observability, setup=setup, leftover=left, removed=removed,
                      plausible=ctx.plausible)


