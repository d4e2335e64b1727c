"""The comparison statistics (cefc_mj/eval/stats.py) agree with scipy's, and a verdict needs p < 0.05."""

import numpy as np
import pytest
from scipy import stats

from cefc_mj.eval.stats import seed_interval, verdict, welch_p


def test_interval_is_students_t_and_needs_two_seeds():
    x = [3.0, 4.0, 6.0, 5.0, 7.0]
    ci = seed_interval(x)
    half = stats.t.ppf(0.975, 4) * np.std(x, ddof=1) / np.sqrt(5)
    assert ci["mean"] == pytest.approx(5.0) and ci["ci_low"] == pytest.approx(5.0 - half)
    assert ci["ci_high"] == pytest.approx(5.0 + half)
    assert seed_interval([2.0])["ci_low"] is None


def test_welch_and_verdicts():
    a, b = [10.0, 11.0, 12.0, 10.5, 11.5], [5.0, 6.0, 5.5, 6.5, 5.2]
    assert welch_p(a, b) == pytest.approx(stats.ttest_ind(a, b, equal_var=False).pvalue)
    assert verdict(a, b, higher_is_better=True) == "better"
    assert verdict(a, b, higher_is_better=False) == "worse"
    close = [5.1, 6.2, 5.4, 6.4, 5.3]
    assert verdict(close, b, higher_is_better=True) == "no significant difference"
    assert welch_p([1.0], b) is None and verdict([1.0], b, True) == "no significant difference"
