"""The outcome of an identifiability analysis in words: the report (rank, kept and dropped
parameters, condition number) and the reason given for every dropped parameter."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from torchcal.params import display_unit

__all__ = ["IdentifiabilityReport", "dependency_reason", "zero_column_reason"]


# Coefficients below this (relative, on unit-norm columns) are not named as partners.
_PARTNER_TOL = 1e-6


def zero_column_reason(name: str, kind: str = "position") -> str:
    """Why a parameter whose Jacobian column is zero is dropped, in words."""
    what = "marker position" if kind == "position" else "marker position or orientation"
    return (f"{name} does not move any {what} at these poses and parameter values (its Jacobian "
            "column is zero), so no measurement can see it")


def dependency_reason(i: int, c, res: float, kept: list[int], names: list[str], units: list[str], norms,
                      rtol: float, order=None) -> tuple[str, dict[str, float]]:
    """Why column ``i`` is dropped: the sentence and its relation (partner -> unscaled coefficient).

    Args:
        c: ``(len(kept),)`` least-squares coefficients of unit-norm column ``i`` on the unit-norm
            kept columns; ``res``: the relative residual of that fit.
        kept: column positions kept; ``norms``: every column's 2-norm (m per unit parameter).
        order: ``np.argsort(-abs(c), kind="stable")`` when the caller sorted many rows at once.
    """
    c = np.asarray(c, dtype=float)
    n = names[i]
    # partners by decreasing |coefficient| (ties: earlier kept column first)
    if order is None:
        order = np.argsort(-np.abs(c), kind="stable")
    partners = order[np.abs(c[order]) > _PARTNER_TOL].tolist()
    # unscaled: a_i/|a_i| = Σ c_j a_j/|a_j|  =>  a_i = Σ c_j |a_i|/|a_j| a_j (per unit of p_i)
    cu = {names[kept[t]]: float(c[t] * norms[i] / norms[kept[t]]) for t in partners}
    relation = dict(cu)
    fi, ui = display_unit(units[i])

    def term(t, lead=False):
        j = kept[t]
        fj, uj = display_unit(units[j])
        v = cu[names[j]] * fj / fi  # display units of partner per display unit of p_i
        return f"{v:.4g} {uj} of {names[j]}" if lead else f"{'+' if v >= 0 else '-'} {abs(v):.4g} {uj} of {names[j]}"

    if not partners:
        why = f"{n} is numerically dependent on the identifiable parameters (residual {res:.2g})"
    elif len(partners) == 1:
        why = (f"{n} cannot be told apart from {names[kept[partners[0]]]}: "
               f"1 {ui} of {n} acts like {term(partners[0], True)}")
    else:
        shown = partners[:3]
        more = f" and {len(partners) - 3} more" if len(partners) > 3 else ""
        why = (f"{n} is a combination of " + ", ".join(names[kept[t]] for t in shown) + more +
               f": 1 {ui} of {n} acts like " + " ".join(term(t, lead=(r == 0)) for r, t in enumerate(shown)) +
               (" + …" if more else ""))
    if res > 1e3 * rtol:
        why += f" (fit residual {res:.2g} of a unit column: nearly independent)"
    return why, relation


# ---------------------------------------------------------------------------- report
@dataclass
class IdentifiabilityReport:
    """What a pose set can identify (see :func:`identifiability`).

    Attributes:
        rank: numerical rank of the column-normalised Jacobian (= ``len(identifiable)``).
        svd_rank: the rank from its SVD (``σ > rtol·σ1``); equal to ``rank`` unless the
            problem is ambiguous at ``rtol`` (a warning is then raised).
        n_params: number of analysed (free) parameters ``k``.
        n_rows: stacked rows ``m = N·M·r``.
        identifiable: the base subset kept by the pivoted QR, in the robot's parameter order.
        dropped: the other free parameters, in the robot's parameter order.
        reasons: a sentence per dropped parameter.
        relations: per dropped parameter, the identifiable parameters that absorb it, as
            unscaled coefficients: moving the dropped parameter by one unit (m or rad) acts like
            moving each partner by ``coef`` of its own unit; ``{}`` for columns that are zero.
        residuals: per dropped parameter, the relative least-squares residual of that fit
            (≈ 0: the column lies in the span of the identifiable ones).
        singular_values: of the unit-norm column-normalised Jacobian of all ``k`` free
            parameters (zero columns included as zero), descending.
        O1, O2, O3, O4, condition: observability indices of the identifiable columns, scaled
            to unit RMS (module docstring).
        column_rms: per free parameter, its column's RMS over rows (m per unit parameter);
            pass to :func:`observability` as ``scale`` to compare other pose sets on this footing.
        pivot_order: identifiable parameters in the order the QR chose them.
        imprecise: the dropped parameters of full rank that the data pin down worse than their
            plausible size (:func:`torchcal.pipelines.fitting.reduce_free`).
    """

    rank: int
    svd_rank: int
    n_params: int
    n_rows: int
    identifiable: list[str]
    dropped: list[str]
    reasons: dict[str, str]
    relations: dict[str, dict[str, float]]
    residuals: dict[str, float]
    singular_values: list[float]
    O1: float
    O2: float
    O3: float
    O4: float
    condition: float
    kind: str = "position"
    rtol: float = 1e-9
    column_rms: dict[str, float] = field(default_factory=dict)
    pivot_order: list[str] = field(default_factory=list)
    imprecise: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """A multi-line, human-readable account: rank, indices, kept and dropped parameters."""
        lines = [f"Identifiability ({self.kind} rows, {self.n_rows} rows): rank {self.rank} of {self.n_params} "
                 f"free parameters (SVD rank {self.svd_rank}, rtol {self.rtol:g})",
                 f"  observability (unit-RMS columns, m = {self.n_rows}): O1 = {self.O1:.4g}, O2 = {self.O2:.4g}, "
                 f"O3 = {self.O3:.4g}, O4 = {self.O4:.4g}, condition = {self.condition:.4g}",
                 f"  identifiable ({len(self.identifiable)}): " + ", ".join(self.identifiable)]
        if self.dropped:
            lines.append(f"  dropped ({len(self.dropped)}):")
            lines += [f"    - {self.reasons[n]}" for n in self.dropped]
        else:
            lines.append("  dropped: none")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()

    def to_dict(self) -> dict:
        """Plain JSON-serialisable values (an infinite condition number becomes ``None``)."""
        fin = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
        return dict(rank=int(self.rank), svd_rank=int(self.svd_rank), n_params=int(self.n_params),
                    n_rows=int(self.n_rows), kind=self.kind, rtol=float(self.rtol),
                    identifiable=list(self.identifiable), dropped=list(self.dropped),
                    reasons=dict(self.reasons),
                    relations={k: {p: float(c) for p, c in v.items()} for k, v in self.relations.items()},
                    residuals={k: float(v) for k, v in self.residuals.items()},
                    singular_values=[float(s) for s in self.singular_values],
                    O1=fin(self.O1), O2=fin(self.O2), O3=fin(self.O3), O4=fin(self.O4),
                    condition=fin(self.condition),
                    column_rms={k: float(v) for k, v in self.column_rms.items()},
                    pivot_order=list(self.pivot_order))
