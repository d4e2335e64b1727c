"""The comparison statistics (cefc_mj/eval/stats.py) agree with scipy's, and a verdict needs p < 0.05."""

import numpy as np
import pytest
from scipy import stats

from cefc_mj.eval.highlevel import SEED_METRICS, _compare_with_reference, _fdr_lines, sitl_fidelity
from cefc_mj.eval.stats import fdr_adjusted, paired_difference, seed_interval, verdict, welch_p


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


def test_paired_difference_is_scipys_paired_t_test():
    a, b = [10.0, 12.0, 9.0, 14.0, 11.0], [9.0, 12.5, 7.0, 12.0, 10.0]
    d = np.subtract(a, b)
    out = paired_difference(a, b)
    assert out["n"] == 5 and out["mean"] == pytest.approx(d.mean())
    assert out["se"] == pytest.approx(d.std(ddof=1) / np.sqrt(5))
    assert out["p"] == pytest.approx(stats.ttest_rel(a, b).pvalue)
    assert paired_difference([1.0], [2.0])["p"] is None
    assert paired_difference([1.0, 2.0], [0.0, 1.0])["p"] is None  # every difference the same


def test_sitl_fidelity_targets():
    """R_t at least 95 % of lock-step; E at most lock-step + one se of the paired difference."""
    ref = {"R_t": np.array([100.0, 200.0]), "E": np.array([100.0, 120.0])}
    close = {"R_t": np.array([96.0, 190.0]), "E": np.array([104.0, 120.0])}
    fid = sitl_fidelity(close, ref, {"E": paired_difference(close["E"], ref["E"])})
    assert fid["R_t_met"] and fid["R_t_share"] == pytest.approx(286 / 300)
    assert fid["E_limit"] == pytest.approx(110.0 + 2.0) and fid["E_met"]
    worse = {"R_t": np.array([90.0, 180.0]), "E": np.array([110.0, 126.0])}
    fid = sitl_fidelity(worse, ref, {"E": paired_difference(worse["E"], ref["E"])})
    assert not fid["R_t_met"] and not fid["E_met"]  # E limit 110 + 2, mean 118


def test_fdr_adjusted_is_benjamini_hochberg_over_the_tested_comparisons():
    # sorted 0.01, 0.03, 0.04, 0.2 -> m/rank x p = 0.04, 0.06, 0.0533, 0.2 -> running minimum from the top
    q = fdr_adjusted([0.01, None, 0.04, 0.03, 0.2])
    assert q[1] is None
    assert q[0] == pytest.approx(0.04) and q[2] == pytest.approx(0.16 / 3) and q[3] == pytest.approx(0.16 / 3)
    assert q[4] == pytest.approx(0.2)
    assert fdr_adjusted([None]) == [None]


def test_a_table_names_only_the_differences_that_survive_the_adjustment():
    """Of two rows that differ from CI-HRL at p < 0.05, only the clear one holds over 4 comparisons."""
    reference = [10.0, 11.0, 12.0, 10.5, 11.5]
    clear = [5.0, 6.0, 5.5, 6.5, 5.2]  # p ~ 1e-5
    borderline = [9.3, 10.4, 9.9, 10.6, 9.4]  # p 0.042, adjusted 0.084
    noise = [10.2, 11.4, 11.6, 10.0, 11.1]
    rows = {
        name: {"training_seeds": {m: values for m in SEED_METRICS}}
        for name, values in {"CI-HRL": reference, "A": clear, "B": borderline, "C": noise, "D": noise}.items()
    }
    _compare_with_reference(rows)
    assert welch_p(borderline, reference) < 0.05 and rows["B"]["vs_reference"]["E"]["verdict"] == "better"
    assert rows["B"]["vs_reference"]["E"]["p_fdr"] > 0.05 > rows["A"]["vs_reference"]["E"]["p_fdr"]
    held = {line.split(":")[0].strip(): line for line in _fdr_lines(rows) if line.startswith("  ")}
    assert set(held) == {"R_H", "R_t", "E"}
    assert "A (better" in held["E"] and "B (" not in held["E"] and "A (worse" in held["R_H"]
