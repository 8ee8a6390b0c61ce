"""A loop model's parameters cut by effect: the geometry (with the set-up's unknowns), then one
ParamSet per effect, and put together again."""
from __future__ import annotations

from torchcal.params import ParamSet

__all__ = ["split_params", "assemble"]


def split_params(params: ParamSet, robot, effects: list) -> tuple[ParamSet, list[ParamSet]]:
    """``params`` cut into the geometry (with the set-up's unknowns) and one ParamSet per effect."""
    K = len(params) - sum(e.n_params for e in effects)
    idx = [list(range(K))]
    o = K
    for e in effects:
        idx.append(list(range(o, o + e.n_params)))
        o += e.n_params

    def take(ii):
        return ParamSet([params.names[i] for i in ii], [params.units[i] for i in ii], params.values[ii],
                        params.free[ii], params.lower[ii], params.upper[ii])
    parts = [take(ii) for ii in idx]
    return parts[0], parts[1:]


def assemble(geo: ParamSet, parts: list[ParamSet]) -> ParamSet:
    return ParamSet.concat(geo, *parts) if parts else geo.clone()

