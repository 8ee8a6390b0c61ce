"""What the independent simulator's instrument adds to the true marker frames: gross outliers on
positions and orientation readings with noise (numpy only)."""
from __future__ import annotations

import numpy as np

from torchcal.sim.physsim_urdf import matrix_to_quat, rotation_exp

__all__ = ["orientation_readings", "outlier_shifts"]


def outlier_shifts(rng: np.random.Generator, N: int, M: int, fraction: float,
                   outlier_mm=(5.0, 20.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gross errors on ``round(fraction N)`` rows: ``(rows (K,), shift (K, M, 3) m, per_marker (K,))``;
    each marker moved by a length uniform in ``outlier_mm`` (mm) in a random direction, per row
    at random one vector for all markers (a bumped instrument) or one per marker (a wrong
    marker identification)."""
    K = int(round(fraction * N))
    rows = np.sort(rng.choice(N, K, replace=False)).astype(int)
    per_marker = rng.random(K) < 0.5
    v = rng.normal(size=(K, M, 3))
    v *= rng.uniform(*outlier_mm, size=(K, M, 1)) * 1e-3 / np.linalg.norm(v, axis=-1, keepdims=True)
    v[~per_marker] = v[~per_marker][:, :1]
    return rows, v, per_marker


def orientation_readings(rng: np.random.Generator, true_R: np.ndarray, rot_noise_rad: float, fraction: float,
                         pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measured and true unit quaternions ``(N, M, 4)`` (w, x, y, z; ``w >= 0``) of the markers
    where ``pose (M,)`` is True, NaN for the others.  ``true_R (N, M, 3, 3)``; the reading is
    ``true_R · exp(n)`` with ``n`` Gaussian, ``rot_noise_rad`` per axis (a small rotation in the
    marker frame), on ``round(fraction N)`` rows drawn at random (NaN on the rest)."""
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"orientation_fraction must be in [0, 1], got {fraction}")
    N, M = true_R.shape[:2]
    noisy = true_R @ rotation_exp(rng.normal(0, rot_noise_rad, (N, M, 3)))
    seen = np.zeros(N, dtype=bool)
    seen[rng.choice(N, int(round(fraction * N)), replace=False)] = True
    keep = seen[:, None] & pose[None, :]
    true_q = np.where(pose[None, :, None], matrix_to_quat(true_R), np.nan)
    return np.where(keep[..., None], matrix_to_quat(noisy), np.nan), true_q
