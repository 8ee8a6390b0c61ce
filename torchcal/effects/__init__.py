"""Physical effects the geometric model lacks, as small models fitted jointly with it.

Adding an effect is one small class (see :class:`Effect`) registered with :func:`register_effect`
(:mod:`torchcal.effects.registry`).
"""
from __future__ import annotations

import torch

from torchcal.effects.base import TIME_COVARIATES, Effect, LinearBasis, Prepared
from torchcal.effects.compliance import JointCompliance, LoadCompliance
from torchcal.effects.deformation import GravityDeformation
from torchcal.effects.joint import Backlash, CyclicJointError, JointScale
from torchcal.effects.registry import EFFECTS, effect_class, effect_type, register_effect
from torchcal.effects.terms import JointTerms
from torchcal.effects.anydriver import ParameterDrivers
from torchcal.effects.frame_path import FramePath
from torchcal.effects.thermal import ThermalDrift, thermal_covariate
from torchcal.params import ParamSet

for _cls in (JointCompliance, Backlash, CyclicJointError, JointScale, ThermalDrift, GravityDeformation, JointTerms,
             LoadCompliance, ParameterDrivers, FramePath):
    register_effect(_cls)

__all__ = ["Effect", "Prepared", "LinearBasis", "EFFECTS", "JointCompliance", "LoadCompliance", "GravityDeformation",
           "Backlash", "CyclicJointError", "JointScale", "ThermalDrift", "JointTerms", "ParameterDrivers", "FramePath",
           "thermal_covariate", "effect_params", "build_effect", "TIME_COVARIATES", "register_effect", "effect_class",
           "effect_type"]


def build_effect(name: str, robot, data=None, geometry=None, **kw) -> Effect:
    """An effect by name, with features at ``geometry`` (``(K,)``, default nominal), bound to
    ``data`` where it applies (joints that move the markers, covariate choice and ranges)."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}")
    eff = EFFECTS[name](robot, geometry=geometry, **kw)
    if data is not None and eff.applicable(data)[0]:
        eff = eff.bind(data)
    return eff


def effect_params(effects, data=None) -> ParamSet:
    """A :class:`~torchcal.params.ParamSet` for the effects' parameters (all free, start values
    from each effect's ``theta``)."""
    names = [n for e in effects for n in e.param_names]
    units = [u for e in effects for u in e.param_units]
    if not names:
        z = torch.zeros(0, dtype=torch.float64)
        return ParamSet([], [], z, z.bool(), z, z)
    vals = torch.cat([e.theta.detach().clone() for e in effects])
    lo = torch.cat([e.bounds()[0] for e in effects])
    hi = torch.cat([e.bounds()[1] for e in effects])
    return ParamSet(names, units, vals, torch.ones(len(names), dtype=torch.bool, device=vals.device), lo, hi)
