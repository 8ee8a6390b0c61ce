"""Evidence for an accepted effect, as a person would check it: per mode, the partial residual
(what the model leaves, plus that mode's own contribution) projected on the mode's displacement,
against the mode's physical signature (gravity torque or moment, direction of approach, joint
angle, temperature), with the fitted mode overlaid. When the effect is real, the points follow
the fitted curve.
"""
from __future__ import annotations

import torch

from torchcal.problems.effect_calibration import EffectCalibrationProblem

__all__ = ["evidence_for", "MAX_PANELS"]

MAX_PANELS = 6


def evidence_for(robot, model, data, setup=None) -> tuple[str, dict]:
    """``(sentence, {mode label: plot data})`` for the last effect of ``model`` on ``data``.

    Plot data per mode: ``x`` (the signature), ``residual`` (partial residual projected on the
    mode's displacement, in the mode's own unit), ``fitted`` (the mode's value), ``r`` (their
    correlation), ``xlabel``, ``ylabel``, ``words``."""
    eff = model.effects[-1]
    full = model.params.values
    a = model.params.names.index(eff.param_names[0]) if eff.param_names else len(full)
    theta = full[a:a + eff.n_params]
    prob = EffectCalibrationProblem(robot, model.params, model.effects, data, setup=setup)
    res = prob.residual_vectors(full[None])[0]
    r = -res  # (n_obs, 3) what the model leaves, in what each observation measures
    p_all = prob.marker_positions(full[None])[0]
    s = full[prob.K:prob.K + prob.S]
    prep = eff.prepare(data.q, data.covariates)
    geo = full[: robot.n_params]
    q_true = prob.joint_values(full[None])[0]
    Jq = robot.joint_jacobian(q_true, geo, check=False)[:, :, :3, :]  # instrument frame
    Rb, _ = robot.base_transform(geo)
    rows = prob.rows
    panels = []
    for label, idx in eff.modes():
        sig = eff.signature(prep, label, theta)
        if sig is None:
            continue
        wo = full.clone()
        wo[[a + i for i in idx]] = 0
        contrib = res - prob.residual_vectors(wo[None])[0]  # the mode's own contribution, as measured
        D = Jq[..., sig["dof"]] if "dof" in sig else (Rb @ sig["G"][..., None])[..., 0]  # (N, M, 3)
        G = prob.obs.project(p_all, D[..., None], s)[..., 0]  # the mode's direction as each observation sees it
        g2 = (G * G).sum(-1)
        use = g2 > 0.01 * float(g2.median()) if bool((g2 > 0).any()) else g2 > 0
        if int(use.sum()) < 3:
            continue
        y = ((r + contrib) * G).sum(-1)[use] / g2[use]
        fitted = sig["fitted"][rows][use]
        x = sig["x"][rows][use]
        c = float(torch.corrcoef(torch.stack([fitted, y]))[0, 1]) if float(fitted.std()) > 0 else float("nan")
        panels.append((float(contrib.norm(dim=-1).mean()), label, {
            "x": x.tolist(), "residual": y.tolist(), "fitted": fitted.tolist(), "r": c, "xlabel": sig["xlabel"],
            "ylabel": sig["ylabel"], "words": eff.mode_words(label), "independent": sig.get("independent", True),
            "note": sig.get("note")}))
    panels.sort(key=lambda t: -t[0])
    out = {label: d for _, label, d in panels[:MAX_PANELS]}
    if not out:
        return "no mode moved the markers enough to plot", out
    best = max(out.items(), key=lambda kv: abs(kv[1]["r"]) if kv[1]["r"] == kv[1]["r"] else -1)
    what, against = best[1]["ylabel"].split(" [")[0], best[1]["xlabel"].split(" [")[0]
    if not best[1]["independent"]:  # a correlation with the fit itself proves nothing: say so
        return (f"{best[1]['words']}: {best[1]['note']}; the partial residual's correlation with the fitted {what} "
                f"(r = {best[1]['r']:.2f}) only says how well it follows the fit", out)
    return (f"{best[1]['words']}: the partial residual follows the fitted {what} against the {against} "
            f"(r = {best[1]['r']:.2f})", out)
