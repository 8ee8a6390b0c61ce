"""The loop's geometric stages: the noise estimate, then the geometric model chosen among nested
parameter sets and Gaussian priors by cross-validation.

**Starts.** Every set starts where the smaller one before it ended: the marker points and the
instrument frame are found first (base + markers), and a bigger set starts from them. A marker
guessed on a joint axis hides that joint's offset at the guess, so a set judged from the guess
would lose to a smaller one for a reason that has nothing to do with the robot.

**Priors.** The full set is also fitted with a Gaussian prior on every geometric error (scale in
mm and mrad chosen by the penalised CV error, :func:`~torchcal.pipelines.crossval.evaluate.evaluate_prior`).
When the full set itself was accepted, on small data (fewer than ten values per parameter,
:func:`~torchcal.pipelines.fitting.is_small`) the prior is a setting of the same model and
replaces it when its penalised CV error is lower; otherwise it must pass the rule against the best
set.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field, replace

from torchcal.measure.data import Measurements
from torchcal.params import ParamSet
from torchcal.pipelines.fitting import is_small
from torchcal.pipelines.precision import implausible_values
from torchcal.pipelines.crossval.priors import PRIOR_SCALES_MM, plausible_scale
from torchcal.pipelines.crossval.models import Context, Model, effect_problem, noise_sigma, orientation_count
from torchcal.pipelines.crossval.evaluate import cv_mean_mm, evaluate, evaluate_prior, fit_params
from torchcal.problems.template import geometric_start
from torchcal.pipelines.crossval.scores import HUBER_K, penalised
from torchcal.measure.noise import robust_sigma
from torchcal.pipelines.loop.steps import compare_at

__all__ = ["GEOMETRIC_SETS", "GeometryChoice", "warm_start", "estimate_noise", "choose_geometry", "orientation_weight",
           "choose_orientation_weight"]

# Nested geometric parameter sets, smallest first: (name, glob patterns, or None for the robot's
# default free set: every origin / DH error). Markers' positions are always free.
GEOMETRIC_SETS = [
    ("base+markers", ["base.*"]),
    ("+joint offsets", ["base.*", "*.offset", "*.dtheta"]),
    ("+joint origins", None),
]


@dataclass
class GeometryChoice:
    """The geometric model chosen (``best``), every set and prior tried with its CV figures
    (``sets``: what report.json's ``geometric_set.sets`` holds) and each fit (``fits``)."""

    best: Model
    sets: list[dict] = field(default_factory=list)
    fits: dict[str, ParamSet] = field(default_factory=dict)


def warm_start(start: ParamSet, fitted: ParamSet) -> ParamSet:
    """``start``'s free flags with the values of an earlier fit (same layout): its marker points,
    instrument frame and errors, where a bigger model begins."""
    p = start.clone()
    p.values = fitted.values.clone()
    return p


def _markers_found(ctx: Context, robot, data: Measurements, setup) -> ParamSet:
    """The instrument frame and the marker points (and frames, when turned ones are measured)
    fitted alone, from the registration."""
    start = geometric_start(robot, data, GEOMETRIC_SETS[0][1], setup, turns=ctx.rot_weight is not None)
    return fit_params(ctx, start, [], data, None, reduce=True)


def orientation_weight(ctx: Context, robot, data: Measurements, setup, rounds: int = 4) -> float | None:
    """The weight (m/rad) that makes measured orientations count like positions of the same noise:
    ``σ_position / σ_rotation`` of the full geometric model fitted with both, iterated until it
    settles (each fit's robust noise of its position and of its orientation residuals). None when
    no orientation was measured."""
    if orientation_count(data, 1.0) == 0:
        return None
    at = ctx.at(ctx.c)
    at.rot_weight = 1.0
    w = None
    for _ in range(rounds):
        found = _markers_found(at, robot, data, setup)
        p = fit_params(at, warm_start(geometric_start(robot, data, None, setup, turns=True), found), [], data, None,
                       reduce=True)
        prob = effect_problem(at, p, [], data, loss=False)
        r = prob.residual_vectors(p.values[None])[0]
        pos, rot = prob.obs.is_position, ~prob.obs.is_position
        s_pos = robust_sigma(r[pos][prob.obs.mask[pos]], 0)
        s_rot = robust_sigma(r[rot], 0) / at.rot_weight
        if not (s_pos > 0 and s_rot > 0):
            return at.rot_weight
        w_new = s_pos / s_rot
        if w is not None and abs(w_new / w - 1) < 0.1:
            return w_new
        w = at.rot_weight = w_new
    return w


def estimate_noise(ctx: Context, robot, data: Measurements, setup, rounds: int = 3,
                   clean: Measurements | None = None) -> tuple[Context, Model, ParamSet]:
    """The largest identifiable set refitted under Huber until the robust noise estimate
    settles; the first, plain fits on ``clean`` (the rows without gross errors, marked unseen) when
    given. Returns (the context at that threshold, the full-set model, the markers' fit)."""
    plain = ctx if clean is None else replace(ctx, data=clean)
    found = _markers_found(plain, robot, plain.data, setup)
    turns = ctx.rot_weight is not None
    full = lambda: warm_start(geometric_start(robot, data, None, setup, turns), found)  # noqa: E731
    # only the last probe is cross-validated: the rounds before it read its fit's noise alone
    probe = evaluate(plain, "noise probe", full(), [], None, folds=rounds == 0)
    for i in range(rounds):
        sigma = noise_sigma(ctx, probe)
        ctx = ctx.at(HUBER_K * sigma, sigma)
        probe = evaluate(ctx, "noise probe", full(), [], None, folds=i == rounds - 1)
    return ctx, probe, found


def choose_geometry(ctx: Context, robot, data: Measurements, setup, probe: Model, found: ParamSet, say) -> GeometryChoice:
    """Nested sets (each from the best before it), then the full set under priors."""
    n_obs = ctx.n_obs
    out = GeometryChoice(best=None)
    for name, pats in GEOMETRIC_SETS:
        prev = found if out.best is None else out.best.params
        start = geometric_start(robot, data, pats, setup, ctx.rot_weight is not None)
        m = probe if pats is None else evaluate(ctx, name, warm_start(start, prev), [], None)
        m.label = name
        out.fits[name] = m.params
        entry = {"name": name, "n_params": int(round(m.k)), "cv_rmse_mm": m.cv_rmse_mm(n_obs)}
        bad = implausible_values(m.params, robot, ctx.plausible)
        if bad:  # a set that needs a joint moved implausibly far is no model of this robot
            entry.update({"accepted": False, "implausible": bad})
        elif out.best is None:
            entry["accepted"] = True
            out.best = m
        else:
            t, _, ok = compare_at(ctx, out.best, m, n_obs)
            entry.update({"t": t, "accepted": ok})
            if ok:
                out.best = m
        out.sets.append(entry)
        say(f"geometric set {name:<24} {m.k:>5.1f} params  CV {entry['cv_rmse_mm']:.4f} mm"
            + ("" if "t" not in entry else f"  t = {entry['t']:.1f}  {'accepted' if entry['accepted'] else 'rejected'}"))
    full_won = out.best.label == GEOMETRIC_SETS[-1][0]
    if full_won and not is_small(data, len(probe.params.free_names)):
        # enough rows for every parameter the full set fits: a prior would only trade what the data
        # see for what an effect not yet modelled leaves in the residual
        return out
    tried: list[Model] = []
    # every error, under the prior
    start = warm_start(geometric_start(robot, data, None, setup, ctx.rot_weight is not None), out.best.params)
    m = evaluate_prior(ctx, "prior", start, [], PRIOR_SCALES_MM[len(PRIOR_SCALES_MM) // 2], tried=tried)
    m = plausible_scale(ctx, m, tried)
    for mt in sorted(tried, key=lambda x: x.prior_mm):
        name = f"prior {mt.prior_mm:g} mm/mrad"
        out.fits[name] = mt.params
        out.sets.append({"name": name, "n_params": int(mt.params.free.sum()), "k_eff": mt.k,
                         "prior_mm": mt.prior_mm, "cv_rmse_mm": mt.cv_rmse_mm(n_obs),
                         "penalised_mm2": 1e6 * penalised(mt.scores, mt.k, n_obs), "chosen_scale": mt is m})
    m.label = f"prior {m.prior_mm:g} mm/mrad"
    entry = next(g for g in out.sets if g["name"] == m.label)
    bad = implausible_values(m.params, robot, ctx.plausible)
    if bad:
        entry.update({"accepted": False, "implausible": bad})
        how, ok = "moves a joint implausibly far", False
    elif full_won:
        # the same parameters: the prior is a setting of the model, chosen by the penalised CV error
        ok = penalised(m.scores, m.k, n_obs) < penalised(out.best.scores, out.best.k, n_obs)
        entry.update({"accepted": ok, "rule": "same set as the accepted full set: lower penalised CV error"})
        how = "penalised CV error against the full set without a prior"
    else:
        t, _, ok = compare_at(ctx, out.best, m, n_obs)
        entry.update({"t": t, "accepted": ok})
        how = f"t = {t:.1f}"
    say(f"geometric {m.label:<26} (scale chosen by CV among {sorted(x.prior_mm for x in tried)})  k_eff "
        f"{m.k:>5.1f}  CV {m.cv_rmse_mm(n_obs):.4f} mm  {how}  {'accepted' if ok else 'rejected'}")
    if ok:
        out.best = m
    return out


def choose_orientation_weight(ctx: Context, robot, train: Measurements, setup, given: float | None, say
                              ) -> tuple[float | None, dict]:
    """The orientation weight (m/rad) the fits use, and why: ``given``; else, when the rows measure
    orientations, the weight among 0 (positions alone), a tenth of and the estimated
    ``σ_position / σ_rotation`` (:func:`orientation_weight`) whose full geometric model has the lowest
    cross-validated mean *position* error: an orientation is fitted only where it helps to place the
    markers, never because it is there. None when orientations are not used. The record says
    each candidate's CV figure and the rule (report.json's ``geometric_set.orientation``)."""
    n = orientation_count(train, 1.0)
    if given is not None and not (math.isfinite(given) and given >= 0):
        raise ValueError(f"orientation_weight must be a finite number of m/rad, 0 or more, got {given!r}")
    if n == 0:
        if given:
            say("orientation weight given, but the training rows measure no orientation (<marker>.qw/.qx/.qy/.qz)")
        return None, {}
    if given == 0:
        say(f"{n} measured orientations ignored (orientation weight 0, given)")
        return None, {"chosen": 0.0, "rule": "given"}
    if given is not None:
        say(f"{n} measured orientations fitted with the positions: 1 mrad counts like {given:.4g} mm (given)")
        return given, {"chosen": given, "rule": "given"}
    try:
        w = orientation_weight(ctx, robot, train, setup)
    except ValueError as e:  # the orientations drive every parameter out of the fit: they place nothing
        say(f"{n} measured orientations left out: fitted with the positions, they leave no parameter to fit ({e})")
        return None, {"chosen": 0.0, "rule": f"no weight could be estimated: {e}"}
    tried = {}
    for cand in (0.0, w / 10, w):
        at = replace(ctx, rot_weight=cand or None)
        try:
            m = evaluate(at, "orientation weight", geometric_start(robot, train, None, setup, cand > 0), [], None)
        except ValueError:
            continue  # a weight whose fit fails is no choice
        tried[cand] = cv_mean_mm(at, m)
    best = min(tried, key=tried.get)
    words = ", ".join(f"{k:.4g} mm/mrad: {v:.4f} mm" for k, v in tried.items())
    say(f"{n} measured orientations: weight chosen by the cross-validated mean position error of the full geometric "
        f"model ({words}); " + ("positions alone place the markers best: orientations left out" if best == 0 else
                                f"fitted with the positions: 1 mrad counts like {best:.4g} mm"))
    record = {"chosen": best, "estimated": w, "rule": "lowest cross-validated mean position error of the full "
              "geometric model", "tried": [{"weight_mm_per_mrad": k, "cv_mean_mm": v} for k, v in tried.items()]}
    return (best or None), record


# the noise an accepted effect leaves must fall this many times below the one the geometry was chosen
# under before the geometry is judged again: joint origins the rule refused under that much more noise
# (a tool change of centimetres hides them all) may be seen now
AGAIN = 3.0
# times the wider set is fitted again with the joints it moved implausibly far held at their values
HOLDS = 3


def geometry_again(ctx: Context, current: Model, say) -> tuple[Context, Model, dict | None]:
    """The geometry judged again once the accepted effects leave a noise :data:`AGAIN` times below
    the one it was chosen under (``ctx.sigma``): every joint origin, plainly and (on small data)
    under the prior, its scale by CV, each against ``current`` by the rule. The context's noise, which
    scales the priors, becomes the noise now left. Returns the context, the model (``current`` when
    nothing wider passes) and what was judged (None when nothing was)."""
    sigma = noise_sigma(ctx, current)
    if sigma * AGAIN > ctx.sigma:
        return ctx, current, None
    robot, n_obs, n_geo = ctx.robot, ctx.n_obs, ctx.n_geo
    wide = geometric_start(robot, ctx.data, None, ctx.setup, ctx.rot_weight is not None).free
    small = is_small(ctx.data, int(wide.sum()))
    if bool((current.info["candidates"] == wide).all()) and current.prior_mm is None and not small:
        return ctx, current, None  # already every joint origin, plainly: nothing wider to judge
    say(f"the effects leave {1e3 * sigma:.4f} mm of noise, {ctx.sigma / sigma:.0f} times below the "
        f"{1e3 * ctx.sigma:.4f} mm the geometry was chosen under: the geometry is judged again")
    entry = {"sigma_chosen_mm": 1e3 * ctx.sigma, "sigma_now_mm": 1e3 * sigma, "tried": [], "chosen": "as before"}
    ctx = ctx.at(ctx.c, sigma)
    if current.prior_mm is not None:  # its prior now weighs against the noise now left
        current = evaluate_prior(ctx, current.label, current.params, current.effects, current.prior_mm,
                                 info=current.info)
    start = current.params.clone()
    start.free[:n_geo] = wide
    info = dict(current.info, candidates=wide.clone())
    tried = [evaluate(ctx, current.label, start, current.effects, None, info=info)]
    held: list[str] = []
    for _ in range(HOLDS):
        # a joint the wider set moves implausibly far is one these data do not hold (it wanders along
        # a direction they barely see): it keeps the value it had, as a calibration fixes a parameter
        # it cannot pin down, and the others are fitted again; refusing the whole set would leave
        # every joint origin's error to the effects
        bad = implausible_values(tried[-1].params, robot, ctx.plausible)
        if not bad:
            break
        held += list(bad)
        start = start.clone()
        start.fix(*bad)
        info = dict(info, candidates=start.free[:n_geo].clone(), held=list(held))
        tried.append(evaluate(ctx, current.label, start, current.effects, None, info=info))
    if small:  # the prior's fit of what is left free, the held joints held
        tried.append(evaluate_prior(ctx, current.label, start, current.effects,
                                    PRIOR_SCALES_MM[len(PRIOR_SCALES_MM) // 2], info=info))
    best = current
    for m in sorted(tried, key=lambda m: penalised(m.scores, m.k, n_obs)):
        name = "every joint origin" + ("" if m.prior_mm is None else f", prior {m.prior_mm:g} mm/mrad") \
            + (f" but {', '.join(m.info['held'])} (held)" if m.info.get("held") else "")
        bad = implausible_values(m.params, robot, ctx.plausible)
        t, _, ok = compare_at(ctx, best, m, n_obs)
        ok = ok and not bad and best is current
        entry["tried"].append({"name": name, "k_eff": m.k, "cv_rmse_mm": m.cv_rmse_mm(n_obs), "t": t, "accepted": ok})
        say(f"geometry again: {name}  {m.k:>5.1f} params  CV {m.cv_rmse_mm(n_obs):.4f} mm  t = {t:.1f}  "
            f"{'accepted' if ok else 'rejected'}" + (" (moves a joint implausibly far)" if bad else ""))
        if ok:
            best, entry["chosen"] = m, name
    return ctx, best, entry
