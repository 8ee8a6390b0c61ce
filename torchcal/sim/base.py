"""The interface every simulator shares: it returns what an instrument would give, and, apart, the
truth that made it. Identifying code receives only ``data``; tests and scripts compare against
``truth``."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

__all__ = ["Simulated", "Simulator", "expected_noise_norm"]


@dataclass
class Simulated:
    """One simulated data set.

    Attributes:
        data: what a real instrument would give (e.g. :class:`~torchcal.measure.io.Measurements`,
            PSD spots, torques): the only thing a solver may read.
        truth: the parameters and settings that made it (units in the key names or the
            simulator's docstring), for checking results.
        noise_floor: the mean Euclidean norm of the added noise where that has a meaning (m),
            else ``None``.
    """

    data: Any
    truth: dict = field(default_factory=dict)
    noise_floor: float | None = None


class Simulator(Protocol):
    """A simulator for one system: ``simulate(n, seed=...)`` makes ``n`` samples (poses, spots,
    trajectory points) reproducibly from ``seed``."""

    def simulate(self, n: int, *, seed: int = 0) -> Simulated: ...


def expected_noise_norm(sigma: float) -> float:
    """Mean Euclidean norm (m) of isotropic 3-D Gaussian noise with ``sigma`` (m) per axis:
    ``σ √2 Γ(2) / Γ(3/2) ≈ 1.596 σ``."""
    return sigma * math.sqrt(2.0) * math.gamma(2.0) / math.gamma(1.5)
