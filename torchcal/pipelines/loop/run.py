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
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchcal.deploy.elm import ELM
from torchcal.effects import EFFECTS, build_effect
from torchcal.measure.data import Measurements
from torchcal.measure.observations import KIND_NAMES, Observations, Setup, check_heldout, needs_setup
from torchcal.params import ParamSet
from torchcal.pipelines.loop.evidence import evidence_for
from torchcal.pipelines.loop.fit import (PRIOR_SCALES_MM, Context, Model, effect_start, evaluate,
                                         evaluate_prior, folds_of, geometric_start, noise_sigma,
                                         observation_model, rescore, split_params)
from torchcal.pipelines.loop.selection import (HUBER_K, OUTLIER_K, T_ACCEPT, compare, penalised, rmse_mm,
                                               row_scores)
from torchcal.problems.identifiability import analyse_jacobian
from torchcal.problems.unseen import unseen
from torchcal.report.calibration import error_details, error_stats, stage_problems

__all__ = ["run_loop", "LoopResult", "T_ACCEPT", "GEOMETRIC_SETS", "PRIOR_SCALES_MM", "stage_stats",
           "derive_directions"]

logger = logging.getLogger("torchcal.pipelines.loop.run")

# Nested geometric parameter sets, smallest first: (name, glob patterns, or None for the robot's
# default free set: every origin / DH error). Markers' positions are always free.
GEOMETRIC_SETS = [
    ("base+markers", ["base.*"]),
    ("+joint offsets", ["base.*", "*.offset", "*.dtheta"]),
    ("+joint origins", None),
]


@dataclass
class LoopResult:
    """Outcome of :func:`run_loop`; :meth:`report` has the JSON shape of ``report.json``.

    Attributes:
        params: geometry + accepted effects, fitted on all training rows.
        effects: accepted effect objects (fitted ``theta``); ``elm``: the residual ELM or None.
        stages: per stage, error statistics (mm) on the training and held-out rows.
        accepted / candidates: what was added, and every candidate examined, with the numbers
            that decided (cross-validated) and the held-out gain measured afterwards.
        geometric: the geometric sets and priors tried and the one chosen.
        noise_sigma_mm: robust per-axis noise estimate of the final model (mm);
            ``huber_mm``: the Huber threshold of the last round (mm).
        suspects: training observations beyond ``OUTLIER_K σ̂``: row, marker, error (mm).
        flags: warnings about candidates (a covariate outside its training range on the test rows).
    """

    robot: object
    params: ParamSet
    effects: list
    elm: object | None
    stages: list[dict]
    accepted: list[dict]
    candidates: list[dict]
    geometric: dict
    n_train: int
    n_test: int
    noise_floor_mm: float | None
    timings: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)   # stage -> {"train": Tensor, "test": Tensor} (m)
    evidence: dict = field(default_factory=dict)  # effect -> arrays for plots
    elm_covariates: list = field(default_factory=list)
    geometric_fits: dict = field(default_factory=dict)  # set name -> ParamSet fitted on all training rows
    noise_sigma_mm: float | None = None
    huber_mm: float | None = None
    suspects: list = field(default_factory=list)
    flags: list = field(default_factory=list)
    prior_mm: float | None = None
    parameters: list = field(default_factory=list)     # [{name, value, unit, std_error}] of the final model
    observability: dict = field(default_factory=dict)  # condition number, O1-O4 of its identified set
    setup: Setup | None = None  # planes and fixed points the rows measured against (None: positions only)

    def __repr__(self) -> str:
        last = self.stages[-1]
        te = f", held-out mean {last['test']['mean_mm']:.4f} mm" if last.get("test") else ""
        return (f"LoopResult({self.robot.name}: {' → '.join(s['name'] for s in self.stages)}; training mean "
                f"{last['train']['mean_mm']:.4f} mm{te}; {len(self.suspects)} suspect observation(s))")

    def problems(self) -> list[str]:
        """Reasons not to trust this model, in words: a final model worse than the nominal one on
        its own training rows, or held-out rows that do not belong to this robot. Empty when none."""
        return stage_problems(self.stages)

    def report(self) -> dict:
        return {"robot": self.robot.name, "n_train": self.n_train, "n_test": self.n_test,
                "noise_floor_mm": self.noise_floor_mm, "noise_sigma_mm": self.noise_sigma_mm,
                "huber_threshold_mm": self.huber_mm, "stages": self.stages, "effects": self.accepted,
                "candidates": self.candidates, "geometric_set": self.geometric, "prior_mm": self.prior_mm,
                "suspect_rows": self.suspects, "flags": self.flags, "parameters": self.parameters,
                "observability": self.observability, "problems": self.problems(),
                "setup": None if self.setup is None else self.setup.describe(
                    self.params.values[self.robot.n_params:self.robot.n_params + self.setup.n_params]),
                "rule": f"accept when the paired t statistic of the cross-validated per-row Huber-score "
                        f"improvement exceeds {T_ACCEPT} and mean*(1+2k/n_obs) decreases (k: effective "
                        f"parameters); a family's modes are added one by one under the same rule with the "
                        f"threshold raised for the number of modes tried",
                "residual_elm": self.elm is not None, "timings_s": self.timings}

    def model(self, *, force: bool = False):
        """A deployable :class:`~torchcal.deploy.model.CalibratedModel`; refused (``ValueError``) when
        :meth:`problems` says the model cannot be trusted, unless ``force``."""
        from torchcal.deploy.model import CalibratedModel

        if self.problems() and not force:
            raise ValueError("this calibration is not fit to deploy: " + "; ".join(self.problems()))
        geo = self.robot.params(self.params.values[: self.robot.n_params])
        geo.free = self.params.free[: self.robot.n_params].clone()
        residual = self.elm
        if residual is not None and residual.n_outputs_ != 3:
            raise ValueError("the residual ELM predicts several markers at once; a deployable model holds a "
                             "residual for one marker: run the loop with that marker only")
        return CalibratedModel(self.robot, geo, effects=list(self.effects), residual=residual,
                               covariates=self.elm_covariates if residual is not None else None,
                               meta={"report": self.report()})


