"""The loop with measured data: calibrate, read the residual, trace it to the physical effect the
model lacks, add it, and report held-out error before and after.

Every decision (which geometric parameters, which effect, whether the residual ELM helps) is
made on the training data alone, by K-fold cross-validation. The held-out ``test`` data never
steers anything: it is only measured.

Acceptance rule (stated once, used for every decision). Adding something to the model is
accepted when, on the cross-validated per-row squared errors (sum over the row's markers),
(1) the mean improvement is significant: a paired one-sided t statistic ``t > T_ACCEPT`` (3.0,
about p < 0.002 for the sample sizes here), and (2) the penalised cross-validated error falls:
``MSE_cv · (1 + 2k / n_obs)`` with ``k`` the free parameters (an AIC-like penalty on what it adds).
The diagnosis repeats, with accepted effects kept, until no candidate passes.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from .effects import EFFECTS, build_effect, effect_params
from .fitting import fit_identified
from .io import Measurements
from .params import ParamSet
from .problem import EffectCalibrationProblem
from .registration import register_base
from .report import error_stats, write_json

__all__ = ["run_loop", "LoopResult", "T_ACCEPT", "GEOMETRIC_SETS"]

T_ACCEPT = 3.0

# Nested geometric parameter sets, smallest first: (name, glob patterns, or None for the robot's
# default free set: every origin / DH error). Markers' positions are always free.
GEOMETRIC_SETS = [
    ("base+markers", ["base.*"]),
    ("+joint offsets", ["base.*", "*.offset", "*.dtheta"]),
    ("+joint origins", None),
]
# When CV rejects the full set (small data), the full set is also tried with a ridge on every
# non-base error: prior residuals sqrt(λ/N)·e per row-normalised error, with λ = c · SSE_cv /
# (1 mm)² so that a 1 mm (or 1 mrad at 1 m) error costs the fraction c of the best CV misfit.
RIDGE_FRACTIONS = (0.01, 0.1, 1.0)


@dataclass
class Candidate:
    name: str
    n_params: int
    cv_rmse_mm: float
    cv_gain_mm: float
    t: float
    accepted: bool
    round: int
    penalised_ok: bool
    reason: str = ""


@dataclass
class LoopResult:
    """Outcome of :func:`run_loop`; :meth:`report` has the JSON shape of ``report.json``."""

    robot: object
    params: ParamSet                  # geometry + accepted effects, fitted on all training rows
    effects: list                     # accepted Effect objects with fitted theta
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

    def report(self) -> dict:
        return {"robot": self.robot.name, "n_train": self.n_train, "n_test": self.n_test,
                "noise_floor_mm": self.noise_floor_mm, "stages": self.stages, "effects": self.accepted,
                "candidates": self.candidates, "geometric_set": self.geometric,
                "rule": f"accept when the paired t statistic of the cross-validated per-row squared-error "
                        f"improvement exceeds {T_ACCEPT} and MSE_cv*(1+2k/n_obs) decreases",
                "residual_elm": self.elm is not None, "timings_s": self.timings}

    def model(self):
        """A deployable :class:`~torchcal.model.CalibratedModel`."""
        from .model import CalibratedModel

        geo = self.robot.params(self.params.values[: self.robot.n_params])
        geo.free = self.params.free[: self.robot.n_params].clone()
        residual = self.elm
        if residual is not None and residual.n_outputs_ != 3:
            raise ValueError("the residual ELM predicts several markers at once; a deployable model holds a "
                             "residual for one marker: run the loop with that marker only")
        return CalibratedModel(self.robot, geo, effects=list(self.effects), residual=residual,
                               covariates=self.elm_covariates if residual is not None else None,
                               meta={"report": self.report()})


# ----------------------------------------------------------------------------- fitting pieces
def _folds(n: int, k: int, seed: int) -> list[Tensor]:
    g = torch.Generator().manual_seed(seed)
    perm = torch.randperm(n, generator=g)
    return [perm[i::k].sort().values for i in range(k)]


def _geometric_start(robot, data: Measurements, patterns) -> ParamSet:
    p = robot.params()
    for m in robot.marker_names:
        if m not in data.marker_names:
            p.fix(f"{m}.*")
        p.fix(f"{m}.droll", f"{m}.dpitch", f"{m}.dyaw")
    if patterns is not None:
        keep = set(p.free_names)
        p.free[:] = False
        for pat in patterns:
            try:
                p.unfix(pat)
            except KeyError:
                pass
        for m in data.marker_names:
            p.unfix(f"{m}.dx", f"{m}.dy", f"{m}.dz")
        p.free &= torch.tensor([n in keep for n in p.names], device=p.free.device)
    return register_base(robot, data, p)


def _fit(robot, data: Measurements, geo: ParamSet, effects: list, start: ParamSet | None = None,
         ridge: float = 0.0) -> ParamSet:
    """Geometry + effects fitted on ``data`` by LM. Without ``start``: the identifiable subset of
    ``geo``'s free entries and all effect parameters, judged as in :func:`fit_identified`. With
    ``start`` (a fit of the same model on a superset of the rows): its free set and values are
    the start, with no new identifiability analysis — what the cross-validation folds use."""
    if start is not None:
        ps = start.clone()
        make = lambda p: EffectCalibrationProblem(robot, p, effects, data, ridge=ridge * len(data))  # noqa: E731
        # ridge is per row, so a fold of fewer rows gets a proportionally weaker prior
        ps, _, _ = fit_identified(make, ps, reduce=False, options={"max_iter": 100, "tau": 1e-6})
        return ps
    ps = ParamSet.concat(geo.clone(), effect_params(effects, data))
    ps, _, _ = fit_identified(lambda p: EffectCalibrationProblem(robot, p, effects, data, ridge=ridge * len(data)), ps,
                              markers=robot.marker_names, options={"max_iter": 200, "tau": 1e-6})
    return ps


def _row_sq_errors(robot, params: ParamSet, effects: list, data: Measurements) -> tuple[Tensor, Tensor]:
    """Per-observation errors (m) and per-row squared errors (m²) of a fitted model."""
    prob = EffectCalibrationProblem(robot, params, effects, data)
    e = prob.errors(params.values[None])[0]
    rows = prob._rows
    sq = torch.zeros(len(data), dtype=e.dtype, device=e.device).index_add_(0, rows, e * e)
    return e, sq


def _residuals(robot, params: ParamSet, effects: list, data: Measurements) -> Tensor:
    """``(N, 3M)`` measured − model position per row (NaN where a marker was not seen)."""
    prob = EffectCalibrationProblem(robot, params, effects, data)
    p, _ = prob._positions(params.values[None])
    out = torch.full((len(data), len(data.marker_names), 3), float("nan"), dtype=p.dtype, device=p.device)
    out[prob._rows, prob.obs_cols_measured] = prob._meas - p[0]
    return out.reshape(len(data), -1)


def _cv(robot, data: Measurements, geo_patterns, effects: list, folds: list[Tensor], ridge: float = 0.0,
        geo_free: Tensor | None = None):
    """Cross-validated per-row squared errors (m²), the per-fold fitted models, and the fit on
    all rows (which the folds start from: identifiable set and values).

    ``geo_free``: the geometric stage's identifiable set, kept when effects are tried. An effect
    must not make geometric errors "identifiable" through itself (thermal scaling sees a base
    rotation at 2e-4 of its size): those fits crawl along flat valleys and mean nothing."""
    geo = _geometric_start(robot, data, geo_patterns)
    if geo_free is not None:
        geo.free &= geo_free
    full = _fit(robot, data, geo, effects, ridge=ridge)
    sq = torch.zeros(len(data), dtype=robot.dtype, device=robot.device)
    fits = []
    for f in folds:
        mask = torch.ones(len(data), dtype=torch.bool)
        mask[f] = False
        tr, va = data.subset(mask), data.subset(f)
        p = _fit(robot, tr, None, effects, start=full, ridge=ridge)
        _, s = _row_sq_errors(robot, p, effects, va)
        sq[f] = s
        fits.append(p)
    return sq, fits, full


def _compare(sq_old: Tensor, sq_new: Tensor, k_old: int, k_new: int, n_obs: int) -> tuple[float, float, bool]:
    d = sq_old - sq_new
    n = d.numel()
    sd = float(d.std()) if n > 1 else 0.0
    t = float(d.mean()) / (sd / math.sqrt(n)) if sd > 0 else (math.inf if float(d.mean()) > 0 else 0.0)
    pen_old = float(sq_old.mean()) * (1 + 2 * k_old / n_obs)
    pen_new = float(sq_new.mean()) * (1 + 2 * k_new / n_obs)
    return t, pen_new < pen_old, t > T_ACCEPT and pen_new < pen_old


def _rmse_mm(sq_rows: Tensor, n_obs: int) -> float:
    return 1e3 * math.sqrt(float(sq_rows.sum()) / max(n_obs, 1))


def _stats(robot, params, effects, data, elm=None) -> tuple[dict | None, Tensor]:
    """Error statistics (mm), overall and per marker, and the per-observation errors (m)."""
    if data is None or len(data) == 0:
        return None, torch.zeros(0)
    prob = EffectCalibrationProblem(robot, params, effects, data)
    e = prob.errors(params.values[None])[0]
    cols = prob.obs_cols_measured
    if elm is not None:
        r = _residuals(robot, params, effects, data)
        pred = elm.predict(_elm_inputs(data))
        left = (r - pred).reshape(len(data), -1, 3)
        seen = ~torch.isnan(left).any(-1)
        e = left[seen].norm(dim=-1)
        cols = torch.nonzero(seen)[:, 1]
    out = error_stats(e)
    out["per_marker"] = {m: error_stats(e[cols == k]) for k, m in enumerate(data.marker_names) if bool((cols == k).any())}
    return out, e


def _elm_covariates(data: Measurements) -> list[str]:
    """Covariates the residual ELM reads after the commands: temperatures and directions."""
    return [k for k in sorted(data.covariates) if k.startswith(("temp", "dir."))]


def _elm_inputs(data: Measurements) -> Tensor:
    return torch.cat([data.q] + [data.covariates[k][:, None] for k in _elm_covariates(data)], 1)


def _elm_cv(robot, data, params_folds, effects, folds, n_hidden: int, ridge: float, seed: int) -> Tensor:
    from .elm import ELM

    sq = torch.zeros(len(data), dtype=robot.dtype, device=robot.device)
    for f, p in zip(folds, params_folds):
        mask = torch.ones(len(data), dtype=torch.bool)
        mask[f] = False
        tr, va = data.subset(mask), data.subset(f)
        r_tr = torch.nan_to_num(_residuals(robot, p, effects, tr))
        elm = ELM(n_hidden=n_hidden, ridge=ridge, seed=seed).fit(_elm_inputs(tr), r_tr)
        left = (_residuals(robot, p, effects, va) - elm.predict(_elm_inputs(va))).reshape(len(va), -1, 3)
        sq[f] = torch.nan_to_num((left * left).sum(-1)).sum(-1)
    return sq


def _evidence(robot, params: ParamSet, effect, effects_before: list, data: Measurements) -> tuple[str, dict]:
    """The residual of the model *without* ``effect`` projected on joint space (per row, minimum
    norm), against the effect's own signature: the numbers a person would check."""
    K = robot.n_params
    geo = params.values[:K]
    r = torch.nan_to_num(_residuals(robot, _without(params, effect, effects_before), effects_before, data))  # (N, 3M)
    if effect.kind == "position":
        prep = effect.prepare(data.q, data.covariates)
        pr = robot.positions(data.q, geo, base=False, check=False)  # robot-base positions
        Rb, _ = robot.base_transform(geo)
        radial = torch.einsum("nmi,nmi->n", (r.reshape(len(data), -1, 3) @ Rb), pr) / pr.norm(dim=-1).sum(-1)
        x = prep.features["dT"]
        c = float(torch.corrcoef(torch.stack([x, radial]))[0, 1])
        return (f"residual along the base-to-marker direction correlates with {effect.covariate} (r = {c:.2f})",
                {"all": {"x": x.tolist(), "residual": (radial * 1e3).tolist(), "r": c,
                         "xlabel": f"{effect.covariate} − mean", "ylabel": "radial residual [mm]"}})
    J = robot.joint_jacobian(data.q, geo, check=False)[:, :, :3, :]  # (N, M, 3, dof)
    mk = [robot.marker_names.index(m) for m in data.marker_names]
    J = J[:, mk].reshape(len(data), -1, robot.dof)
    dq = (torch.linalg.pinv(J) @ r[..., None])[..., 0]  # (N, dof) rad
    a = params.names.index(effect.param_names[0])
    theta = params.values[a:a + effect.n_params]
    effect.theta = theta.clone()
    pred = effect.joint_delta(theta[None], effect.prepare(data.q, data.covariates))[0]  # (N, dof)
    prep = effect.prepare(data.q, data.covariates)
    xsig = _signature_x(effect, data, prep)  # (N, dof) what a person plots the residual against
    best, out = None, {}
    for j in effect.joints:
        i = robot.joint_names.index(j)
        if float(pred[:, i].std()) == 0:
            continue
        c = float(torch.corrcoef(torch.stack([pred[:, i], dq[:, i]]))[0, 1])
        out[j] = {"x": xsig[:, i].tolist(), "fitted": pred[:, i].tolist(), "residual": dq[:, i].tolist(), "r": c}
        if best is None or abs(c) > abs(best[1]):
            best = (j, c)
    sig = {"joint_compliance": "gravity-torque deflection", "backlash": "direction of the last motion",
           "cyclic_joint_error": "harmonics of the joint angle", "joint_scale": "joint angle"}.get(effect.name, "signature")
    if best is None:
        return "no joint moved the signature", out
    return (f"residual projected on joint {best[0]} correlates with the fitted {sig} (r = {best[1]:.2f})", out)


