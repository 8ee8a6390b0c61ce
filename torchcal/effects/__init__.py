"""Physical effects the geometric model lacks, as small models fitted jointly with it.

Adding an effect is one small class (see :class:`Effect`) registered in :data:`EFFECTS`.
"""
from .base import Effect, Prepared
from .joint import Backlash, CyclicJointError, JointCompliance, JointScale
from .thermal import ThermalDrift, thermal_covariate

EFFECTS: dict[str, type[Effect]] = {c.name: c for c in
                                    (JointCompliance, Backlash, CyclicJointError, JointScale, ThermalDrift)}

__all__ = ["Effect", "Prepared", "EFFECTS", "JointCompliance", "Backlash", "CyclicJointError", "JointScale",
           "ThermalDrift", "thermal_covariate", "effect_params", "build_effect"]


def build_effect(name: str, robot, data=None, **kw) -> Effect:
    """An effect by name, bound to ``data`` where it needs to be (covariate choice, joints seen)."""
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known: {sorted(EFFECTS)}")
    eff = EFFECTS[name](robot, **kw)
    if data is not None and eff.applicable(data)[0]:
        eff = eff.bind(data) if isinstance(eff, ThermalDrift) else eff.restrict_to_data(data)
    return eff


def effect_params(effects, data=None):
    """A :class:`~torchcal.params.ParamSet` for the effects' parameters (all free, start values
    from each effect's :meth:`Effect.init_theta`)."""
    import torch

    from ..params import ParamSet

    names = [n for e in effects for n in e.param_names]
    units = [u for e in effects for u in e.param_units]
    if not names:
        z = torch.zeros(0, dtype=torch.float64)
        return ParamSet([], [], z, z.bool(), z, z)
    vals = torch.cat([e.init_theta(data) for e in effects])
    lo = torch.cat([e.bounds()[0] for e in effects])
    hi = torch.cat([e.bounds()[1] for e in effects])
    return ParamSet(names, units, vals, torch.ones(len(names), dtype=torch.bool, device=vals.device), lo, hi)