# ----------------------------------------------------------------------------- statistics
def stage_stats(robot, params: ParamSet, effects: list, data: Measurements | None, elm=None,
                setup: Setup | None = None) -> tuple[dict | None, Tensor]:
    """Error statistics (mm), overall and per marker, and the per-observation errors (m) of a
    model on ``data`` (``setup``: the planes and fixed points, ``LoopResult.setup``). An
    observation's error is the Euclidean norm of what it measured: a plane contact's signed
    distance, a partial position's measured axes."""
    st, d = _stage(robot, params, effects, data, elm, setup)
    return st, d["e"]


def _stage(robot, params: ParamSet, effects: list, data: Measurements | None, elm=None,
           setup: Setup | None = None) -> tuple[dict | None, dict]:
    """:func:`stage_stats` and the error details a figure needs (:func:`torchcal.report.calibration.error_details`)."""
    if data is None or len(data) == 0:
        z = torch.zeros(0)
        return None, {"e": z, "xyz": z.reshape(0, 3), "dist": z}
    prob = observation_model(Context(robot, data, [], None, 1.0, setup), params, effects, data)
    e3 = prob.residual_vectors(params.values[None])[0]
    if elm is not None:  # the ELM is only fitted on full positions, whose order is data.seen's
        r = residual_matrix(robot, params, effects, data, setup)
        left = (r - elm.predict(elm_inputs(data))).reshape(len(data), -1, 3)
        e3 = -left[data.seen]
    d = error_details(robot, params.values[: robot.n_params], data, e3, prob.obs)
    cols = prob.obs.data_marker
    e = d["e"]
    out = error_stats(e)
    out["per_marker"] = {m: error_stats(e[cols == k]) for k, m in enumerate(data.marker_names) if bool((cols == k).any())}
    kinds = torch.unique(prob.obs.kind).tolist()
    if len(kinds) > 1 or kinds != [0] or not bool(prob.obs.mask.all()):
        out["per_kind"] = {KIND_NAMES[k]: error_stats(e[prob.obs.kind == k]) for k in kinds}
    return out, d


