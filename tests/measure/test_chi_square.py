"""The chi-square tail and bound (measure/stats.py) behind "significant" (report/units.py) and the
loop's screening, written without scipy.stats to keep report writing and the loop fast: checked
against scipy's and against the closed forms of 1 and 2 degrees of freedom."""
from __future__ import annotations

import math

import pytest

from torchcal.measure.stats import chi2_isf, chi2_sf
from torchcal.report.units import SIGNIFICANT_Z, significant


def test_the_bound_equals_scipy_and_the_closed_forms():
    alpha = math.erfc(SIGNIFICANT_Z / math.sqrt(2))
    assert chi2_isf(alpha, 1) == pytest.approx(SIGNIFICANT_Z ** 2, rel=1e-12)  # χ²₁ = z²
    assert chi2_isf(0.05, 2) == pytest.approx(-2 * math.log(0.05), rel=1e-12)  # χ²₂ sf = exp(-x/2)
    stats = pytest.importorskip("scipy.stats")
    for k in (1, 2, 3, 7, 24, 61):
        for a in (alpha, 0.05, 1e-6):
            assert chi2_isf(a, k) == pytest.approx(stats.chi2.isf(a, k), rel=1e-11), (k, a)


def test_a_group_is_significant_beyond_the_bound_only():
    alpha = math.erfc(SIGNIFICANT_Z / math.sqrt(2))
    b = chi2_isf(alpha, 4)
    z = math.sqrt(b / 4)
    assert significant([z * 1.01] * 4, [1.0] * 4) and not significant([z * 0.99] * 4, [1.0] * 4)


def test_the_tail_equals_scipy_down_to_the_screening_chances():
    # the screening compares p-values with 0.1 % over thousands of pairs: the far tail must hold too
    stats = pytest.importorskip("scipy.stats")
    for k in (1, 2, 3, 4, 5, 8, 13):
        for x in (0.0, 1e-3, 0.7, 3.0, 20.0, 80.0, 300.0):
            ref = float(stats.chi2.sf(x, k))
            assert chi2_sf(x, k) == pytest.approx(ref, rel=1e-11, abs=1e-300), (k, x)
    assert chi2_sf(2.0, 2) == pytest.approx(math.exp(-1.0), rel=1e-15)
