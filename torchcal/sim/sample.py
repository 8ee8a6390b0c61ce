"""One simulated data set from the independent simulator: what the instrument recorded (joints rad,
marker positions m, orientations, covariates) and, apart, the truth behind each row (clean positions, noise,
outliers) that identifying code never reads."""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcal.measure.data import Measurements
from torchcal.measure.io import save_measurements

__all__ = ["Sample"]


@dataclass
class Sample:
    """One simulated measurement campaign.

    ``q (N, dof)`` commanded joint values, ``positions (N, M, 3)`` m measured (noise and outliers
    included), ``covariates`` name -> ``(N,)``, ``quaternions (N, M, 4)`` measured orientations
    (w, x, y, z; NaN where not measured) or ``None``.  Truth only, never written to the data:
    ``true_positions (N, M, 3)`` noise- and outlier-free, ``true_quaternions (N, M, 4)``
    noise-free (NaN for markers measured without orientation), ``outlier_rows (K,)``,
    ``outlier_shift_m (K, M, 3)`` and ``outlier_per_marker (K,)`` (False: the whole row moved
    by one vector, as when the instrument is bumped; True: each marker by its own vector, as
    with a wrong marker identification).
    """

    q: np.ndarray
    positions: np.ndarray
    joint_names: list[str]
    marker_names: list[str]
    covariates: dict[str, np.ndarray] = field(default_factory=dict)
    true_positions: np.ndarray | None = None
    outlier_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    outlier_shift_m: np.ndarray | None = None
    outlier_per_marker: np.ndarray | None = None
    quaternions: np.ndarray | None = None
    true_quaternions: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.q)

    def to_measurements(self, dtype=None):
        """torchcal's ``Measurements`` (float64 unless ``dtype``); carries no truth."""
        t = lambda a: torch.as_tensor(np.array(a, dtype=float), dtype=dtype or torch.float64)  # noqa: E731
        return Measurements(t(self.q), t(self.positions), list(self.marker_names), list(self.joint_names),
                            None if self.quaternions is None else t(self.quaternions),
                            {k: t(v) for k, v in self.covariates.items()})

    def save_csv(self, path: str | os.PathLike) -> None:
        """Write the measurement CSV (``torchcal.measure.io`` format); truth stays out."""
        save_measurements(path, self.to_measurements())

    def subset(self, idx) -> "Sample":
        """Rows ``idx`` (indices or bool mask), outlier truth re-indexed."""
        idx = np.asarray(idx)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(int)
        where = {int(r): k for k, r in enumerate(self.outlier_rows)}
        rows = np.array([i for i, r in enumerate(idx) if int(r) in where], dtype=int)
        pick = lambda a: None if a is None else a[[where[int(idx[i])] for i in rows]]  # noqa: E731
        rows_of = lambda a: None if a is None else a[idx]  # noqa: E731
        return Sample(self.q[idx], self.positions[idx], list(self.joint_names), list(self.marker_names),
                      {k: v[idx] for k, v in self.covariates.items()}, rows_of(self.true_positions), rows,
                      pick(self.outlier_shift_m), pick(self.outlier_per_marker), rows_of(self.quaternions),
                      rows_of(self.true_quaternions))
