"""The solver interface and the registry that finds solvers by name."""
from __future__ import annotations

import time
from typing import Callable

import torch

from torchcal.optim.result import Result
from torchcal.problems.base import Problem

__all__ = ["Solver", "register", "get_solver", "available", "is_population", "minimize"]

_REGISTRY: dict[str, type["Solver"]] = {}


class Solver:
    """Base class of every solver. Options go to ``__init__``; :meth:`minimize` runs.

    Subclasses set ``name`` and implement :meth:`_run`. ``seed`` seeds a private
    ``torch.Generator`` so runs are reproducible and never touch global RNG state.
    """

    name = "solver"
    population = False  # searches with a population inside finite bounds (a swarm, a GA)

    def __init__(self, *, seed: int | None = 0, progress: bool = False,
                 callback: Callable[[int, float], None] | None = None):
        self.seed = seed
        self.progress = progress
        self.callback = callback

    def generator(self, problem: Problem, seed: int | None = None) -> torch.Generator:
        """A generator on the problem's device seeded with ``seed`` (default: the solver's)."""
        seed = self.seed if seed is None else seed
        g = torch.Generator(device=problem.device)
        g.manual_seed(0 if seed is None else int(seed))
        return g

    def minimize(self, problem: Problem) -> Result:

        t0 = time.perf_counter()
        res = self._run(problem)
        res.wall_time_s = time.perf_counter() - t0
        res.method = self.name
        return res

    def _run(self, problem: Problem) -> Result:  # pragma: no cover - abstract
        raise NotImplementedError


def register(cls: type[Solver]) -> type[Solver]:
    """Class decorator: make a solver available by its ``name`` (and ``aliases``)."""
    for key in (cls.name, *getattr(cls, "aliases", ())):
        _REGISTRY[key.lower()] = cls
    return cls


def available(population: bool | None = None) -> list[str]:
    """Registered solver names (aliases too); ``population``: only those that do (True) or do not
    (False) search with a population."""
    return sorted(k for k, c in _REGISTRY.items() if population is None or c.population == population)


def solvers(population: bool | None = None) -> dict[str, tuple[str, ...]]:
    """Each registered solver once: its name -> its aliases (``population`` as in :func:`available`)."""
    out = {}
    for c in _REGISTRY.values():
        if population is None or c.population == population:
            out[c.name.lower()] = tuple(a.lower() for a in getattr(c, "aliases", ()))
    return dict(sorted(out.items()))


def is_population(method: str) -> bool:
    """Whether the solver registered as ``method`` searches with a population (it needs a box)."""
    return bool(getattr(_REGISTRY.get(method.lower()), "population", False))


def get_solver(method: str, **options) -> Solver:
    try:
        cls = _REGISTRY[method.lower()]
    except KeyError:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(available())}") from None
    return cls(**options)


def minimize(problem: Problem, method: str = "lm", **options) -> Result:
    """Minimise ``problem`` with the solver registered as ``method`` (e.g. ``"lm"``, ``"pso"``,
    ``"ldpso-bt"``, ``"cpso"``, ``"ga"``, ``"ma"``, ``"mma"``)."""
    return get_solver(method, **options).minimize(problem)