# x axis of the evidence plot per effect: (label, unit)
SIGNATURE_AXIS = {"joint_compliance": ("gravity torque", "N·m"), "backlash": ("direction of the last motion", "±1"),
                  "cyclic_joint_error": ("joint angle", "rad"), "joint_scale": ("joint angle", "rad")}


def _signature_x(effect, data: Measurements, prep) -> Tensor:
    """``(N, dof)`` the physical signature of a joint effect per joint: gravity torque for
    compliance (URDF inertials), direction for backlash, the joint angle otherwise."""
    if effect.name == "joint_compliance" and not effect.lumped:
        tau = effect.torques(data.q, data.covariates)
        return effect._scatter(tau[None])[0]
    if effect.name == "backlash":
        return effect._scatter(prep.features["dir"][None])[0]
    return data.q


def _without(params: ParamSet, effect, effects_before: list) -> ParamSet:
    names = [n for e in effects_before for n in e.param_names]
    keep = list(range(len(params) - len(names) - effect.n_params)) + [params.names.index(n) for n in names]
    return ParamSet([params.names[i] for i in keep], [params.units[i] for i in keep], params.values[keep],
                    params.free[keep], params.lower[keep], params.upper[keep])


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


# ----------------------------------------------------------------------------- the loop
def run_loop(robot, train: Measurements, test: Measurements | None = None, *, candidates: list[str] | None = None,
             folds: int = 5, seed: int = 0, elm: bool = True, elm_hidden: int | None = None,
             noise_mm: float | None = None, progress: bool = False, log=print) -> LoopResult:
    """Base registration → geometric calibration (parameter set chosen by CV) → diagnosis and
    effects → residual ELM (kept only when it helps in CV) → final fit on all training rows.

    Args:
        candidates: effect names to consider (default: every effect in
            :data:`torchcal.effects.EFFECTS` that the data allows).
        folds: K of the K-fold cross-validation on the training rows.
        noise_mm: instrument noise (mean Euclidean error a perfect model would leave, mm) for the
            report; default: the median of a ``marker_std_mm`` covariate when the data has one.
        log: a print-like function for progress lines (``None`` to stay quiet).
    """
    t0 = time.perf_counter()
    say = log or (lambda *a, **k: None)
    derived = derive_directions(train)
    if derived is not None:
        if test is not None:
            derive_directions(test)
        say(f"no direction columns: derived dir.<joint> from the time order of '{derived}' (for backlash)")
    timings: dict[str, float] = {}
    n_obs = int(train.seen.sum())
    fl = _folds(len(train), min(folds, len(train)), seed)

    # 1. nominal: base registration only
    geo0 = _geometric_start(robot, train, GEOMETRIC_SETS[0][1])  # base registration only
    nominal = ParamSet.concat(geo0, effect_params([], train))
    stages = []
    st_tr, e_tr = _stats(robot, nominal, [], train)
    st_te, e_te = _stats(robot, nominal, [], test)
    stages.append(_stage("nominal", 0, st_tr, st_te))
    errors = {"nominal": {"train": e_tr, "test": e_te}}
    timings["nominal"] = time.perf_counter() - t0

    # 2. geometric parameter set by CV (nested sets, the acceptance rule between neighbours)
    t1 = time.perf_counter()
    geo_choice, geo_fits = [], {}
    best_sq, best_fits, best_set, best_k = None, None, None, 0
    for name, pats in GEOMETRIC_SETS:
        sq, fits, full = _cv(robot, train, pats, [], fl)
        geo_fits[name] = full
        k = int(full.free.sum())
        entry = {"name": name, "n_params": k, "cv_rmse_mm": _rmse_mm(sq, n_obs)}
        if best_sq is None:
            entry["accepted"] = True
            best_sq, best_fits, best_set, best_k, best_full = sq, fits, (name, pats, 0.0), k, full
        else:
            t, pen_ok, ok = _compare(best_sq, sq, best_k, k, n_obs)
            entry.update({"t": t, "accepted": ok})
            if ok:
                best_sq, best_fits, best_set, best_k, best_full = sq, fits, (name, pats, 0.0), k, full
        geo_choice.append(entry)
        say(f"geometric set {name:<22} {k:>3} params  CV RMSE {entry['cv_rmse_mm']:.4f} mm"
            + ("" if "t" not in entry else f"  t = {entry['t']:.1f}  {'accepted' if entry['accepted'] else 'rejected'}"))
    if best_set[1] is not None:  # the full set lost: try it regularised
        sse = float(best_sq.sum())
        for c in RIDGE_FRACTIONS:
            ridge = c * sse / 1e-6 / len(train)  # per row
            sq, fits, full = _cv(robot, train, None, [], fl, ridge=ridge)
            geo_fits[f"+joint origins, ridge c={c:g}"] = full
            k = int(full.free.sum())
            t, pen_ok, ok = _compare(best_sq, sq, best_k, best_k, n_obs)  # shrunk: counts as no new parameter
            name = f"+joint origins, ridge c={c:g}"
            entry = {"name": name, "n_params": k, "ridge_per_row": ridge, "cv_rmse_mm": _rmse_mm(sq, n_obs), "t": t,
                     "accepted": ok}
            geo_choice.append(entry)
            say(f"geometric set {name:<22} {k:>3} params  CV RMSE {entry['cv_rmse_mm']:.4f} mm  t = {t:.1f}  "
                f"{'accepted' if ok else 'rejected'}")
            if ok:
                best_sq, best_fits, best_set, best_full = sq, fits, (name, None, ridge), full
    geo_patterns, geo_ridge = best_set[1], best_set[2]
    params = best_full
    geo_free = best_full.free[: robot.n_params].clone()
    st_tr, e_tr = _stats(robot, params, [], train)
    st_te, e_te = _stats(robot, params, [], test)
    stages.append(_stage("geometric", int(params.free.sum()), st_tr, st_te, _rmse_mm(best_sq, n_obs)))
    errors["geometric"] = {"train": e_tr, "test": e_te}
    timings["geometric"] = time.perf_counter() - t1

    # 3. diagnosis: add effects while one passes the rule
    t2 = time.perf_counter()
    names = candidates if candidates is not None else list(EFFECTS)
    pool = []
    cand_report = []
    for n in names:
        eff = build_effect(n, robot, train)
        ok, why = eff.applicable(train)
        if not ok or eff.n_params == 0:
            cand_report.append({"name": n, "accepted": False, "applicable": False, "reason": why or "no parameters"})
            continue
        pool.append(n)
    accepted_effects, accepted, stage_fits = [], [], []
    cur_sq, cur_fits, cur_k, cur_full = best_sq, best_fits, best_k, best_full
    rnd = 0
    while pool:
        rnd += 1
        results = []
        for n in pool:
            eff = build_effect(n, robot, train)
            trial = accepted_effects + [eff]
            sq, fits, full = _cv(robot, train, geo_patterns, trial, fl, ridge=geo_ridge, geo_free=geo_free)
            k = int(full.free.sum())
            t, pen_ok, ok = _compare(cur_sq, sq, cur_k, k, n_obs)
            gain = _rmse_mm(cur_sq, n_obs) - _rmse_mm(sq, n_obs)
            results.append((ok, t, n, sq, fits, k, gain, pen_ok, full, eff))
            say(f"round {rnd}: {n:<20} {k:>3} params  CV RMSE {_rmse_mm(sq, n_obs):.4f} mm  gain {gain:+.4f} mm  "
                f"t = {t:.1f}")
        # among candidates that pass, the one with the lowest penalised CV error wins (t only
        # says an improvement is real; a look-alike effect can have a similar t and a smaller gain)
        results.sort(key=lambda r: (r[0], -float(r[3].mean()) * (1 + 2 * r[5] / n_obs) if r[0] else r[1]),
                     reverse=True)
        ok, t, n, sq, fits, k, gain, pen_ok, full, eff = results[0]
        for r_ in results:
            # measured on the held-out rows after the decision, for the report only
            test_gain = None
            if test is not None:
                cur_te, _ = _stats(robot, cur_full, accepted_effects, test)
                cand_te, _ = _stats(robot, r_[8], accepted_effects + [r_[9]], test)
                test_gain = cur_te["mean_mm"] - cand_te["mean_mm"]
            cand_report.append({"name": r_[2], "round": rnd, "n_params": r_[5], "cv_rmse_mm": _rmse_mm(r_[3], n_obs),
                                "cv_gain_mm": r_[6], "t": r_[1], "penalised_ok": r_[7], "test_gain_mm": test_gain,
                                "accepted": bool(r_[0] and r_[2] == n)})
        if not ok:
            break
        accepted_effects.append(eff)
        stage_fits.append(full)
        cur_sq, cur_fits, cur_k, cur_full = sq, fits, k, full
        pool.remove(n)
        say(f"accepted {n}")
    timings["diagnosis"] = time.perf_counter() - t2

    # final fit with the accepted effects, stage by stage (each stage adds one effect)
    params_by_stage = []
    prev_params = params
    for i, eff in enumerate(accepted_effects):
        effs = accepted_effects[: i + 1]
        p = stage_fits[i]
        for e in effs:  # copy fitted values into the effect objects
            a = p.names.index(e.param_names[0])
            e.theta = p.values[a:a + e.n_params].clone()
        st_tr, e_tr = _stats(robot, p, effs, train)
        st_te, e_te = _stats(robot, p, effs, test)
        gain_test = None
        if st_te is not None and stages[-1].get("test"):
            gain_test = stages[-1]["test"]["mean_mm"] - st_te["mean_mm"]
        ev_text, ev_data = _evidence(robot, p, eff, effs[:-1], train)
        accepted.append({"name": eff.name, "joints": list(eff.joints), "n_params": eff.n_params,
                         "cv_gain_mm": next(c["cv_gain_mm"] for c in cand_report if c.get("accepted") and c["name"] == eff.name),
                         "test_gain_mm": gain_test, "evidence": ev_text,
                         "params": {n: float(v) for n, v, f in zip(p.names, p.values.tolist(), p.free.tolist())
                                    if n.startswith(eff.name + ".") and f},
                         "units": {n: u for n, u in zip(eff.param_names, eff.param_units)}})
        stages.append(_stage(f"+{eff.name}", int(p.free.sum()), st_tr, st_te))
        errors[f"+{eff.name}"] = {"train": e_tr, "test": e_te}
        params_by_stage.append((p, ev_data))
        prev_params = p
    params = prev_params
    evidence = {eff.name: ev for eff, (_, ev) in zip(accepted_effects, params_by_stage)}

    # 4. residual ELM: kept only when it passes the same rule in CV
    t3 = time.perf_counter()
    elm_model = None
    if elm and len(train) >= 20:
        from .elm import ELM

        H = elm_hidden or max(8, min(64, len(train) // 4))
        sq_elm = _elm_cv(robot, train, cur_fits, accepted_effects, fl, H, 1e-3, seed)
        k_elm = H * 3 * len(train.marker_names)
        t, pen_ok, ok = _compare(cur_sq, sq_elm, cur_k, cur_k + k_elm, n_obs)
        gain = _rmse_mm(cur_sq, n_obs) - _rmse_mm(sq_elm, n_obs)
        cand_report.append({"name": "residual_elm", "n_params": k_elm, "cv_rmse_mm": _rmse_mm(sq_elm, n_obs),
                            "cv_gain_mm": gain, "t": t, "penalised_ok": pen_ok, "accepted": ok})
        say(f"residual ELM ({H} hidden): CV RMSE {_rmse_mm(sq_elm, n_obs):.4f} mm  gain {gain:+.4f} mm  t = {t:.1f}"
            f"  {'kept' if ok else 'not kept'}")
        if ok:
            r = torch.nan_to_num(_residuals(robot, params, accepted_effects, train))
            elm_model = ELM(n_hidden=H, ridge=1e-3, seed=seed).fit(_elm_inputs(train), r)
            st_tr, e_tr = _stats(robot, params, accepted_effects, train, elm_model)
            st_te, e_te = _stats(robot, params, accepted_effects, test, elm_model)
            stages.append(_stage("+residual_elm", int(params.free.sum()) + k_elm, st_tr, st_te))
            errors["+residual_elm"] = {"train": e_tr, "test": e_te}
    timings["residual_elm"] = time.perf_counter() - t3
    timings["total"] = time.perf_counter() - t0

    if noise_mm is None and "marker_std_mm" in train.covariates:
        noise_mm = float(train.covariates["marker_std_mm"].median())
    return LoopResult(robot=robot, params=params, effects=accepted_effects, elm=elm_model, stages=stages,
                      accepted=accepted, candidates=cand_report, geometric={"chosen": best_set[0], "sets": geo_choice},
                      n_train=len(train), n_test=0 if test is None else len(test), noise_floor_mm=noise_mm,
                      timings=timings, errors=errors, evidence=evidence, elm_covariates=_elm_covariates(train),
                      geometric_fits=geo_fits)


def _stage(name: str, k: int, train: dict | None, test: dict | None, cv_rmse_mm: float | None = None) -> dict:
    s = {"name": name, "n_params": k, "train": train}
    if test is not None:
        s["test"] = test
    if cv_rmse_mm is not None:
        s["cv_rmse_mm"] = cv_rmse_mm
    return s
