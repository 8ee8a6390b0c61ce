"""Where the session's load changed with nothing logged: the break in time (or the row order) at
which the residual changes as a change of the payload would make it.

A payload swapped mid-session changes every joint's gravity torque, so the deflection of a
compliant joint changes by ``c_j Δτ_j(q)``: a different displacement at every pose, which no
constant step of a parameter explains. Where another set-up change sits in the same session (a
tracker knocked), the step the loop finds first may be that one, and a load tied to it explains
nothing of the swap. So the load's change is found by its own shape: a unit change of the payload's
mass or of one of its first moments moves the markers, through each joint's twist at unit
compliance, by one column each (four per joint that moves the markers; the compliances are not
taken from the fit, whose joints may still miss one), and a change from a break on moves them by
those columns where the driver is past the break. Each break is scored by what its columns explain
together beyond the current model's (χ² with as many degrees of freedom as their rank on noise),
the best kept when that is improbable at :data:`~torchcal.pipelines.loop.screen.ALPHA` shared by
every break scanned (Bonferroni). The load is then only offered:
:class:`~torchcal.effects.compliance.LoadCompliance` fits it and the cross-validated rule judges it.

Scanned only once a compliance with a payload is accepted and where no column logs a load. A load
carried for a while (a change and its return) is not scanned: a window's columns cost the square
of the breaks.
"""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.effects import build_effect
from torchcal.effects.base import TIME_COVARIATES
from torchcal.effects.compliance import load_columns
from torchcal.effects.drivers import ROW
from torchcal.effects.shapes import shape_column, step_breaks
from torchcal.measure.stats import chi2_sf
from torchcal.pipelines.crossval.models import Context, Model, effect_problem, fit_noise
from torchcal.pipelines.loop.screen import ALPHA, _projector, break_sums
from torchcal.pipelines.loop.start import _basis_columns

__all__ = ["load_changes", "step_power"]

MOMENTS = ("m", "mx", "my", "mz")


def _session_columns(data) -> list[str]:
    """The columns a session's order is read from: its time columns, else the row order."""
    times = [c for c in TIME_COVARIATES if c in data.covariates]
    return times or ([ROW] if ROW in data.covariates else [])


def _payload_fitted(current: Model) -> bool:
    """Whether an accepted compliance fitted a payload (its four mass moments, from link inertials)."""
    return any(getattr(e, "has_payload", False) and not getattr(e, "lumped", True)
               and all(f"{e.name}.payload.{k}" in current.params.names for k in MOMENTS) for e in current.effects)


def step_power(G: Tensor, x: Tensor, at: Tensor, Q: Tensor, rp: Tensor) -> tuple[Tensor, Tensor]:
    """What a step of the columns ``G (3 n_obs, P)`` at each break ``at (B,)`` (increasing) explains
    beyond ``Q (3 n_obs, r)`` (orthonormal) of the residual ``rp (3 n_obs,)`` (orthogonal to ``Q``),
    all ``P`` columns at once, and their rank per break: ``(B,)`` each. ``x (3 n_obs,)`` is the
    driver's value at each residual component; a step's columns are ``G`` where ``x ≥`` its break.
    The products come from cumulative sums in the driver's order, so every break costs ``P² + P r``."""
    from_break = break_sums(x, at)
    M = from_break(G[:, :, None] * Q[:, None, :])  # (B, P, r)
    A = from_break(G[:, :, None] * G[:, None, :]) - M @ M.mT  # (B, P, P): the projected columns' products
    u = from_break(G * rp[:, None])  # (B, P)
    # each break's columns normalised, so the rank cut is relative to each column's own size
    d = A.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
    s = torch.where(d > 0, 1.0 / d.clamp(min=1e-300), torch.zeros_like(d))
    An = A * s[:, :, None] * s[:, None, :]
    un = u * s
    ev, V = torch.linalg.eigh(An)
    keep = ev > ev.amax(-1, keepdim=True).clamp(min=0) * 1e-8
    proj = (V.mT @ un[..., None])[..., 0]
    power = torch.where(keep, proj * proj / ev.clamp(min=1e-300), torch.zeros_like(ev)).sum(-1)
    return power, keep.sum(-1)


def _moment_columns(ctx: Context, prob) -> Tensor:
    """``(3 n_obs, 4 J)``: what a unit change of the payload's mass and first moments moves the
    markers by through each joint's twist at unit compliance (every joint that moves the markers, each
    compliance unknown), in the observations' residuals of ``prob``."""
    geo = prob.params.values[: ctx.robot.n_params]
    full = build_effect("joint_compliance", ctx.robot, ctx.data, geometry=geo)
    if getattr(full, "lumped", True) or not full.has_payload:
        return prob.params.values.new_zeros(3 * prob.n_obs, 0)
    cols, groups, _ = _basis_columns(ctx, prob, full)
    return cols[:, [i for g in groups for i in g[1:1 + len(MOMENTS)]]]


def load_changes(ctx: Context, current: Model, known: list[str] = ()) -> list[str]:
    """The load change the residual of ``current`` shows (module docstring), as a load of
    :class:`~torchcal.effects.compliance.LoadCompliance` (``<column>~step<b>``); none where no accepted
    compliance fitted a payload, where a column logs the load, where the session has no order, or
    where nothing passes. ``known``: loads already offered (steps an accepted effect found), whose
    columns are taken out first."""
    data = ctx.data
    cols = _session_columns(data)
    if not _payload_fitted(current) or not cols or load_columns(data.covariates):
        return []
    prob = effect_problem(ctx, current.params, current.effects, data)
    x = prob.x0
    w3 = prob.observation_weights(x).repeat_interleave(3)
    G = _moment_columns(ctx, prob) * w3[:, None]
    if not G.shape[1]:
        return []
    rows = prob.rows
    extra = [G * shape_column(t, data.covariates[c][rows].to(G), 0.0, 1.0).repeat_interleave(3)[:, None]
             for c, _, t in (k.partition("~") for k in known) if c in data.covariates]
    Q = _projector(torch.cat([prob.data_jacobian(x) * w3[:, None], *extra], 1), torch.ones_like(w3))
    r = prob.residual_vectors(current.params.values[None])[0]  # (n_obs, 3)
    if ctx.c is not None:  # Huber's pseudo-observations, as the screening reads them
        n = r.norm(dim=-1, keepdim=True)
        r = r * torch.where(n > ctx.c, ctx.c / n.clamp(min=1e-300), torch.ones_like(n))
    rw = r.reshape(-1) * w3
    rp = rw - Q @ (Q.T @ rw)
    sigma = fit_noise(prob, x)
    best, n_tested = None, 0
    for c in cols:
        v = data.covariates[c]
        b = step_breaks(v[torch.isfinite(v)])
        if not b:
            continue
        power, rank = step_power(G, v[rows].to(G).repeat_interleave(3), torch.tensor(b, dtype=G.dtype, device=G.device),
                                 Q, rp)
        n_tested += len(b)
        i = int(power.argmax())
        if best is None or float(power[i]) > best[0]:
            best = (float(power[i]), int(rank[i]), f"{c}~step{b[i]:.10g}")
    if best is None or sigma <= 0 or best[1] == 0 or n_tested * chi2_sf(best[0] / sigma ** 2, best[1]) >= ALPHA:
        return []
    return [best[2]] if best[2] not in known else []
