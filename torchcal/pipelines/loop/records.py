"""Typed records of the loop's diagnosis: where a candidate effect starts (:class:`EffectStart`),
what trying it gave (:class:`Trial`), the line the report shows for it (:class:`Candidate`) and
an accepted effect's finding (:class:`Finding`). They become JSON only in ``report/``, with the keys
``report.json`` has always had."""
from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.measure.records import JsonRecord
from torchcal.params import ParamSet

__all__ = ["EffectStart", "Candidate", "Trial", "Finding"]


@dataclass
class EffectStart:
    """Where a candidate effect starts (:func:`~torchcal.pipelines.loop.start.effect_start`).

    Attributes:
        effect: the effect restricted to the chosen modes, its ``theta`` at the linear step's
            values; None when nothing is proposed (``reason`` says why).
        params: start values (geometry, then each effect's parameters); free flags of the
            current model plus the effect's.
        effects: the trial's effect list (the current ones it does not supersede, then ``effect``).
        selection: per step of the mode selection, each mode's t and the threshold, in words.
        prior_mm: the geometric prior (mm and mrad) the selection chose with the effect (None: none).
        soft: the soft option's figures when a family is kept whole under a prior (``sigma_mm``,
            ``t``, ``k``, ``pen_hard``, ``pen_soft``), else None.
        aliases: a chosen mode -> the modes the data cannot tell from it.
    """
    effect: object | None
    prior_mm: float | None
    selection: list[str] = field(default_factory=list)
    reason: str = ""
    params: ParamSet | None = None
    effects: list = field(default_factory=list)
    soft: dict | None = None
    aliases: dict[str, list[str]] = field(default_factory=dict)
    info: dict = field(default_factory=dict)


# the keys report.json has shown for each kind of candidate line
_KEYS = {
    "not applicable": ("name", "accepted", "applicable", "reason"),
    "covered": ("name", "reason", "round", "accepted"),
    "not proposed": ("name", "reason", "selection", "round", "accepted"),
    "fitted": ("name", "n_params", "cv_rmse_mm", "cv_gain_mm", "t", "penalised_ok", "modes", "added_modes",
               "extends", "selection", "aliases", "soft", "prior_mm", "round", "accepted", "test_gain_mm"),
    "residual_elm": ("name", "n_params", "cv_rmse_mm", "cv_gain_mm", "t", "penalised_ok", "accepted"),
}


@dataclass
class Candidate(JsonRecord):
    """One candidate effect in one round of the diagnosis, as the report lists it.

    ``kind`` says how far it got: ``"not applicable"`` (the data lack what it reads),
    ``"covered"`` (an accepted family holds its modes), ``"not proposed"`` (no mode passed the
    selection), ``"fitted"`` (fitted and judged by the rule) or ``"residual_elm"``. Figures in mm;
    ``t``: the paired t statistic of the cross-validated score gain; ``penalised_ok``: the
    penalised mean fell too; ``test_gain_mm``: the held-out mean gain, measured after the decision.
    """
    name: str
    kind: str
    reason: str = ""
    accepted: bool = False
    applicable: bool = True
    round: int | None = None
    n_params: int | None = None
    cv_rmse_mm: float | None = None
    cv_gain_mm: float | None = None
    t: float | None = None
    penalised_ok: bool | None = None
    modes: list[str] = field(default_factory=list)
    added_modes: list[str] = field(default_factory=list)
    extends: list[str] = field(default_factory=list)
    selection: list[str] = field(default_factory=list)
    aliases: dict[str, list[str]] = field(default_factory=dict)
    soft: dict | None = None
    prior_mm: float | None = None
    test_gain_mm: float | None = None

    def to_json(self) -> dict:
        out = {k: getattr(self, k) for k in _KEYS[self.kind]}
        if self.kind == "fitted" and self.prior_mm is None:  # a fit without a geometric prior names none
            del out["prior_mm"]
        return out


@dataclass
class Trial:
    """What trying one candidate gave: its report line, the fitted model (None when it was not
    fitted), whether it passed the rule (``ok``) and whether an accepted family covers it."""
    name: str
    line: Candidate
    model: object | None = None
    ok: bool = False
    covered: bool = False
    pruned: list[dict] = field(default_factory=list)


@dataclass
class Finding(JsonRecord):
    """An accepted effect as the report states it.

    Attributes:
        name: the effect; stage: its stage's name (``+name``, with the modes added in a later round).
        joints: the joints it acts on; n_params: its parameters; modes: the modes it keeps;
            added_modes: those this stage added; extends: the effects it replaced.
        cv_gain_mm, test_gain_mm: cross-validated and held-out mean gain (mm; None without held-out rows).
        evidence: the evidence in words; found: the findings in words.
        soft_prior_mm: the Gaussian prior (mm RMS at the markers per mode) a family is kept under, or None.
        aliases: a mode -> the modes the data cannot tell from it.
        params, standard_errors, units: the fitted values, their standard errors, in SI units.
    """
    name: str
    stage: str
    joints: list[str]
    n_params: int
    modes: list[str]
    added_modes: list[str]
    extends: list[str]
    cv_gain_mm: float
    test_gain_mm: float | None
    evidence: str
    found: list[str]
    soft_prior_mm: float | None
    aliases: dict[str, list[str]]
    params: dict[str, float]
    standard_errors: dict[str, float]
    units: dict[str, str]

    def to_json(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}
