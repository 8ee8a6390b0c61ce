"""Parameter sets: a named, unit-carrying vector with free/fixed flags and bounds."""
from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcal.advice import advice

__all__ = ["ParamSet", "NoSuchParameter", "display_unit"]

_WILDCARD = re.compile(r"[*?\[]")  # what makes a glob pattern more than a name

# The one unit table: SI unit -> (factor, unit) in which people read it. m and rad share the
# factor, so ratios of the two read unchanged. Spellings of one unit ("rad/N/m", "rad/(N*m)")
# read alike. Reports, tables and plots all go through display_unit.
_DISPLAY = {"m": (1e3, "mm"), "rad": (1e3, "mrad"),
            "rad/(N*m)": (1e6, "µrad/(N·m)"), "rad/N/m": (1e6, "µrad/(N·m)"), "rad/(N m)": (1e6, "µrad/(N·m)"),
            "rad/N": (1e6, "µrad/N"), "m/N": (1e9, "µm/kN"),
            # lumped compliance × mass (× lever): what a joint twists per unit gravity on a mass (moment)
            "rad*kg/(N*m)": (1e6, "µrad·kg/(N·m)"), "rad*kg/N": (1e6, "µrad·kg/N"),
            "1/K": (1e6, "µm/(m·K)"), "1/s": (3.6e9, "µm/(m·h)"), "1": (1e6, "ppm"),
            "kg": (1.0, "kg"), "kg*m": (1.0, "kg·m"), "N*m": (1.0, "N·m"), "s": (1.0, "s"), "K": (1.0, "K")}


def display_unit(unit: str) -> tuple[float, str]:
    """``(factor, unit)`` to show a value given in the SI ``unit``: m -> mm, rad -> mrad,
    rad/(N*m) -> µrad/(N·m), m/N -> µm/kN, 1/K -> µm/(m·K), a scale factor -> ppm; anything
    else as it is."""
    return _DISPLAY.get(unit, (1.0, unit))


class NoSuchParameter(KeyError, ValueError):
    """A parameter pattern (``free=``, ``--free``) that names no parameter: a lookup that failed
    (KeyError) on a value the user gave (ValueError, which the command line refuses)."""

    def __str__(self) -> str:  # the message as written, not KeyError's repr of it
        return str(self.args[0]) if self.args else ""