def residual_matrix(robot, params: ParamSet, effects: list, data: Measurements, setup: Setup | None = None) -> Tensor:
    """``(N, 3M)`` measured − model position per row (NaN where a marker's full position was not
    measured)."""
    prob = observation_model(Context(robot, data, [], None, 1.0, setup), params, effects, data)
    e3 = prob.residual_vectors(params.values[None])[0]
    full = prob.obs.full_positions
    out = torch.full((len(data), len(data.marker_names), 3), float("nan"), dtype=e3.dtype, device=e3.device)
    out[prob.obs.rows[full], prob.obs.data_marker[full]] = -e3[full]
    return out.reshape(len(data), -1)


def elm_covariates(data: Measurements) -> list[str]:
    """Covariates the residual ELM reads after the commands: temperatures and directions."""
    return [k for k in sorted(data.covariates) if k.startswith(("temp", "dir."))]


def elm_inputs(data: Measurements) -> Tensor:
    return torch.cat([data.q] + [data.covariates[k][:, None] for k in elm_covariates(data)], 1)


# ----------------------------------------------------------------------------- covariates
TIME_COLUMNS = ("t_start_robot", "time", "t", "timestamp")


def derive_directions(data: Measurements) -> str | None:
    """Add ``dir.<joint>`` covariates (+1/-1: direction from which each joint reached the
    posture) from the time order of the rows, when the data has a time column and no direction
    columns. The first posture in time counts as approached from below. Returns the time column
    used, or None. A covariate, not a measurement: it is derived for test data the same way."""
    if any(k.startswith("dir.") for k in data.covariates):
        return None
    key = next((k for k in TIME_COLUMNS if k in data.covariates), None)
    if key is None or len(data) < 2:
        return None
    order = torch.argsort(data.covariates[key])
    q = data.q[order]
    steps = torch.diff(q, dim=0, prepend=q[:1])
    d = torch.where(steps >= 0, torch.ones_like(q), -torch.ones_like(q))
    inv = torch.empty_like(order)
    inv[order] = torch.arange(len(order), device=order.device)
    for j, n in enumerate(data.joint_names):
        data.covariates[f"dir.{n}"] = d[inv, j]
    return key


def _extrapolation(eff, test: Measurements | None) -> list[dict]:
    """Covariates an effect reads whose held-out values leave the training range."""
    out = []
    if test is None:
        return out
    for c, (lo, hi) in eff.covariate_range.items():
        if c not in test.covariates:
            continue
        v = test.covariates[c]
        tol = 0.01 * (hi - lo)
        outside = float(((v < lo - tol) | (v > hi + tol)).double().mean())
        if outside > 0:
            out.append({"effect": eff.name, "covariate": c, "train_range": [lo, hi],
                        "test_range": [float(v.min()), float(v.max())], "fraction_outside": outside,
                        "note": "the held-out rows lie outside the training range of this covariate: the "
                                "effect would extrapolate there" + (" (time covariates are clamped to the "
                                                                    "training range in the deployed model)"
                                                                    if c in TIME_COLUMNS else "")})
    return out


# ----------------------------------------------------------------------------- the loop
def _duplicate_groups(data: Measurements) -> Tensor:
    """A group id per row: rows with identical commands share one (they must share a fold)."""
    _, inv = torch.unique(data.q, dim=0, return_inverse=True)
    return inv


def _say(log):
    def out(msg: str) -> None:
        logger.info(msg)
        if log is not None:
            log(msg)
    return out


