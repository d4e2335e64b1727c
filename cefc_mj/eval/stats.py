"""Statistics over training seeds for the method comparisons (Table V): mean with a 95 % confidence
interval, and the p-value of a Welch t-test against a reference method, both from scipy.stats.

A method "beats" another on a metric only where p < ALPHA on the test games; otherwise the report
says "no significant difference", whatever the sign of the difference. A table compares many methods
with one reference, so `fdr_adjusted` also gives each metric's p-values adjusted over the table's
comparisons (Benjamini-Hochberg, scipy.stats.false_discovery_control): the differences that hold
once about one chance "difference" in twenty comparisons is allowed for.

"No significant difference" alone cannot say two methods are alike, so the module also has:

- `welch_difference`: the difference of means with its Welch interval;
- `tost_p`: the two one-sided Welch tests (TOST) of equivalence within a margin;
- `comparison_verdict`: "better" / "worse" (difference test p < alpha), "equivalent within +-m"
  (TOST p < alpha) or "undecided (underpowered)", from p-values adjusted as the caller decides
  (`fdr_adjusted`, `holm_adjusted`);
- `minimum_detectable_difference`: the smallest true difference the two-sided test detects with 80 %
  power at given seed counts and a pooled SD (`pooled_sd`), from the noncentral t of Student's
  two-sample test (or the normal approximation); `equivalence_power` for the TOST;
- `noninferiority`: the one-sided paired test that the game's adversary is at most a relative margin
  weaker than the nearest-group rule;
- `iqm_interval`, `improvement_interval`: rliable's interquartile mean and probability of improvement
  with stratified-bootstrap percentile intervals, implemented here with numpy and scipy (rliable 1.2.0
  needs arch < 8, and arch 7.2, the newest it allows, fails to import beside pandas 3). Checked once
  against rliable 1.2.0 (with pandas 2.3): the same point estimates, intervals within the bootstrap's
  noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


# ---------------------------------------------------------------------------- saying "alike"
POWER = 0.80
"""Power at which the minimum detectable difference is stated."""
BOOTSTRAP_REPS = 10_000
"""Resamples of the stratified bootstrap intervals of the aggregates."""
UNDECIDED = "undecided (underpowered)"
"""The verdict where neither a difference nor equivalence within the margin is shown."""


@dataclass(frozen=True)
class WelchDifference:
    """The difference of two methods' means over training seeds with its Welch confidence interval."""

    n: int
    """Seeds of the row compared."""
    n_reference: int
    """Seeds of the reference."""
    difference: float
    """mean(values) - mean(reference)."""
    se: float
    """Its standard error, sqrt(s1^2 / n1 + s2^2 / n2)."""
    df: float
    """Welch-Satterthwaite degrees of freedom."""
    ci_low: float
    """Lower bound of the CONFIDENCE interval of the difference (Student's t with df)."""
    ci_high: float
    """Upper bound of that interval."""


