"""Plausible sizes of a robot's geometric errors, and the judgements made against them: a parameter
the data pin down worse than its plausible size is not identified by them (imprecise), and a
fitted error larger than it is no model of the robot (implausible). Both say why in words."""
from __future__ import annotations

import torch
from torch import Tensor

from torchcal.advice import advice
from torchcal.params import ParamSet, display_unit
from torchcal.problems.uncertainty import unit_variances

__all__ = ["PLAUSIBLE", "check_plausible", "drop_imprecise", "imprecise", "imprecise_reason", "implausible_values",
           "implausible_reason"]

# Plausible size of a geometric error (per unit): a parameter the data pin down only to worse
# than this (one standard error) is not identified by them, whatever its numerical rank. A marker
# a few micrometres off a joint axis makes that joint's offset full-rank and meaningless.
PLAUSIBLE = {"m": 0.01, "rad": 0.01}


def check_plausible(plausible: dict | None) -> dict:
    """``plausible`` as a dict unit -> largest plausible error (default :data:`PLAUSIBLE`), or an
    error that says what is wrong."""
    if plausible is None:
        return dict(PLAUSIBLE)
    if not isinstance(plausible, dict):
        raise TypeError(f"plausible must be a dict unit -> size, e.g. {PLAUSIBLE}, got {type(plausible).__name__}")
    bad = [u for u in plausible if u not in PLAUSIBLE]
    if bad:
        raise ValueError(f"plausible: unknown unit(s) {bad}; geometric errors are in {sorted(PLAUSIBLE)} "
                         "(metres and radians), e.g. {'m': 0.01, 'rad': 0.01}")
    neg = {u: v for u, v in plausible.items() if not (isinstance(v, (int, float)) and v > 0)}
    if neg:
        raise ValueError(f"plausible: sizes must be positive numbers (m or rad; inf for no limit), got {neg}")
    return {u: float(v) for u, v in plausible.items()}


def drop_imprecise(J: Tensor, keep: Tensor, limit: Tensor, noise: Tensor) -> tuple[Tensor, Tensor]:
    """Among each problem's ``keep`` columns, drop the one whose standard error
    ``noise · sqrt((JᵀJ)⁻¹_ii)`` exceeds its ``limit`` by the largest factor, and repeat while any
    does (each drop makes the others better determined). Batched over problems (a fleet).

    The inverse over the kept columns comes once from a QR factor
    (:func:`~torchcal.problems.uncertainty.unit_variances`); dropping column ``j`` then updates it
    by ``H − H e_j e_jᵀ H / H_jj``, the inverse of the Gram matrix without ``j``.

    Args:
        J: ``(B, m, k)`` Jacobians (m per unit); keep: ``(B, k)`` bool, full column rank;
        limit: ``(k,)`` plausible sizes (inf: none); noise: ``(B,)`` per-axis noise (m).
    Returns:
        ``(step (B, k) long: the round in which a column was dropped, −1 for the others;
        standard errors (B, k) when dropped)``.
    """
    keep = keep.clone()
    B, k = keep.shape
    step = torch.full((B, k), -1, dtype=torch.long, device=keep.device)
    se_at = J.new_zeros(B, k)
    s = J.norm(dim=1).clamp(min=1e-300)
    An = J / s[:, None, :]
    H = unit_variances(An, keep, full=True)  # (B, k, k) inverse Gram over the kept columns
    rows = torch.arange(B, device=keep.device)
    for t in range(k):
        se = noise[:, None] * H.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt() / s
        ratio = torch.where(keep, se / limit, torch.full_like(se, -1.0))
        worst_ratio, worst = ratio.max(-1)
        hit = worst_ratio > 1
        if not bool(hit.any()):
            break
        r, j = rows[hit], worst[hit]
        step[r, j] = t
        se_at[r, j] = se[hit, j]
        keep[r, j] = False
        h = H[r, :, j]
        H[r] = H[r] - h[:, :, None] * h[:, None, :] / h[torch.arange(r.numel()), j][:, None, None]
    return step, se_at


def imprecise(J, names: list[str], units: list[str], noise: float, plausible: dict | None = None) -> dict[str, float]:
    """Parameters whose standard error ``noise · sqrt((JᵀJ)⁻¹_ii)`` exceeds their plausible size,
    dropped worst first (:func:`drop_imprecise`): name -> standard error, in the order dropped."""
    plausible = PLAUSIBLE if plausible is None else plausible
    J = torch.as_tensor(J)
    lim = torch.tensor([plausible.get(u, float("inf")) for u in units], dtype=J.dtype, device=J.device)
    keep = torch.ones(1, len(names), dtype=torch.bool, device=J.device)
    step, se = drop_imprecise(J[None], keep, lim, torch.tensor([float(noise)], dtype=J.dtype, device=J.device))
    order = sorted((t, i) for i, t in enumerate(step[0].tolist()) if t >= 0)
    return {names[i]: float(se[0, i]) for _, i in order}


def imprecise_reason(name: str, unit: str, se: float, noise: float) -> str:
    """Why a parameter of full rank is not identified: its standard error ``se`` (its unit) at
    the per-axis ``noise`` (m) exceeds what such an error can plausibly be."""
    f, u = display_unit(unit)
    return (f"{name} is determined only to ±{se * f:.3g} {u} by these poses (noise {noise * 1e3:.3g} mm), more "
            "than such an error can plausibly be")


def implausible_values(params: ParamSet, robot, plausible: dict | None = None) -> dict[str, float]:
    """Fitted errors of the robot's joints (origin shifts, turns, zero offsets, DH errors) larger than
    their plausible size: name -> value (its unit). The instrument frame and the marker points are
    unknowns of the set-up, not errors of the robot, and are never judged here."""
    plausible = PLAUSIBLE if plausible is None else plausible
    joints = set(robot.joint_names)
    out = {}
    for n, v, u, f in zip(params.names, params.values.tolist(), params.units, params.free.tolist()):
        if f and n.split(".")[0] in joints and abs(v) > plausible.get(u, float("inf")):
            out[n] = v
    return out


def implausible_reason(values: dict[str, float], units: dict[str, str], plausible: dict) -> str:
    """Why a model with ``values`` (name -> value) is refused, in words, with the way out."""
    def one(n):
        f, u = display_unit(units[n])
        return f"{n} = {values[n] * f:+.4g} {u}"
    lim = ", ".join(f"{plausible[u] * display_unit(u)[0]:g} {display_unit(u)[1]}" for u in sorted(plausible))
    return (f"the fit moves or turns joints by more than a plausible error ({lim}): "
            + ", ".join(one(n) for n in list(values)[:6]) + (" …" if len(values) > 6 else "")
            + ". The data cannot support this model: measure more poses spread over the joint ranges, fit fewer "
              "parameters, or, if errors this large are real, raise the limit ("
            + advice("plausible={'m': …, 'rad': …}", "--plausible-mm, --plausible-mrad") + ")")