def run_loop(robot, train: Measurements, test: Measurements | None = None, *, candidates: list[str] | None = None,
             folds: int = 5, seed: int = 0, elm: bool = True, elm_hidden: int | None = None,
             noise_mm: float | None = None, progress: bool = False, log=print) -> LoopResult:
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
        noise_mm: instrument noise (mean Euclidean error a perfect model would leave, mm) for the
            report; default: the median of a ``marker_std_mm`` covariate when the data has one.
        progress: a progress bar over the diagnosis candidates (tqdm).
        log: a print-like function for progress lines (``None`` to stay quiet); lines also go
            to the ``torchcal.pipelines.loop.run`` logger.

    Returns:
        A :class:`LoopResult`.
    """
    names = list(EFFECTS) if candidates is None else list(candidates)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {sorted(EFFECTS)}")
    if folds < 2:
        raise ValueError(f"folds must be at least 2, got {folds}")
    t0 = time.perf_counter()
    say = _say(log)
    derived = derive_directions(train)
    if derived is not None:
        if test is not None:
            derive_directions(test)
        say(f"no direction columns: derived dir.<joint> from the time order of '{derived}' (for backlash)")
    timings: dict[str, float] = {}
    n_obs = train.n_values / 3
    fl = folds_of(len(train), min(folds, len(train)), seed, _duplicate_groups(train))

    # 1. nominal: base registration only; the planes and fixed points located from it
    if test is not None:
        check_heldout(train, test)
    setup = Setup.from_data(robot, train, geometric_start(robot, train, None).values) if needs_setup(train) else None
    if test is not None:
        Observations(robot, test, setup)  # the held-out rows fit this robot and set-up, before any fitting
    if setup is not None:
        say(f"set-up unknowns identified with the robot: planes {setup.planes}, fixed points {setup.pivots}"
            + ("" if int(train.seen.sum()) >= 3 else "; no position measured, so the instrument frame is the "
               "robot base"))
    geo0 = geometric_start(robot, train, GEOMETRIC_SETS[0][1], setup)
    stages, errors = [], {}

    def add_stage(name: str, k: float, params, effects, elm_model=None, cv=None, extra=None):
        st_tr, e_tr = _stage(robot, params, effects, train, elm_model, setup)
        st_te, e_te = _stage(robot, params, effects, test, elm_model, setup)
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
    ctx = Context(robot, train, fl, None, 1.0, setup)
    probe = evaluate(ctx, "noise probe", geometric_start(robot, train, None, setup), [], None)
    for _ in range(3):
        sigma = noise_sigma(ctx, probe)
        ctx = ctx.at(HUBER_K * sigma, sigma)
        probe = evaluate(ctx, "noise probe", geometric_start(robot, train, None, setup), [], None)
    say(f"noise estimate σ̂ = {1e3 * ctx.sigma:.4f} mm per axis; Huber threshold {1e3 * ctx.c:.4f} mm")

    # 3. geometry: nested sets, then priors when the full set is rejected
    geo_choice, geo_fits = [], {}
    best: Model | None = None
    for name, pats in GEOMETRIC_SETS:
        m = probe if pats is None else evaluate(ctx, name, geometric_start(robot, train, pats, setup), [], None)
        m.label = name
        geo_fits[name] = m.params
        entry = {"name": name, "n_params": int(round(m.k)), "cv_rmse_mm": m.cv_rmse_mm(n_obs)}
        if best is None:
            entry["accepted"] = True
            best = m
        else:
            t, _, ok = _compare_at(ctx, best, m, n_obs)
            entry.update({"t": t, "accepted": ok})
            if ok:
                best = m
        geo_choice.append(entry)
        say(f"geometric set {name:<24} {m.k:>5.1f} params  CV {entry['cv_rmse_mm']:.4f} mm"
            + ("" if "t" not in entry else f"  t = {entry['t']:.1f}  {'accepted' if entry['accepted'] else 'rejected'}"))
    if best.label != GEOMETRIC_SETS[-1][0]:
        full_start = geometric_start(robot, train, None, setup)  # every error, held by the prior
        tried: list[Model] = []
        m = evaluate_prior(ctx, "prior", full_start, [], PRIOR_SCALES_MM[len(PRIOR_SCALES_MM) // 2], tried=tried)
        for mt in sorted(tried, key=lambda x: x.prior_mm):
            name = f"prior {mt.prior_mm:g} mm/mrad"
            geo_fits[name] = mt.params
            geo_choice.append({"name": name, "n_params": int(mt.params.free.sum()), "k_eff": mt.k,
                               "prior_mm": mt.prior_mm, "cv_rmse_mm": mt.cv_rmse_mm(n_obs),
                               "penalised_mm2": 1e6 * penalised(mt.scores, mt.k, n_obs), "chosen_scale": mt is m})
        t, _, ok = _compare_at(ctx, best, m, n_obs)
        m.label = f"prior {m.prior_mm:g} mm/mrad"
        next(g for g in geo_choice if g["name"] == m.label).update({"t": t, "accepted": ok})
        say(f"geometric {m.label:<26} (scale chosen by CV among {sorted(x.prior_mm for x in tried)})  k_eff "
            f"{m.k:>5.1f}  CV {m.cv_rmse_mm(n_obs):.4f} mm  t = {t:.1f}  {'accepted' if ok else 'rejected'}")
        if ok:
            best = m
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
    accepted_steps: list[tuple[str, Model, dict]] = []
    bar = _bar(progress)
    rnd = 0
    while pool:
        rnd += 1
        sigma = noise_sigma(ctx, current)
        if abs(HUBER_K * sigma - ctx.c) > 0.1 * ctx.c:
            # the model explains more: tighten the threshold and refit it under it, so that no
            # candidate is credited with what the tighter threshold alone gains
            ctx = ctx.at(HUBER_K * sigma)
            current = _refit(ctx, current)
            if accepted_steps:
                accepted_steps[-1] = accepted_steps[-1][:1] + (current,) + accepted_steps[-1][2:]
        results = []
        for n in list(pool):
            if bar is not None:
                bar.set_description(f"round {rnd}: {n}")
            res = _try(ctx, current, n, robot, train, test, n_obs, say, rnd)
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
                entry["test_gain_mm"] = _test_gain(robot, current, r["model"], test, setup)
                flags += _extrapolation(r["model"].effects[-1], test)
            cand_report.append(entry)
        if winner is None:
            break
        current = _refresh(ctx, winner["model"], n_obs)
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
        current = _refit(ctx, current)
    timings["diagnosis"] = time.perf_counter() - t2
    if accepted_steps:
        accepted_steps[-1] = accepted_steps[-1][:1] + (current,) + accepted_steps[-1][2:]
    geo_model = best if accepted_steps else current
    add_stage("geometric", geo_model.k, geo_model.params, [], cv=best.cv_rmse_mm(n_obs),
              extra={"prior_mm": best.prior_mm, "k_eff": geo_model.k})

    accepted = []
    evidence = {}
    seen_names: set[str] = set()
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
        ev_text, ev_data = evidence_for(robot, m, train, setup)
        evidence[stage.lstrip("+")] = ev_data
        accepted.append({"name": name, "stage": stage, "joints": list(eff.joints), "n_params": eff.n_params,
                         "modes": [lab for lab, _ in eff.modes()], "added_modes": entry.get("added_modes", []),
                         "extends": entry.get("extends", []), "cv_gain_mm": entry["cv_gain_mm"],
                         "test_gain_mm": gain, "evidence": ev_text,
                         "found": eff.describe(free=m.params.free[len(m.params) - eff.n_params:]),
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
        sc_elm, sq_elm = _elm_cv(ctx, current, H, seed)
        k_elm = H * 3 * len(train.marker_names)
        t, pen_ok, ok = compare(current.scores, sc_elm, current.k, current.k + k_elm, n_obs)
        gain = current.cv_rmse_mm(n_obs) - rmse_mm(sq_elm, n_obs)
        cand_report.append({"name": "residual_elm", "n_params": k_elm, "cv_rmse_mm": rmse_mm(sq_elm, n_obs),
                            "cv_gain_mm": gain, "t": t, "penalised_ok": pen_ok, "accepted": ok})
        say(f"residual ELM ({H} hidden): CV {rmse_mm(sq_elm, n_obs):.4f} mm  gain {gain:+.4f} mm  t = {t:.1f}"
            f"  {'kept' if ok else 'not kept'}")
        if ok:
            r = _clipped(residual_matrix(robot, current.params, current.effects, train, setup), ctx.c)
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

    if noise_mm is None and "marker_std_mm" in train.covariates:
        noise_mm = float(train.covariates["marker_std_mm"].median())
    for p in stage_problems(stages):
        say("warning: " + p)
    parameters, observability = _parameter_table(ctx, current)
    return LoopResult(robot=robot, params=current.params, effects=current.effects, elm=elm_model, stages=stages,
                      accepted=accepted, candidates=cand_report,
                      geometric={"chosen": best.label, "sets": geo_choice, "prior_mm": best.prior_mm},
                      n_train=len(train), n_test=0 if test is None else len(test), noise_floor_mm=noise_mm,
                      timings=timings, errors=errors, evidence=evidence, elm_covariates=elm_covariates(train),
                      geometric_fits=geo_fits, noise_sigma_mm=1e3 * sigma, huber_mm=1e3 * ctx.c,
                      suspects=suspects, flags=flags, prior_mm=best.prior_mm, parameters=parameters,
                      observability=observability, setup=setup)


def _parameter_table(ctx: Context, m: Model) -> tuple[list, dict]:
    """The final model's identified parameters (value, unit, standard error) and the condition
    number and observability indices (O1-O4) of their Jacobian."""
    p = m.params
    se = m.info.get("se", {})
    table = [{"name": n, "value": float(v), "unit": u, "std_error": se.get(n)}
             for n, v, u, f in zip(p.names, p.values.tolist(), p.units, p.free.tolist()) if f]
    prob = observation_model(ctx, p, m.effects, ctx.data)
    rep = analyse_jacobian(prob.data_jacobian(prob.x0), p.free_names, [p.units[i] for i in p.free_index.tolist()],
                           markers=ctx.robot.marker_names)
    fin = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
    out = {"condition": fin(rep.condition), "O1": fin(rep.O1), "O2": fin(rep.O2), "O3": fin(rep.O3),
           "O4": fin(rep.O4), "rank": rep.rank, "n_params": rep.n_params, "not_seen_by_data": list(rep.dropped)}
    if not ctx.data.positions_only:
        out["not_seen"] = unseen(ctx.robot, ctx.data, p, ctx.setup)
    return table, out


def _bar(progress: bool):
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(desc="diagnosis", unit="candidate")


def _try(ctx: Context, current: Model, name: str, robot, train, test, n_obs: int, say, rnd: int) -> dict:
    """One candidate effect against ``current``: its start (modes chosen), fit, CV and the rule;
    under a geometric prior, the prior is re-chosen among its neighbours with the effect."""
    covering = [e.name for e in current.effects if name in getattr(e, "supersedes", ()) and e.name != name]
    if covering:
        return {"name": name, "covered": True,
                "entry": {"name": name, "reason": f"its modes are part of the accepted {covering[0]}"}}
    eff = build_effect(name, robot, train, geometry=current.params.values[: robot.n_params])
    # a family replaces what it extends: an effect it supersedes, or itself accepted with fewer modes
    superseded = [e for e in current.effects if e.name in eff.supersedes or (eff.selectable and e.name == name)]
    start = effect_start(ctx, current, eff, superseded)
    if start["effect"] is None:
        say(f"round {rnd}: {name:<20} {start['reason']}")
        return {"name": name, "entry": {"name": name, "reason": start["reason"], "selection": start["selection"]}}
    if start["prior_mm"] is None:
        best = evaluate(ctx, f"+{name}", start["params"], start["effects"], None, info=start["info"])
    else:  # with the effect in, the geometry may want another prior: its CV chooses again
        best = evaluate_prior(ctx, f"+{name}", start["params"], start["effects"], start["prior_mm"], info=start["info"])
    t, pen_ok, ok = compare(current.scores, best.scores, current.k, best.k, n_obs)
    gain = current.cv_rmse_mm(n_obs) - best.cv_rmse_mm(n_obs)
    modes = [lab for lab, _ in best.effects[-1].modes()] if best.effects[-1].selectable else []
    before = {lab for e in superseded for lab, _ in e.modes()}
    added = [lab for lab in modes if lab not in before]
    say(f"round {rnd}: {name:<20} {best.k:>5.1f} params  CV {best.cv_rmse_mm(n_obs):.4f} mm  gain {gain:+.4f} mm"
        f"  t = {t:.1f}" + (f"  modes: {', '.join(modes)}" if modes else ""))
    entry = {"name": name, "n_params": int(round(best.k)), "cv_rmse_mm": best.cv_rmse_mm(n_obs),
             "cv_gain_mm": gain, "t": t, "penalised_ok": pen_ok, "modes": modes, "added_modes": added,
             "extends": [e.name for e in superseded], "selection": start["selection"]}
    if best.prior_mm is not None:
        entry["prior_mm"] = best.prior_mm
    return {"name": name, "ok": ok, "model": best, "entry": entry}


def _compare_at(ctx: Context, best: Model, m: Model, n_obs: int) -> tuple[float, bool, bool]:
    """The rule between ``best`` and ``m``, scored with ``best``'s own Huber threshold: scores
    are held constant beyond a multiple of the threshold, so a threshold set by a better model
    would make every error of a coarse one look alike."""
    c = HUBER_K * noise_sigma(ctx, best)
    if c <= ctx.c:
        return compare(best.scores, m.scores, best.k, m.k, n_obs)
    at = ctx.at(c)
    return compare(rescore(at, best), rescore(at, m), best.k, m.k, n_obs)


def _refit(ctx: Context, m: Model) -> Model:
    """``m`` fitted again under the context's threshold, every candidate parameter judged again:
    with less noise left, parameters the rounds before could not see may be seen now."""
    again = m.params.clone()
    again.free[: ctx.n_geo] = m.info["candidates"]
    again.free[ctx.n_geo:] = True
    return evaluate(ctx, m.label, again, m.effects, m.prior_mm, info=m.info)


def _refresh(ctx: Context, m: Model, n_obs: int) -> Model:
    """The accepted model with its new effect's features recomputed at the geometry fitted with
    it: the rigid fit it started from had absorbed part of the effect into the geometry (a mean
    joint deflection into a zero offset), and the gravity torques depend on those angles."""
    geo = m.params.values[: ctx.robot.n_params]
    eff = m.effects[-1].at_geometry(geo)
    eff.theta = m.effects[-1].theta.clone()
    again = evaluate(ctx, m.label, m.params, m.effects[:-1] + [eff], m.prior_mm, info=m.info)
    return again if penalised(again.scores, again.k, n_obs) <= penalised(m.scores, m.k, n_obs) else m


def _test_gain(robot, current: Model, cand: Model, test, setup: Setup | None = None) -> float | None:
    """Held-out mean gain of a candidate over the current model (measured after the decision)."""
    if test is None:
        return None
    a, _ = stage_stats(robot, current.params, current.effects, test, setup=setup)
    b, _ = stage_stats(robot, cand.params, cand.effects, test, setup=setup)
    return a["mean_mm"] - b["mean_mm"]


def _clipped(r: Tensor, c: float | None) -> Tensor:
    """``(N, 3M)`` residuals with each observation shortened to at most ``c`` (Huber's
    pseudo-observations: a least-squares learner fitted to them is as robust as the loss), NaN -> 0."""
    r3 = torch.nan_to_num(r).reshape(r.shape[0], -1, 3)
    if c is not None:
        n = r3.norm(dim=-1, keepdim=True)
        r3 = r3 * torch.where(n > c, c / n.clamp(min=1e-300), torch.ones_like(n))
    return r3.reshape(r.shape)


def _elm_cv(ctx: Context, current: Model, n_hidden: int, seed: int) -> tuple[Tensor, Tensor]:
    """Cross-validated per-row scores (Huber, and plain squared errors) of the current model plus
    a residual ELM fitted per fold."""
    robot, data = ctx.robot, ctx.data
    out = torch.zeros(len(data), dtype=robot.dtype, device=robot.device)
    plain = torch.zeros_like(out)
    for f, p in zip(ctx.folds, current.fold_fits):
        mask = torch.ones(len(data), dtype=torch.bool)
        mask[f] = False
        tr, va = data.subset(mask), data.subset(f)
        r_tr = _clipped(residual_matrix(robot, p, current.effects, tr), ctx.c)
        model = ELM(n_hidden=n_hidden, ridge=1e-3, seed=seed).fit(elm_inputs(tr), r_tr)
        left = (residual_matrix(robot, p, current.effects, va) - model.predict(elm_inputs(va))).reshape(len(va), -1, 3)
        seen = va.seen
        rows = torch.nonzero(seen)[:, 0]
        out[f] = row_scores(left[seen].norm(dim=-1), rows, len(va), ctx.c)
        plain[f] = row_scores(left[seen].norm(dim=-1), rows, len(va), None)
    return out, plain
