"""Numbers as reports print them: every quantity in its one display unit (the table is
:func:`torchcal.params.display_unit`), a value with its standard error, time covariates as ISO 8601
dates, and whether a fitted value is significant."""
from __future__ import annotations

import math
from datetime import datetime, timezone

from torchcal.effects.base import TIME_COVARIATES
from torchcal.measure.stats import chi2_isf
from torchcal.params import display_unit

__all__ = ["shown", "with_error", "covariate_value", "is_time", "iso_time", "SIGNIFICANT_Z", "significant",
           "z_score"]

# a finding is stated only when its value lies this many standard errors from zero (two-sided
# chance 0.27 % for one parameter); a group of k parameters uses the chi-square bound of the
# same chance
SIGNIFICANT_Z = 3.0
# epoch seconds after 2000-01-01 are read as dates; smaller "times" are durations or run clocks
_EPOCH_2000 = 946684800.0


def _num(v: float, digits: int) -> str:
    if v == 0 or not math.isfinite(v):
        return f"{v:g}"
    mag = math.floor(math.log10(abs(v)))
    if -4 <= mag < 6:
        return f"{v:.{max(digits - 1 - mag, 0)}f}"
    return f"{v:.{digits - 1}e}"


def shown(value: float | None, unit: str, digits: int = 4) -> tuple[str, str]:
    """``(number, unit)`` of a value given in the SI ``unit``, in that quantity's display unit,
    with ``digits`` significant digits and no exponent between 1e-4 and 1e6 (``"–"`` for None)."""
    f, u = display_unit(unit)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–", u
    return _num(float(value) * f, digits), u


def with_error(value: float, se: float | None, unit: str) -> str:
    """``"4.45 ± 6.2 mrad"``: a value and its standard error in the display unit."""
    v, u = shown(value, unit)
    if se is None or not math.isfinite(se):
        return f"{v} {u} (standard error unknown)"
    e, _ = shown(se, unit, 2)
    return f"{v} ± {e} {u}"


def is_time(covariate: str) -> bool:
    """Whether a covariate is a time (epoch seconds) rather than a temperature."""
    return covariate in TIME_COVARIATES


def iso_time(t: float) -> str:
    """Epoch seconds as an ISO 8601 date and time (UTC, to the second)."""
    return datetime.fromtimestamp(float(t), tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def covariate_value(covariate: str, v: float) -> str:
    """A covariate's value as a person reads it: a time as an ISO 8601 date, a temperature in
    °C / K as given."""
    if is_time(covariate) and abs(float(v)) >= _EPOCH_2000:
        return iso_time(v)
    if is_time(covariate):
        return f"{float(v):.6g} s"
    return f"{float(v):.4g}"


def z_score(value: float, se: float | None) -> float:
    """``|value| / se`` (nan when the standard error is unknown or zero)."""
    if se is None or not math.isfinite(se) or se <= 0:
        return float("nan")
    return abs(float(value)) / float(se)


def significant(values: list[float], ses: list[float | None], z: float = SIGNIFICANT_Z) -> bool:
    """Whether a group of fitted values is significantly non-zero: ``Σ (value / se)²`` beyond the
    chi-square bound whose chance equals that of ``|value| > z·se`` for one value (correlations
    between the values ignored). False when a standard error is unknown."""
    zs = [z_score(v, s) for v, s in zip(values, ses)]
    if not zs or any(math.isnan(x) for x in zs):
        return False
    alpha = math.erfc(z / math.sqrt(2.0))  # two-sided normal tail beyond z
    return bool(sum(x * x for x in zs) > chi2_isf(alpha, len(zs)))