def welch_difference(values, reference, confidence: float = CONFIDENCE) -> WelchDifference | None:
    """The difference of means values - reference and its Welch interval (the interval of
    scipy.stats.ttest_ind(..., equal_var=False)); None with fewer than two seeds on either side or no
    variance at all."""
    a, b = np.asarray(values, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.size < 2 or b.size < 2:
        return None
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    if va + vb == 0:
        return None
    se = math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    d = float(a.mean() - b.mean())
    half = float(stats.t.ppf(0.5 + confidence / 2, df)) * se
    return WelchDifference(int(a.size), int(b.size), d, se, float(df), d - half, d + half)


@dataclass(frozen=True)
class Interaction:
    """A difference of differences over four independent groups of per-seed values, with its Welch
    interval and two-sided p (the budget x method interaction of the second pre-registration)."""

    estimate: float
    """(mean a1 - mean b1) - (mean a2 - mean b2)."""
    se: float
    """sqrt(sum over the four groups of s^2 / n)."""
    df: float
    """Welch-Satterthwaite degrees of freedom of that sum."""
    ci_low: float
    """Lower bound of its CONFIDENCE interval (Student's t with df)."""
    ci_high: float
    """Upper bound."""
    p: float
    """Two-sided p of H0: the interaction is 0."""


def interaction(a1, b1, a2, b2, confidence: float = CONFIDENCE) -> Interaction | None:
    """(a1 - b1) - (a2 - b2) on the groups' means, tested with the Welch-Satterthwaite t (the groups
    independent, variances unequal); None with fewer than two seeds in a group or no variance."""
    groups = [np.asarray(g, dtype=np.float64) for g in (a1, b1, a2, b2)]
    if any(g.size < 2 for g in groups):
        return None
    v = [g.var(ddof=1) / g.size for g in groups]
    if sum(v) == 0:
        return None
    se = math.sqrt(sum(v))
    df = sum(v) ** 2 / sum(vi**2 / (g.size - 1) for vi, g in zip(v, groups))
    means = [float(g.mean()) for g in groups]
    estimate = (means[0] - means[1]) - (means[2] - means[3])
    half = float(stats.t.ppf(0.5 + confidence / 2, df)) * se
    p = float(2 * stats.t.sf(abs(estimate) / se, df))
    return Interaction(estimate, se, float(df), estimate - half, estimate + half, p)


def tost_p(values, reference, margin: float) -> float | None:
    """p of the two one-sided Welch tests (TOST) that |mean(values) - mean(reference)| < margin: the
    larger of the one-sided p's against H0 difference <= -margin and H0 difference >= +margin (p <
    alpha exactly when the 1 - 2 alpha Welch interval lies inside +-margin). None where `welch_p` is."""
    if not margin > 0:
        raise ValueError(f"margin={margin!r}: must be > 0")
    a, b = np.asarray(values, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if welch_p(a, b) is None:
        return None
    lower = stats.ttest_ind(a + margin, b, equal_var=False, alternative="greater").pvalue
    upper = stats.ttest_ind(a - margin, b, equal_var=False, alternative="less").pvalue
    return float(max(lower, upper))


def comparison_verdict(
    difference: float | None,
    p_difference: float | None,
    p_equivalence: float | None,
    higher_is_better: bool,
    margin_text: str = "the margin",
    alpha: float = ALPHA,
) -> str:
    """One row against the reference from (possibly adjusted) p-values: "better" / "worse" where the
    difference test's p < alpha (by the sign of `difference`), else "equivalent within <margin_text>"
    where the equivalence test's p < alpha, else UNDECIDED. A significant difference inside the
    margin still reads "better"/"worse". The two tests' null hypotheses (difference 0; |difference| >=
    margin) cannot both be true, so reading both at alpha adds no false claim per metric."""
    if p_difference is not None and p_difference < alpha and difference is not None and difference != 0:
        return "better" if (difference > 0) == higher_is_better else "worse"
    if p_equivalence is not None and p_equivalence < alpha:
        return f"equivalent within {margin_text}"
    return UNDECIDED


def holm_adjusted(p_values) -> list[float | None]:
    """Holm's step-down adjusted p-values (family-wise error) of a family of comparisons; None
    entries stay None and do not count in the family."""
    tested = [i for i, p in enumerate(p_values) if p is not None]
    adjusted: list[float | None] = [None] * len(p_values)
    running = 0.0
    m = len(tested)
    for rank, i in enumerate(sorted(tested, key=lambda i: p_values[i])):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        adjusted[i] = float(running)
    return adjusted


def pooled_sd(groups) -> tuple[float, int]:
    """(SD, degrees of freedom) pooled over groups of per-seed values: sqrt(sum (n_i - 1) s_i^2 /
    sum (n_i - 1)); groups of one value add nothing. ValueError where no group has two values."""
    squares, df = 0.0, 0
    for values in groups:
        x = np.asarray(values, dtype=np.float64)
        if x.size >= 2:
            squares += float(((x - x.mean()) ** 2).sum())
            df += x.size - 1
    if df == 0:
        raise ValueError("pooled_sd: no group has two values")
    return math.sqrt(squares / df), df


def two_sample_power(
    delta: float, n: int, n_reference: int, sd: float, alpha: float = ALPHA, method: str = "t"
) -> float:
    """Power of the two-sided two-sample t-test at level alpha to detect a true difference `delta`
    between groups of n and n_reference with common SD `sd`. method "t": the noncentral t of Student's
    test (df n + n_reference - 2, noncentrality delta / (sd sqrt(1/n + 1/n_reference)), both tails);
    "normal": the normal approximation (z in place of t)."""
    if n < 2 or n_reference < 2 or not sd > 0:
        raise ValueError(f"two_sample_power: needs n >= 2 per group and sd > 0 (n={n}, {n_reference}, sd={sd})")
    ncp = abs(delta) / (sd * math.sqrt(1 / n + 1 / n_reference))
    if method == "normal":
        z = stats.norm.ppf(1 - alpha / 2)
        return float(stats.norm.sf(z - ncp) + stats.norm.cdf(-z - ncp))
    if method != "t":
        raise ValueError(f"method={method!r}: must be 't' or 'normal'")
    df = n + n_reference - 2
    crit = stats.t.ppf(1 - alpha / 2, df)
    # The lower tail P(T < -crit) as P(T' > crit) of the mirrored noncentrality: the same number, but
    # scipy's nct.cdf returns NaN there for some large noncentralities at few df (e.g. df 2, ncp 10).
    return float(stats.nct.sf(crit, df, ncp) + stats.nct.sf(crit, df, -ncp))


def minimum_detectable_difference(
    n: int, n_reference: int, sd: float, alpha: float = ALPHA, power: float = POWER, method: str = "t"
) -> float:
    """The smallest true difference that the two-sided two-sample test at level alpha detects with
    probability `power`, for n and n_reference seeds with common SD `sd` (`two_sample_power`'s
    methods). "normal": (z_{1 - alpha/2} + z_power) sd sqrt(1/n + 1/n_reference); "t" solves the
    noncentral t's power for the difference (slightly larger at few seeds). Welch's test, which the
    comparisons run, has at most Student's df, so its MDD is at least this."""
    if not 0 < power < 1:
        raise ValueError(f"power={power!r}: must be in (0, 1)")
    scale = sd * math.sqrt(1 / n + 1 / n_reference)
    normal = float((stats.norm.ppf(1 - alpha / 2) + stats.norm.ppf(power)) * scale)
    two_sample_power(normal, n, n_reference, sd, alpha, method)  # checks n, sd and method
    if method == "normal":
        return normal
    from scipy.optimize import brentq

    high = normal
    while two_sample_power(high, n, n_reference, sd, alpha) < power:  # the t's MDD exceeds the normal's
        high *= 1.25
    return float(brentq(lambda d: two_sample_power(d, n, n_reference, sd, alpha) - power, normal, high))


def equivalence_power(
    n: int, n_reference: int, sd: float, margin: float, alpha: float = ALPHA, delta: float = 0.0
) -> float:
    """Approximate power of the TOST (equivalence within +-margin at level alpha) where the true
    difference is `delta` (default none), common SD `sd`: P(T_df > t_{1-alpha} - (margin - delta)/se) +
    P(T_df > t_{1-alpha} - (margin + delta)/se) - 1, at least 0 (the standard shifted-t
    approximation, df n + n_reference - 2, se = sd sqrt(1/n + 1/n_reference))."""
    if n < 2 or n_reference < 2 or not sd > 0 or not margin > 0:
        raise ValueError("equivalence_power: needs n >= 2 per group, sd > 0 and margin > 0")
    df = n + n_reference - 2
    se = sd * math.sqrt(1 / n + 1 / n_reference)
    crit = stats.t.ppf(1 - alpha, df)
    p = stats.t.cdf((margin - abs(delta)) / se - crit, df) + stats.t.cdf((margin + abs(delta)) / se - crit, df) - 1
    return float(max(0.0, p))


@dataclass(frozen=True)
class NonInferiority:
    """Whether a game's adversary is at most `margin` (relative) weaker than a reference adversary (the
    nearest-group rule) against one method: a one-sided paired t-test over training seeds."""

    margin: float
    """Relative margin m: H0 mean E(adversary) <= (1 - m) mean E(rule); H1 the opposite."""
    n: int
    """Pairs (training seeds)."""
    ratio: float | None
    """mean E(adversary) / mean E(rule) (None where the rule's mean is 0)."""
    p: float | None
    """One-sided p of the paired t-test on E(adversary) - (1 - m) E(rule) > 0 (None with fewer than two
    pairs or every difference the same)."""
    verdict: str
    """"non-inferior within <m>" where p < ALPHA, else "non-inferiority not shown"."""


def noninferiority(values, reference, margin: float, alpha: float = ALPHA) -> NonInferiority:
    """The one-sided paired non-inferiority test of `values` (E against the adversary, per training
    seed) against `reference` (E against the rule, the same seeds and games): H0 mean(values) <= (1 -
    margin) mean(reference), rejected where the paired differences values - (1 - margin) reference
    are significantly above 0 (scipy.stats.ttest_1samp, alternative "greater")."""
    if not 0 <= margin < 1:
        raise ValueError(f"margin={margin!r}: must be in [0, 1)")
    a, b = np.asarray(values, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"noninferiority: {a.size} values against {b.size} reference values; pairs needed")
    d = a - (1 - margin) * b
    p = None
    if d.size >= 2 and not np.all(d == d[0]):
        p = float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)
    ratio = float(a.mean() / b.mean()) if a.size and b.mean() != 0 else None
    shown = p is not None and p < alpha
    verdict = f"non-inferior within {100 * margin:g} %" if shown else "non-inferiority not shown"
    return NonInferiority(float(margin), int(d.size), ratio, p, verdict)


# ---------------------------------------------------------------------------- aggregates (rliable's)
@dataclass(frozen=True)
class BootstrapInterval:
    """A point estimate with its percentile interval from a stratified bootstrap over runs."""

    estimate: float
    """The statistic on the scores as they are."""
    ci_low: float
    """Lower percentile bound (CONFIDENCE interval)."""
    ci_high: float
    """Upper percentile bound."""
    reps: int
    """Bootstrap resamples."""


def _runs_by_tasks(scores) -> np.ndarray:
    """Scores as [runs, tasks] (a 1-D array is one task)."""
    x = np.asarray(scores, dtype=np.float64)
    x = x[:, None] if x.ndim == 1 else x
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"scores: expected [runs] or [runs, tasks], got shape {np.shape(scores)}")
    return x


