"""The settings records of the population solvers (:mod:`torchcal.options`): one frozen dataclass
per solver, as the drivers have. A solver takes ``settings=`` and/or the fields as keywords
(``get_solver("pso", pop_size=50)`` and ``get_solver("pso", PSOOptions(pop_size=50))`` are the same);
a misspelt key is refused with the fields that exist. What each field means is documented on the
solver's class (:class:`~torchcal.optim.pso.PSO`, :class:`~torchcal.optim.pso.LDPSO_BT`,
:class:`~torchcal.optim.cpso.ChaoticPSO`, :class:`~torchcal.optim.ga.GeneticAlgorithm`,
:class:`~torchcal.optim.mayfly.Mayfly`); the defaults are the seeds' settings.
"""
from __future__ import annotations

from dataclasses import dataclass

from torchcal.options import Options

__all__ = ["PSOOptions", "LDPSOOptions", "CPSOOptions", "GAOptions", "MayflyOptions"]


@dataclass(frozen=True)
class PSOOptions(Options):
    """Settings of :class:`~torchcal.optim.pso.PSO` (seed 000's PSO baseline)."""

    pop_size: int = 240
    max_iter: int = 500
    w: float | tuple[float, float] = 0.8
    c1: float = 1.49
    c2: float = 1.49
    v_max: float | None = 0.2
    stall_iter: int | None = None
    stall_tol: float = 0.0


@dataclass(frozen=True)
class LDPSOOptions(Options):
    """Settings of :class:`~torchcal.optim.pso.LDPSO_BT` (seed 000)."""

    n_max: int = 240
    n_min: int = 40
    max_iter: int = 500
    w1: float = 0.8
    w2: float = 0.4
    k_switch: float = 0.8
    c1: float = 1.49
    c2: float = 1.49
    v_max: float | None = 0.2
    stall_iter: int | None = None
    stall_tol: float = 0.0


@dataclass(frozen=True)
class CPSOOptions(Options):
    """Settings of :class:`~torchcal.optim.cpso.ChaoticPSO` (seed 001)."""

    pop_size: int = 200
    max_iter: int = 200
    w: float | tuple[float, float] = (0.9, 0.2)
    c1: float = 1.3
    c2: float = 1.8
    v_max: float | None = 0.2
    n_chaos: int = 10
    chaos_radius: float | None = None
    mu: float = 4.0


@dataclass(frozen=True)
class GAOptions(Options):
    """Settings of :class:`~torchcal.optim.ga.GeneticAlgorithm` (seed 004)."""

    pop_size: int = 30
    max_iter: int = 200
    p_crossover: float = 0.8
    p_mutation: float = 0.2
    migration: float = 0.7
    n_islands: int = 2
    migration_interval: int = 20
    n_elite: int | None = None
    selection: str = "sus"
    scaling_rate: float = 2.0
    alpha: float = 0.3
    mutation_scale: float = 0.1
    shrink: float = 1.0


@dataclass(frozen=True)
class MayflyOptions(Options):
    """Settings of :class:`~torchcal.optim.mayfly.Mayfly` (seed 002)."""

    pop_size: int = 20
    max_iter: int = 200
    n_off: int | None = None
    g: float = 0.8
    g_damp: float = 1.0
    a1: float = 1.0
    a2: float = 1.5
    a3: float = 1.5
    beta: float = 2.0
    d: float = 0.1
    d_damp: float = 0.99
    fl: float = 0.1
    fl_damp: float = 0.99
    v_max: float = 0.1
