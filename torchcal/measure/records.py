"""Typed records of a model's error on measured data, shared by calibrate, the loop and the fleet.

- :class:`ErrorStats`: the statistics of a set of errors in one unit (mm for positions, mrad for
  angles), overall and per marker, per observation kind and for the measured orientations.
- :class:`Stage`: one model along a fit (nominal, geometric, + an effect …) and its statistics on
  the training and held-out rows.
- :class:`ErrorDetails`: the per-observation errors behind a stage's statistics, which the figures
  read; :class:`StageErrors` pairs those of the training and held-out rows.
- :class:`Suspect`: an observation far from the model, listed for a person to check.

They turn into JSON only at the edge (:meth:`to_json`, called by ``report/``), with the keys
``report.json`` has always had (``mean_mm``, ``per_marker`` …). Reading a record by those keys
(``stage["test"]["mean_mm"]``) still works, for scripts written when these were dicts.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import torch
from torch import Tensor

__all__ = ["JsonRecord", "ErrorStats", "Stage", "ErrorDetails", "StageErrors", "Suspect", "STAT_NAMES"]

# the statistics of a set of errors, in the order tables show them
STAT_NAMES = ("mean", "std", "max", "rmse", "median", "p95")


class JsonRecord(Mapping):
    """Base of the typed records that ``report.json`` shows (:meth:`to_json`). A record is also a
    read-only mapping by those keys (``rec["mean_mm"]``, ``rec.get(key)``, ``set(rec)``), exactly
    as the dicts it replaces were, so that scripts written against the dicts keep working."""

    def to_json(self) -> dict:
        raise NotImplementedError

    def _as_dict(self) -> dict:  # what reading by key sees
        return self.to_json()

    def __getitem__(self, key: str):
        return self._as_dict()[key]

    def __iter__(self):
        return iter(self._as_dict())

    def __len__(self) -> int:
        return len(self._as_dict())


@dataclass(frozen=True)
class ErrorStats(JsonRecord):
    """Statistics of ``n`` errors in ``unit`` (``mm`` or ``mrad``): mean, standard deviation
    (unbiased), max, root mean square, median (the lower middle) and 95th percentile (linear
    interpolation). NaN when ``n == 0``.

    ``per_marker``/``per_kind``: the same per marker and per kind of observation (a kind only when
    the rows measured more than full positions); ``orientation``: the angle errors (mrad) of the
    measured orientations, apart from the positions. None where not computed."""
    n: int
    mean: float = math.nan
    std: float = math.nan
    max: float = math.nan
    rmse: float = math.nan
    median: float = math.nan
    p95: float = math.nan
    unit: str = "mm"
    per_marker: dict[str, ErrorStats] | None = None
    per_kind: dict[str, ErrorStats] | None = None
    orientation: ErrorStats | None = None

    def value(self, stat: str) -> float:
        """One statistic by name (:data:`STAT_NAMES`)."""
        return getattr(self, stat)

    def to_json(self) -> dict:
        """``{"n", "mean_mm", …, "per_marker", …}``: the keys of ``report.json``."""
        out: dict = {"n": self.n}
        if self.n:
            out.update({f"{s}_{self.unit}": getattr(self, s) for s in STAT_NAMES})
        if self.per_marker is not None:
            out["per_marker"] = {m: s.to_json() for m, s in self.per_marker.items()}
        if self.per_kind is not None:
            out["per_kind"] = {k: s.to_json() for k, s in self.per_kind.items()}
        if self.orientation is not None:
            out["orientation"] = self.orientation.to_json()
        return out


@dataclass(frozen=True)
class Stage(JsonRecord):
    """One model along a fit and its error statistics.

    Attributes:
        name: ``nominal``, ``geometric``, ``+<effect>``, ``+residual_elm`` … (the fleet names its
            final stage after the solve).
        n_params: parameters fitted (for a prior-held fit, its effective number rounded).
        train, test: statistics on the training and held-out rows (``test`` None without them).
        cv_rmse_mm: the loop's cross-validated RMS error (mm) of this model, when it has one.
        prior_mm: the Gaussian prior (mm and mrad) the geometric fit was held by, None: none.
        k_eff: effective number of parameters of a prior-held fit.
    """
    name: str
    n_params: int
    train: ErrorStats | None
    test: ErrorStats | None = None
    cv_rmse_mm: float | None = None
    prior_mm: float | None = None
    k_eff: float | None = None

    def to_json(self) -> dict:
        out: dict = {"name": self.name, "n_params": self.n_params,
                     "train": None if self.train is None else self.train.to_json()}
        if self.test is not None:
            out["test"] = self.test.to_json()
        if self.cv_rmse_mm is not None:
            out["cv_rmse_mm"] = self.cv_rmse_mm
        if self.k_eff is not None:  # a prior-held fit states its prior, None when it had none
            out.update(prior_mm=self.prior_mm, k_eff=self.k_eff)
        return out


@dataclass(frozen=True)
class ErrorDetails(JsonRecord):
    """The errors behind a stage's statistics, one entry per observation (``n`` of them).

    Attributes:
        e: ``(n,)`` m: the norm of what each observation measured (a plane contact's signed
            distance, a partial position's measured axes).
        xyz: ``(n_pos, 3)`` m: model − measured of the position observations, instrument frame;
            NaN in axes not measured.
        dist: ``(n,)`` m: the marker's distance from the robot base.
        row: ``(n,)`` 0-based row of the data; marker: ``(n,)`` index into ``robot.marker_names``;
        dims: ``(n,)`` how many components each observation measured.
    """
    e: Tensor
    xyz: Tensor
    dist: Tensor
    row: Tensor | None = None
    marker: Tensor | None = None
    dims: Tensor | None = None

    @property
    def n(self) -> int:
        """How many observations."""
        return int(self.e.numel())

    def _as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


@dataclass(frozen=True)
class StageErrors(JsonRecord):
    """A stage's :class:`ErrorDetails` on the training and held-out rows (None: no such rows)."""
    train_details: ErrorDetails | None
    test_details: ErrorDetails | None = None

    def plotted(self, split: str) -> ErrorDetails | None:
        """The details of ``split`` (``"train"`` or ``"test"``) when it has observations to plot."""
        d = getattr(self, f"{split}_details")
        return d if d is not None and d.n else None

    @property
    def train(self) -> Tensor:
        """``(n,)`` m: the training observations' errors (empty without details)."""
        return torch.zeros(0) if self.train_details is None else self.train_details.e

    @property
    def test(self) -> Tensor:
        """``(n,)`` m: the held-out observations' errors (empty without held-out rows)."""
        return torch.zeros(0) if self.test_details is None else self.test_details.e

    def _as_dict(self) -> dict:
        out = {"train": self.train, "test": self.test}
        out.update({k: getattr(self, k) for k in ("train_details", "test_details") if getattr(self, k) is not None})
        return out


@dataclass(frozen=True, eq=False)  # equal to any mapping with its keys and values, as the dicts it replaces
class Suspect(JsonRecord):
    """An observation far from the model: a gross error left out of a fit (calibrate, the fleet) or
    a suspect the loop's Huber loss down-weights; listed for a person to check, never dropped.

    Attributes:
        row: 0-based row of its data file; marker: the marker it measured.
        error_mm: its error (mm); kind: what it measured (the loop's rows: ``"position"``, ``"plane
            contact"`` …; None where every observation is a position).
    """
    row: int
    marker: str
    error_mm: float
    kind: str | None = None

    def to_json(self) -> dict:
        out: dict = {"row": self.row, "marker": self.marker}
        if self.kind is not None:
            out["kind"] = self.kind
        out["error_mm"] = self.error_mm
        return out