@dataclass
class ParamSet:
    """Values of a robot's error parameters, with names, units, free flags and bounds.

    Every entry is an *error* whose nominal value is 0 (the base frame is absolute: 0 means the
    instrument frame coincides with the robot base). ``values``, ``lower`` and ``upper`` are
    ``(K,)`` tensors; ``free`` is a ``(K,)`` bool tensor.
    """

    names: list[str]
    units: list[str]
    values: Tensor
    free: Tensor
    lower: Tensor
    upper: Tensor

    def __post_init__(self):
        k = len(self.names)
        for f in ("values", "free", "lower", "upper"):
            t = getattr(self, f)
            if t.shape != (k,):
                raise ValueError(f"ParamSet.{f} has shape {tuple(t.shape)}, expected ({k},)")
        if len(set(self.names)) != k:
            dup = sorted({n for n in self.names if self.names.count(n) > 1})
            raise ValueError(f"duplicate parameter names: {dup[:5]}")
        self._index = {n: i for i, n in enumerate(self.names)}

    def __len__(self) -> int:
        return len(self.names)

    def clone(self) -> "ParamSet":
        return ParamSet(list(self.names), list(self.units), self.values.clone(), self.free.clone(),
                        self.lower.clone(), self.upper.clone())

    def index(self, name: str) -> int:
        try:
            return self._index[name]
        except KeyError:
            close = [n for n in self.names if name.split(".")[0] in n][:6]
            raise KeyError(f"no parameter named {name!r}" + (f"; similar: {', '.join(close)}" if close else "")) from None

    def select(self, patterns) -> list[int]:
        """Indices of parameters whose names match any glob pattern (``"joint_2.*"``, ``"*.dz"``)."""
        if isinstance(patterns, str):
            patterns = [patterns]
        # a pattern without wildcards matches its own name only: looked up, not matched against every name
        exact = {p for p in patterns if not _WILDCARD.search(p)}
        globs = [p for p in patterns if p not in exact]
        idx = [i for i, n in enumerate(self.names) if n in exact or any(fnmatch.fnmatchcase(n, p) for p in globs)]
        if not idx:
            raise NoSuchParameter(f"no parameter matches {list(patterns)}; names look like {self.names[:4]} … "
                                  + advice("(robot.param_names lists them all)",
                                           "(--free takes glob patterns of these names, e.g. --free 'elbow*' --free "
                                           "'*.offset'; report.md of a calibration lists them)"))
        return idx

    def fix(self, *patterns: str) -> "ParamSet":
        """Mark matching parameters fixed (in place); returns self for chaining."""
        self.free[self.select(list(patterns))] = False
        return self

    def unfix(self, *patterns: str) -> "ParamSet":
        self.free[self.select(list(patterns))] = True
        return self

    def only(self, *patterns: str) -> "ParamSet":
        """Free exactly the matching parameters."""
        self.free[:] = False
        return self.unfix(*patterns)

    @property
    def free_names(self) -> list[str]:
        return [self.names[i] for i in self._free()[1]]

    @property
    def free_index(self) -> Tensor:
        """``(k,)`` indices of the free entries."""
        return self._free()[0]

    def _free(self) -> tuple[Tensor, list[int]]:
        """The free entries' indices as a tensor and a list, found again only when ``free`` was
        replaced or written in place: on a GPU, finding them makes the host wait for the device."""
        if self.free.is_inference():  # no version counter to tell a change by
            idx = torch.nonzero(self.free).flatten()
            return idx, idx.tolist()
        c = getattr(self, "_free_cache", None)
        if c is None or c[0] is not self.free or c[1] != self.free._version:
            idx = torch.nonzero(self.free).flatten()
            c = self._free_cache = (self.free, self.free._version, idx, idx.tolist())
        return c[2], c[3]

    def expand(self, x_free: Tensor) -> Tensor:
        """``(P, n_free)`` or ``(n_free,)`` free values -> full ``(P, K)`` / ``(K,)`` vectors
        (fixed entries keep their current values)."""
        idx = self.free_index
        if x_free.shape[-1] != idx.numel():
            raise ValueError(f"expected {idx.numel()} free values, got {x_free.shape[-1]}")
        full = self.values.to(x_free.dtype).expand(*x_free.shape[:-1], len(self)).clone()
        full[..., idx] = x_free
        return full

    def __getitem__(self, name: str) -> float:
        return float(self.values[self.index(name)])

    def __setitem__(self, name: str, value: float) -> None:
        self.values[self.index(name)] = value

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, self.values.tolist()))

    @staticmethod
    def concat(*sets: "ParamSet") -> "ParamSet":
        """One ParamSet holding the entries of several, in order."""
        return ParamSet(sum((s.names for s in sets), []), sum((s.units for s in sets), []),
                        torch.cat([s.values for s in sets]), torch.cat([s.free for s in sets]),
                        torch.cat([s.lower for s in sets]), torch.cat([s.upper for s in sets]))

    def table(self, only_free: bool = False, scale: bool = True) -> str:
        """A readable table; with ``scale`` lengths are shown in mm and angles in mrad."""
        lines = [f"{'parameter':<32} {'value':>14}  unit  free"]
        for n, u, v, f in zip(self.names, self.units, self.values.tolist(), self.free.tolist()):
            if only_free and not f:
                continue
            if scale:
                f_, u = display_unit(u)
                v = v * f_
            lines.append(f"{n:<32} {v:>14.6f}  {u:<5} {'yes' if f else 'no'}")
        return "\n".join(lines)