def iqm(scores) -> float:
    """Interquartile mean over every run and task (rliable's aggregate_iqm: the mean after cutting
    25 % of the scores at each end, scipy.stats.trim_mean)."""
    return float(stats.trim_mean(_runs_by_tasks(scores).ravel(), 0.25))


def probability_of_improvement(x, y) -> float:
    """P(X > Y) of rliable: per task the probability that a run of x scores above a run of y (ties
    count half; the Mann-Whitney U over n_x n_y), averaged over tasks. Higher scores are better:
    negate a lower-is-better metric first."""
    a, b = _runs_by_tasks(x), _runs_by_tasks(y)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"probability_of_improvement: {a.shape[1]} tasks against {b.shape[1]}")
    return float(_improvement(a[None], b[None])[0])


def _improvement(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[reps] P(X > Y) of resampled score arrays a [reps, n, tasks] and b [reps, m, tasks]."""
    diff = a[:, :, None, :] - b[:, None, :, :]  # [reps, n, m, tasks]
    per_task = ((diff > 0) + 0.5 * (diff == 0)).mean(axis=(1, 2))
    return per_task.mean(axis=-1)


def _resample(x: np.ndarray, reps: int, rng: np.random.Generator) -> np.ndarray:
    """[reps, runs, tasks]: runs drawn with replacement within each task (the stratified bootstrap)."""
    runs, tasks = x.shape
    idx = rng.integers(0, runs, size=(reps, runs, tasks))
    return np.take_along_axis(np.broadcast_to(x, (reps, runs, tasks)), idx, axis=1)


def _interval(estimate: float, draws: np.ndarray, reps: int, confidence: float) -> BootstrapInterval:
    low, high = np.percentile(draws, [50 * (1 - confidence), 50 * (1 + confidence)])
    return BootstrapInterval(float(estimate), float(low), float(high), int(reps))


def iqm_interval(scores, reps: int = BOOTSTRAP_REPS, confidence: float = CONFIDENCE, seed: int = 0):
    """The IQM of scores [runs] or [runs, tasks] with its percentile interval from the stratified
    bootstrap (runs resampled within each task), as rliable's get_interval_estimates reports it."""
    x = _runs_by_tasks(scores)
    draws = _resample(x, reps, np.random.default_rng(seed)).reshape(reps, -1)
    return _interval(iqm(x), stats.trim_mean(draws, 0.25, axis=1), reps, confidence)


def improvement_interval(x, y, reps: int = BOOTSTRAP_REPS, confidence: float = CONFIDENCE, seed: int = 0):
    """`probability_of_improvement(x, y)` with its percentile interval from the stratified bootstrap,
    x's and y's runs resampled independently within each task (rliable's
    StratifiedIndependentBootstrap)."""
    a, b = _runs_by_tasks(x), _runs_by_tasks(y)
    rng = np.random.default_rng(seed)
    draws = np.concatenate(
        [  # in chunks, so that [reps, n, m, tasks] stays small
            _improvement(_resample(a, k, rng), _resample(b, k, rng))
            for k in [min(1000, reps - s) for s in range(0, reps, 1000)]
        ]
    )
    return _interval(probability_of_improvement(a, b), draws, reps, confidence)
