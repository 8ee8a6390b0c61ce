"""Covariate series a measurement cell logs beside the poses, for the independent simulator: room
and motor temperatures (degC), campaign time (s) and the payload carried (kg), each ``(n,)`` in
visiting order and drawn from its own seed.  Whether a series drives an effect is the robot's business
(:class:`~torchcal.sim.physsim.PhysicalRobot`'s ``thermal`` columns and joint terms); the
others are recorded as plausible, unrelated logs."""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

__all__ = ["SERIES", "ambient_temperature", "campaign_time", "covariate_columns", "motor_temperature",
           "payload_runs", "payload_swap", "skin_temperature", "warmup_temperature"]

Seed = int | Sequence[int]


def warmup_temperature(n: int, span_k: float = 8.0, seed: Seed = 0, *, start_c: float = 20.0,
                       noise_k: float = 0.1) -> np.ndarray:
    """``(n,)`` degC, rows in visiting order: ``start_c + span_k (1 - exp(-i / (n/4)))`` plus
    Gaussian noise of ``noise_k``: a robot warming up over the campaign."""
    warm = span_k * (1 - np.exp(-np.arange(n) / max(n / 4, 1.0)))
    return start_c + warm + np.random.default_rng(seed).normal(0, noise_k, n)


def ambient_temperature(n: int, seed: Seed = 0, *, mean_c: float = 21.5, swing_k: float = 0.6,
                        cycles: float = 6.0, noise_k: float = 0.1) -> np.ndarray:
    """``(n,)`` degC: a hall's air, the air conditioning cycling by ``±swing_k`` with ``cycles``
    periods over the campaign (about 10 min each at 8 s a pose over 450 poses) at a drawn
    phase, plus sensor noise ``noise_k``."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * math.pi)
    i = np.arange(n) / max(n, 1)
    return mean_c + swing_k * np.sin(2 * math.pi * cycles * i + phase) + rng.normal(0, noise_k, n)


def motor_temperature(n: int, seed: Seed = 0, *, ambient_c: float = 22.0, rise_k: float = 18.0,
                      tau_rows: float = 40.0, block_rows: int = 30, noise_k: float = 0.1) -> np.ndarray:
    """``(n,)`` degC: a motor heating with its load, first order.  Each block of ``block_rows``
    rows runs at a duty drawn uniform in [0.1, 1]; the winding relaxes towards
    ``ambient_c + rise_k · duty`` with a time constant of ``tau_rows`` rows (it cools in light
    blocks), starting cold at ``ambient_c``; plus sensor noise ``noise_k``."""
    rng = np.random.default_rng(seed)
    duty = np.repeat(rng.uniform(0.1, 1.0, -(-n // block_rows)), block_rows)[:n]
    target, a = ambient_c + rise_k * duty, 1 - math.exp(-1 / tau_rows)
    out, t = np.empty(n), ambient_c
    for i in range(n):
        t += (target[i] - t) * a
        out[i] = t
    return out + rng.normal(0, noise_k, n)


def skin_temperature(n: int, seed: Seed = 0, *, ambient_c: float = 22.0, rise_k: float = 6.0,
                     tau_rows: float = 120.0, block_rows: int = 60, noise_k: float = 0.1) -> np.ndarray:
    """``(n,)`` degC: the arm's cover, the motor model with a smaller rise and a slower response."""
    return motor_temperature(n, seed, ambient_c=ambient_c, rise_k=rise_k, tau_rows=tau_rows, block_rows=block_rows,
                             noise_k=noise_k)


def campaign_time(n: int, seed: Seed = 0, *, step_s: float = 8.0, jitter_s: float = 2.0, pause_every: int = 50,
                  pause_s: float = 600.0) -> np.ndarray:
    """``(n,)`` s since the first pose: ``step_s ± jitter_s`` (uniform) per pose and a pause of
    ``pause_s`` every ``pause_every`` poses (the operator's breaks)."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(step_s - jitter_s, step_s + jitter_s, n)
    steps[0] = 0.0
    i = np.arange(n)
    steps[(i % pause_every == 0) & (i > 0)] += pause_s
    return np.cumsum(steps)


def payload_runs(n: int, seed: Seed = 0, *, masses: Sequence[float] = (0.0, 4.0, 8.0), run: int = 25) -> np.ndarray:
    """``(n,)`` kg: the payload the robot carries, changed every ``run`` poses to one of ``masses``
    at random (a cell measured with several loads, each swapped in by hand for a block of poses)."""
    rng = np.random.default_rng(seed)
    blocks = rng.choice(np.asarray(masses, dtype=float), -(-n // run))
    return np.repeat(blocks, run)[:n]


def payload_swap(n: int, seed: Seed = 0, *, before: float = 0.0, after: float = 8.0, at: float = 0.5) -> np.ndarray:
    """``(n,)`` kg: ``before`` up to the fraction ``at`` of the rows, ``after`` from there on (a payload
    swapped once in the session)."""
    return np.where(np.arange(n) >= int(at * n), after, before).astype(float)


SERIES: dict[str, Callable[..., np.ndarray]] = {
    "ambient": ambient_temperature, "motor": motor_temperature, "skin": skin_temperature, "time": campaign_time,
    "warmup": warmup_temperature, "payloads": payload_runs, "payload_swap": payload_swap}


def covariate_columns(spec: dict, n: int, seed: int) -> dict[str, np.ndarray]:
    """``{column: (kind, {keyword: value})}`` with ``kind`` in :data:`SERIES` -> ``{column: (n,)}``,
    in the order given; column ``k`` is drawn from the seed ``[seed, 100 + k]`` so that adding a
    column leaves the others as they were."""
    out = {}
    for k, (name, (kind, kw)) in enumerate(spec.items()):
        if kind not in SERIES:
            raise ValueError(f"covariate {name!r}: unknown series {kind!r}; series are {sorted(SERIES)}")
        out[name] = SERIES[kind](n, seed=[seed, 100 + k], **kw)
    return out
