"""What a report may state about an accepted effect: only what is significant.

The loop accepts an effect on its cross-validated gain; each of its modes, and each shared
quantity (a payload, the tilt of gravity), is then judged on its own value and standard error.
A group of values is a finding only when it lies :data:`~torchcal.report.units.SIGNIFICANT_Z`
standard errors from zero (chi-square for a group); the rest is listed as measured but not
significant, with its value and standard error, never as a statement about the robot.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchcal.report.units import SIGNIFICANT_Z, significant, with_error, z_score

__all__ = ["EffectFindings", "effect_findings"]


@dataclass
class EffectFindings:
    """``stated``: sentences for the significant modes (the effect's own words); ``not_significant``:
    per group that is not, its label and every value with its standard error; ``groups``: the
    judgement per group (label, parameters, largest |value| / se, significant)."""

    effect: str
    stated: list[str] = field(default_factory=list)
    not_significant: list[str] = field(default_factory=list)
    groups: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"effect": self.effect, "stated": self.stated, "not_significant": self.not_significant,
                "groups": self.groups, "z": SIGNIFICANT_Z}


def _groups(effect) -> list[tuple[str, list[int]]]:
    """The effect's modes, then its other parameters grouped by what they describe (a payload's
    mass and moments, the two components of gravity's tilt)."""
    out = [(label, list(cols)) for label, cols in effect.modes()]
    taken = {i for _, cols in out for i in cols}
    local = [n.split(".", 1)[1] for n in effect.param_names]
    rest: dict[str, list[int]] = {}
    for i, n in enumerate(local):
        if i not in taken:
            rest.setdefault(n.split(".")[0], []).append(i)
    return out + list(rest.items())


def effect_findings(effect, values: dict[str, float], std_errors: dict[str, float | None],
                    z: float = SIGNIFICANT_Z) -> EffectFindings:
    """Judge an accepted effect's fitted values.

    Args:
        effect: the effect object (its modes, parameter names and sentences).
        values: full parameter name -> fitted value (SI units) of the parameters that were fitted;
            the others are not judged.
        std_errors: full parameter name -> standard error (same unit), None where unknown.
    """
    names, units = effect.param_names, effect.param_units
    theta = torch.tensor([float(values.get(n, 0.0)) for n in names], dtype=torch.float64)
    keep = torch.zeros(len(names), dtype=torch.bool)
    out = EffectFindings(effect.name)
    for label, cols in _groups(effect):
        cols = [i for i in cols if names[i] in values]
        if not cols:
            continue
        v = [float(values[names[i]]) for i in cols]
        s = [std_errors.get(names[i]) for i in cols]
        ok = significant(v, s, z)
        zs = [z_score(a, b) for a, b in zip(v, s)]
        out.groups.append({"label": label, "params": [names[i] for i in cols], "significant": ok,
                           "max_z": max((x for x in zs if x == x), default=None)})
        if ok:
            keep[cols] = True
        else:
            local = [names[i].split(".", 1)[1] for i in cols]
            local = [n[len(label) + 1:] if n.startswith(label + ".") else n for n in local]
            parts = ", ".join(f"{n} = {with_error(a, b, units[i])}" for n, i, a, b in zip(local, cols, v, s))
            out.not_significant.append(f"{label} = {with_error(v[0], s[0], units[cols[0]])}"
                                       if local == [label] else f"{label}: {parts}")
    if bool(keep.any()):
        out.stated = effect.describe(theta, free=keep)
    return out
