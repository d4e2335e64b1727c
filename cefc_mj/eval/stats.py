"""Statistics over training seeds for the method comparisons (Table V): mean with a 95 % confidence
interval, and the p-value of a Welch t-test against a reference method, both from scipy.stats.

A method "beats" another on a metric only where p < ALPHA on the test games; otherwise the report
says "no significant difference", whatever the sign of the difference. A table compares many methods
with one reference, so `fdr_adjusted` also gives each metric's p-values adjusted over the table's
comparisons (Benjamini-Hochberg, scipy.stats.false_discovery_control): the differences that hold
once about one chance "difference" in twenty comparisons is allowed for."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

ALPHA = 0.05
"""Significance level of the comparisons."""
CONFIDENCE = 0.95
"""Confidence level of the intervals over training seeds."""


def seed_interval(values) -> dict[str, float | int | None]:
    """{"n", "mean", "std", "ci_low", "ci_high"} of per-seed values: Student's t interval of the mean
    (None bounds with fewer than two seeds)."""
    x = np.asarray(values, dtype=np.float64)
    n = int(x.size)
    mean = float(x.mean()) if n else math.nan
    if n < 2:
        return {"n": n, "mean": mean, "std": None, "ci_low": None, "ci_high": None}
    std = float(x.std(ddof=1))
    low, high = stats.t.interval(CONFIDENCE, df=n - 1, loc=mean, scale=std / math.sqrt(n)) if std > 0 else (mean, mean)
    return {"n": n, "mean": mean, "std": std, "ci_low": float(low), "ci_high": float(high)}


def welch_p(values, reference) -> float | None:
    """Two-sided p-value of Welch's t-test between two methods' per-seed values (None with fewer
    than two seeds on either side, or no variance at all)."""
    a, b = np.asarray(values, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.size < 2 or b.size < 2 or (a.std() == 0 and b.std() == 0):
        return None
    return float(stats.ttest_ind(a, b, equal_var=False).pvalue)


def fdr_adjusted(p_values) -> list[float | None]:
    """Benjamini-Hochberg adjusted p-values of a family of comparisons (None entries, comparisons that
    could not be tested, stay None and do not count in the family)."""
    tested = [i for i, p in enumerate(p_values) if p is not None]
    adjusted: list[float | None] = [None] * len(p_values)
    if tested:
        for i, q in zip(tested, stats.false_discovery_control([p_values[i] for i in tested], method="bh")):
            adjusted[i] = float(q)
    return adjusted


def verdict(values, reference, higher_is_better: bool) -> str:
    """ "better" / "worse" (than the reference) where Welch's p < ALPHA, else "no significant difference"."""
    p = welch_p(values, reference)
    if p is None or p >= ALPHA:
        return "no significant difference"
    ahead = float(np.mean(values)) > float(np.mean(reference))
    return "better" if ahead == higher_is_better else "worse"


def paired_difference(values, reference) -> dict[str, float | int | None]:
    """{"n", "mean", "se", "p"} of per-game differences values - reference on the same games: the mean
    difference, its standard error and the two-sided p of the paired t-test (None with fewer than
    two games, or where every difference is the same)."""
    d = np.asarray(values, dtype=np.float64) - np.asarray(reference, dtype=np.float64)
    n = int(d.size)
    if n < 2:
        return {"n": n, "mean": float(d.mean()) if n else math.nan, "se": None, "p": None}
    se = float(d.std(ddof=1) / math.sqrt(n))
    p = float(stats.ttest_rel(values, reference).pvalue) if se > 0 else None
    return {"n": n, "mean": float(d.mean()), "se": se, "p": p}


def weaker_p(values, reference) -> float | None:
    """One-sided p of the paired t-test that `values` are lower than `reference` on average (pairs:
    the same training seed's policy on the same games, e.g. E against an adversary and against a
    rule); None with fewer than two pairs or where every difference is the same."""
    d = np.asarray(values, dtype=np.float64) - np.asarray(reference, dtype=np.float64)
    if d.size < 2 or np.all(d == d[0]):
        return None
    return float(stats.ttest_rel(values, reference, alternative="less").pvalue)
