"""The comparison statistics (cefc_mj/eval/stats.py) agree with scipy's, and a verdict needs p < 0.05;
equivalence, power, non-inferiority and the rliable-style aggregates against known values, hand
computations and simulations; Table V's comparison fields."""

import json

import numpy as np
import pytest
from scipy import stats

from cefc_mj import paths
from cefc_mj.eval.highlevel_comparison import SEED_METRICS, _compare_with_reference, add_comparisons
from cefc_mj.eval.highlevel_report import (
    _fdr_lines,
    _unadjusted_lines,
    aggregate_lines,
    equivalence_lines,
    paired_lines,
    table5_markdown,
)
from cefc_mj.eval.highlevel_sitl import sitl_fidelity
from cefc_mj.eval.stats import (
    UNDECIDED,
    comparison_verdict,
    equivalence_power,
    fdr_adjusted,
    holm_adjusted,
    improvement_interval,
    iqm,
    iqm_interval,
    minimum_detectable_difference,
    noninferiority,
    paired_difference,
    pooled_sd,
    probability_of_improvement,
    seed_interval,
    tost_p,
    two_sample_power,
    verdict,
    welch_difference,
    welch_p,
)


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
    assert set(held) == set(SEED_METRICS)  # every compared metric, not only the printed p columns
    below = {line.split(":")[0].strip(): line for line in _unadjusted_lines(rows) if line.startswith("  ")}
    assert set(below) == set(SEED_METRICS) and "B (better" in below["E"] and "A (better" in below["E"]
    assert "A (better" in held["E"] and "B (" not in held["E"] and "A (worse" in held["R_H"]


# ---------------------------------------------------------------------------- saying "alike"
def test_welch_difference_is_scipys_interval():
    a, b = [10.0, 11.0, 12.0, 10.5, 11.5], [5.0, 6.0, 5.5, 6.5, 5.2, 7.0]
    d = welch_difference(a, b)
    res = stats.ttest_ind(a, b, equal_var=False)
    ci = res.confidence_interval(0.95)
    assert d.difference == pytest.approx(np.mean(a) - np.mean(b)) and d.df == pytest.approx(res.df)
    assert (d.ci_low, d.ci_high) == (pytest.approx(ci.low), pytest.approx(ci.high))
    assert d.se == pytest.approx(np.sqrt(np.var(a, ddof=1) / 5 + np.var(b, ddof=1) / 6))
    assert (d.n, d.n_reference) == (5, 6)
    assert welch_difference([1.0], b) is None and welch_difference([1.0, 1.0], [2.0, 2.0]) is None


def test_tost_is_two_one_sided_welch_tests_and_the_90_percent_interval():
    reference = [10.0, 11.0, 12.0, 10.5, 11.5, 10.8]
    alike = [10.9, 11.2, 10.6, 11.3, 11.0, 10.7]  # mean difference +0.05
    p = tost_p(alike, reference, margin=1.0)
    lower = stats.ttest_ind(np.add(alike, 1.0), reference, equal_var=False, alternative="greater").pvalue
    upper = stats.ttest_ind(np.subtract(alike, 1.0), reference, equal_var=False, alternative="less").pvalue
    assert p == pytest.approx(max(lower, upper)) and p < 0.05  # equivalent within +-1
    ci90 = welch_difference(alike, reference, confidence=0.90)
    assert -1.0 < ci90.ci_low and ci90.ci_high < 1.0
    assert tost_p(alike, reference, margin=0.3) > 0.05  # not within +-0.3: the 90 % interval is wider
    assert tost_p([15.0, 16.0, 15.5, 16.2], reference, margin=1.0) > 0.99  # 4.8 apart: far from equivalent
    # the boundary: equivalent at level alpha exactly when the 1 - 2 alpha interval lies inside the margin
    for margin in (0.4, 0.6, 0.8):
        inside = -margin < ci90.ci_low and ci90.ci_high < margin
        assert (tost_p(alike, reference, margin) < 0.05) == inside
    assert tost_p([1.0], reference, 1.0) is None
    with pytest.raises(ValueError, match="margin"):
        tost_p(alike, reference, 0.0)


def test_the_verdict_reads_difference_then_equivalence_then_undecided():
    assert comparison_verdict(2.0, 0.01, 0.9, higher_is_better=True) == "better"
    assert comparison_verdict(2.0, 0.01, 0.9, higher_is_better=False) == "worse"
    assert comparison_verdict(-0.2, 0.01, 0.01, True, "±1.5 s") == "worse"  # a difference inside the margin
    assert comparison_verdict(0.1, 0.40, 0.01, False, "±1.5 s") == "equivalent within ±1.5 s"
    assert comparison_verdict(0.1, 0.40, 0.30, False, "±1.5 s") == UNDECIDED == "undecided (underpowered)"
    assert comparison_verdict(None, None, None, True) == UNDECIDED


def test_holm_and_pooled_sd_by_hand():
    # sorted 0.01, 0.03, 0.04 -> 3 x 0.01, 2 x 0.03, 1 x 0.04 = 0.03, 0.06, 0.04 -> running maximum
    assert holm_adjusted([0.01, None, 0.04, 0.03]) == [pytest.approx(0.03), None, pytest.approx(0.06), 0.06]
    assert holm_adjusted([0.6, 0.7]) == [1.0, 1.0] and holm_adjusted([None]) == [None]
    sd, df = pooled_sd([[1.0, 3.0], [2.0, 4.0, 6.0], [7.0]])  # squares 2 + 8 over 1 + 2 df
    assert df == 3 and sd == pytest.approx(np.sqrt(10 / 3))
    with pytest.raises(ValueError):
        pooled_sd([[1.0], [2.0]])


def test_power_and_mdd_against_a_textbook_value_and_a_simulation():
    # R's power.t.test(n = 20, delta = 1, sd = 1) gives power 0.8689528 (two-sample, two-sided, 0.05)
    assert two_sample_power(1.0, 20, 20, 1.0) == pytest.approx(0.8689528, abs=2e-6)
    normal = minimum_detectable_difference(5, 20, 1.7, method="normal")
    assert normal == pytest.approx((stats.norm.ppf(0.975) + stats.norm.ppf(0.8)) * 1.7 * np.sqrt(1 / 5 + 1 / 20))
    # few seeds at a strict level: scipy's noncentral t cdf is NaN there, the power is not
    assert 0.9 < two_sample_power(1000.0, 2, 2, 100.0, alpha=0.025) < 1.0
    assert minimum_detectable_difference(2, 2, 100.0, alpha=0.025) > minimum_detectable_difference(2, 2, 100.0)
    mdd = minimum_detectable_difference(5, 5, 1.7)
    assert two_sample_power(mdd, 5, 5, 1.7) == pytest.approx(0.8) and mdd > minimum_detectable_difference(
        5, 5, 1.7, method="normal"
    )
    # at the MDD, Student's test rejects in 80 % of simulated experiments
    rng = np.random.default_rng(0)
    a = rng.normal(mdd, 1.7, size=(20000, 5))
    b = rng.normal(0.0, 1.7, size=(20000, 5))
    rejected = stats.ttest_ind(a, b, axis=1).pvalue < 0.05
    assert rejected.mean() == pytest.approx(0.8, abs=0.015)
    # the TOST's power at a true difference of 0, against the same kind of simulation (Welch's TOST)
    a, b = rng.normal(0, 1.0, size=(4000, 20)), rng.normal(0, 1.0, size=(4000, 20))
    lower = stats.ttest_ind(a + 0.8, b, axis=1, equal_var=False, alternative="greater").pvalue
    upper = stats.ttest_ind(a - 0.8, b, axis=1, equal_var=False, alternative="less").pvalue
    simulated = (np.maximum(lower, upper) < 0.05).mean()
    assert equivalence_power(20, 20, 1.0, 0.8) == pytest.approx(simulated, abs=0.03)
    with pytest.raises(ValueError):
        minimum_detectable_difference(1, 5, 1.0)


def test_noninferiority_is_a_one_sided_paired_test_of_the_shifted_differences():
    rule = np.array([130.0, 150.0, 140.0, 160.0, 145.0])
    adversary = np.array([128.0, 149.0, 141.0, 155.0, 146.0])  # 0.99 of the rule: within 10 %
    test = noninferiority(adversary, rule, 0.10)
    shifted = adversary - 0.9 * rule
    assert test.p == pytest.approx(stats.ttest_1samp(shifted, 0.0, alternative="greater").pvalue)
    assert test.p < 0.05 and test.verdict == "non-inferior within 10 %" and test.n == 5
    assert test.ratio == pytest.approx(adversary.mean() / rule.mean())
    weak = noninferiority(0.8 * rule + np.array([1.0, -2.0, 0.5, 1.5, -1.0]), rule, 0.10)  # 0.8 of the rule
    assert weak.p > 0.5 and weak.verdict == "non-inferiority not shown"
    assert noninferiority([1.0], [1.0], 0.1).p is None
    with pytest.raises(ValueError, match="pairs"):
        noninferiority([1.0, 2.0], [1.0], 0.1)


def test_iqm_and_probability_of_improvement_by_hand():
    # 8 scores, sorted -50, 1, 2, 3, 4, 5, 6, 100: trim 2 at each end -> mean of 2, 3, 4, 5
    assert iqm([100.0, 1.0, 5.0, 3.0, 6.0, 4.0, 2.0, -50.0]) == pytest.approx(3.5)
    assert iqm([[1.0, 2.0], [3.0, 4.0]]) == pytest.approx(2.5)  # runs x tasks: every score counts
    # x = 1, 3, 5 against y = 2, 3: (1, 2) 0, (1, 3) 0, (3, 2) 1, (3, 3) a tie 0.5, (5, 2) 1, (5, 3) 1
    assert probability_of_improvement([1.0, 3.0, 5.0], [2.0, 3.0]) == pytest.approx((0 + 0 + 1 + 0.5 + 1 + 1) / 6)
    # two tasks averaged: task 1 x always above (1), task 2 never (0)
    assert probability_of_improvement([[5.0, 0.0], [6.0, 1.0]], [[1.0, 9.0]]) == pytest.approx(0.5)


def test_the_stratified_bootstrap_by_hand():
    """Two runs: a resample is (a, a), (a, b), (b, a) or (b, b), so its IQM (= mean) is a, the midpoint or
    b with chances 1/4, 1/2, 1/4: the 95 % percentile interval is [a, b]; each task resamples its own."""
    out = iqm_interval([2.0, 6.0], reps=4000, seed=1)
    assert out.estimate == 4.0 and (out.ci_low, out.ci_high) == (2.0, 6.0) and out.reps == 4000
    draws = stats.trim_mean(np.array([2.0, 6.0])[np.random.default_rng(1).integers(0, 2, (4000, 2))], 0.25, axis=1)
    assert np.isclose(draws, 4.0).mean() == pytest.approx(0.5, abs=0.03)
    same = iqm_interval([[2.0, 10.0], [6.0, 10.0]], reps=2000)  # a task with no spread narrows nothing
    assert (same.ci_low, same.ci_high) == (6.0, 8.0)  # (2 + 10) / 2 and (6 + 10) / 2
    poi = improvement_interval([3.0, 4.0], [1.0, 2.0], reps=2500)  # every x above every y
    assert (poi.estimate, poi.ci_low, poi.ci_high) == (1.0, 1.0, 1.0)
    mixed = improvement_interval([1.0, 3.0], [2.0], reps=2500, seed=3)
    assert mixed.estimate == 0.5 and (mixed.ci_low, mixed.ci_high) == (0.0, 1.0)
    assert improvement_interval([1.0, 3.0], [2.0], reps=2500, seed=3) == mixed  # seeded


def test_table5_comparison_fields_verdicts_and_primary():
    """Every row against CI-HRL: difference, Welch and TOST p with their BH adjustments, MDD from the
    pooled SD, the verdict; the primary pair Holm-adjusted; the aggregates; all JSON."""
    rng = np.random.default_rng(0)
    reference = 150 + rng.normal(0, 5, 20)  # E in steps: margin 15
    rows = {
        "CI-HRL": reference,
        "MAPPO+AT-M": 151 + rng.normal(0, 5, 20),  # alike: equivalent within +-1.5 s
        "A": 190 + rng.normal(0, 5, 5),  # far worse
        "B": 155 + rng.normal(0, 30, 3),  # noisy: undecided
    }
    result = {"protocol": {"seed": 10000}, "rows": {}}
    for name, e in rows.items():
        seeds = {m: list(e) for m in SEED_METRICS} | {"seeds": list(range(len(e)))}
        result["rows"][name] = {"training_seeds": seeds, "against_rule": {"E": list(np.asarray(e) / 1.05)}}
    add_comparisons(result)
    vs = {name: row.get("vs_reference") for name, row in result["rows"].items()}
    assert vs["CI-HRL"] is None
    assert vs["MAPPO+AT-M"]["E"]["decision"] == "equivalent within ±1.5 s"
    assert vs["A"]["E"]["decision"] == "worse" and vs["A"]["R_H"]["decision"] == "better"  # higher R_H is better
    assert vs["B"]["E"]["decision"] == UNDECIDED
    e = vs["MAPPO+AT-M"]["E"]
    assert e["tost_p"] == pytest.approx(tost_p(rows["MAPPO+AT-M"], reference, 15.0)) and e["margin"] == 15.0
    assert e["difference"]["difference"] == pytest.approx(rows["MAPPO+AT-M"].mean() - reference.mean())
    tests = [vs[n]["E"]["tost_p"] for n in ("MAPPO+AT-M", "A", "B")]
    assert [vs[n]["E"]["tost_p_fdr"] for n in ("MAPPO+AT-M", "A", "B")] == fdr_adjusted(tests)
    assert vs["MAPPO+AT-M"]["R_t"]["tost_p"] is None  # no margin for R_t: no equivalence test
    sd, df = pooled_sd(rows.values())
    assert result["comparison"]["pooled_sd"]["E"] == {"sd": pytest.approx(sd), "df": df}
    assert vs["A"]["E"]["mdd"] == pytest.approx(minimum_detectable_difference(5, 20, sd))
    primary = result["comparison"]["primary"]
    assert primary["E"]["p_holm"] == holm_adjusted([e["p"], vs["MAPPO+AT-M"]["R_H"]["p"]])[0]
    assert primary["E"]["decision"] == "equivalent within ±1.5 s"
    agg = result["comparison"]["aggregates"]
    assert agg["E"]["iqm"]["CI-HRL"]["estimate"] == pytest.approx(iqm(reference))
    poi = probability_of_improvement(-reference, -rows["MAPPO+AT-M"])  # lower E is better
    assert agg["E"]["probability_of_improvement"]["estimate"] == pytest.approx(poi)
    assert result["rows"]["A"]["adversary_noninferiority"]["verdict"] == "non-inferior within 10 %"
    json.dumps(result)  # every field is JSON
    text = "\n".join(equivalence_lines(result) + aggregate_lines(result))
    assert "MAPPO+AT-M" in text and "equivalent within ±1.5 s" in text and "Minimum detectable difference" in text
    assert "Primary comparison (docs/research/preregistration.md; exploratory here: batch seed 10000" in text


def test_same_runs_are_paired_and_the_mdd_is_given_at_the_holm_level_with_the_margins_units():
    """CI-HRL-wo-FT is CI-HRL's runs before fine-tuning: besides Welch's test it gets the paired t-test
    over the seeds, which sees a shift that the spread between seeds hides from Welch's; the primary
    comparison's MDD at Holm's first level (alpha / 2) is above the unadjusted one; margins carry units."""
    rng = np.random.default_rng(3)
    reference = 150 + rng.normal(0, 10, 20)
    rows = {
        "CI-HRL": reference,
        "CI-HRL-wo-FT": reference + 2 + rng.normal(0, 1, 20),
        "MAPPO+AT-M": 152 + rng.normal(0, 10, 20),
    }
    result = {"protocol": {"seed": 10000}, "rows": {}}
    for name, e in rows.items():
        seeds = {m: list(e) for m in SEED_METRICS} | {"seeds": list(range(100, 120))}
        result["rows"][name] = {"training_seeds": seeds, "policy": f"{name}_seed100.pt"}
    add_comparisons(result)
    wo_ft = result["rows"]["CI-HRL-wo-FT"]["vs_reference"]
    paired = wo_ft["paired"]["E"]
    assert wo_ft["paired"]["method"] == "CI-HRL" and paired["p"] == pytest.approx(
        stats.ttest_rel(rows["CI-HRL-wo-FT"], reference).pvalue
    )
    assert paired["p"] < 0.001 and wo_ft["E"]["p"] > 0.05  # the pairing is what finds the shift
    low, high = stats.t.interval(0.95, 19, loc=paired["mean"], scale=paired["se"])
    assert (paired["ci_low"], paired["ci_high"]) == (pytest.approx(low), pytest.approx(high))
    assert "paired" not in result["rows"]["MAPPO+AT-M"]["vs_reference"]
    assert result["comparison"]["paired"]["rows"] == ["CI-HRL-wo-FT"]
    text = "\n".join(paired_lines(result))
    assert "Paired (the same runs): CI-HRL-wo-FT is CI-HRL's 20 training runs" in text
    assert f"E {paired['mean'] * 0.1:+.2f} s [{low * 0.1:.2f}, {high * 0.1:.2f}], p {paired['p']:.3f}" in text
    holm = result["comparison"]["primary"]["mdd_holm"]
    sd = result["comparison"]["pooled_sd"]["E"]["sd"]
    assert holm["alpha"] == 0.025 and holm["E"] == pytest.approx(minimum_detectable_difference(20, 20, sd, alpha=0.025))
    assert holm["E"] > result["rows"]["MAPPO+AT-M"]["vs_reference"]["E"]["mdd"]
    lines = "\n".join(equivalence_lines(result))
    assert "Minimum detectable difference, unadjusted" in lines and f"E {holm['E'] * 0.1:.2f} s" in lines
    assert "at the Holm level of the primary comparison (alpha 0.025" in lines
    assert (
        result["comparison"]["margins"]["E"]["value"] == 15.0
        and "steps" in result["comparison"]["margins"]["E"]["unit"]
    )
    assert result["rows"]["CI-HRL"]["episodes_of"] == {
        "training_seed": 100,
        "policy": "CI-HRL_seed100.pt",
        "what": result["rows"]["CI-HRL"]["episodes_of"]["what"],
    }
    # not the same seeds: not the same runs, no paired test
    result["rows"]["CI-HRL-wo-FT"]["training_seeds"]["seeds"] = list(range(200, 220))
    assert "paired" not in add_comparisons(result)["rows"]["CI-HRL-wo-FT"]["vs_reference"]


def test_the_shipped_table5_reanalysed_is_underpowered_not_alike():
    """The shipped report's rows re-analysed (nothing flown): no row is better, worse or equivalent on E
    after the adjustment, and the pooled SD of E is the 1.7 s the docs cite."""
    result = add_comparisons(json.loads((paths.EVAL_DIR / "reports" / "table5.json").read_text()))
    assert result["comparison"]["pooled_sd"]["E"]["sd"] * 0.1 == pytest.approx(1.69, abs=0.005)
    decisions = {row["vs_reference"]["E"]["decision"] for row in result["rows"].values() if "vs_reference" in row}
    assert decisions == {UNDECIDED}
    assert result["rows"]["CI-HRL-w-CL-M"]["adversary_noninferiority"]["verdict"] == "non-inferiority not shown"


def test_table5_markdown_has_a_row_per_method_with_its_verdicts():
    """The report's Markdown table (what the README quotes): one row per method in the report's order,
    its seed count, the verdict cells equal to the comparison's decisions, CI-HRL the reference, the
    primary comparison below."""
    result = add_comparisons(json.loads((paths.EVAL_DIR / "reports" / "table5.json").read_text()))
    table, _, primary = table5_markdown(result).partition("\n\n")
    lines = table.splitlines()
    assert len(lines) == 2 + len(result["rows"]) and lines[1] == "|" + "---|" * 13
    for line, (method, row) in zip(lines[2:], result["rows"].items()):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[0].strip("*") == method and cells[1] == str(len(row["training_seeds"]["seeds"]))
        if method == "CI-HRL":
            assert cells[6] == cells[9] == "reference"
        else:
            assert (cells[8], cells[11]) == (
                row["vs_reference"]["E"]["decision"],
                row["vs_reference"]["R_H"]["decision"],
            )
    primary_head = "Primary comparison (docs/research/preregistration.md; exploratory here: batch seed 10000"
    assert primary.startswith(primary_head)
    assert table5_markdown({"rows": {}}) == ""


def test_interaction_is_the_difference_of_differences_with_the_welch_satterthwaite_t():
    from cefc_mj.eval.stats import interaction

    rng = np.random.default_rng(4)
    groups = [
        rng.normal(mu, sd, n) for mu, sd, n in ((10.0, 2.0, 12), (8.0, 1.0, 10), (13.0, 1.5, 20), (12.5, 2.5, 20))
    ]
    got = interaction(*groups)
    means = [g.mean() for g in groups]
    v = [g.var(ddof=1) / g.size for g in groups]
    assert got.estimate == pytest.approx((means[0] - means[1]) - (means[2] - means[3]))
    assert got.se == pytest.approx(np.sqrt(sum(v)))
    assert got.df == pytest.approx(sum(v) ** 2 / sum(x**2 / (g.size - 1) for x, g in zip(v, groups)))
    assert got.p == pytest.approx(2 * stats.t.sf(abs(got.estimate) / got.se, got.df))
    assert got.ci_low < got.estimate < got.ci_high
    # Two groups only (a2, b2 constant offsets of a1, b1 with the same spread): I is the Welch difference
    # of (a1 - b1) less a known shift, so no interaction is found when the gap is the same in both.
    same = interaction(groups[0], groups[1], groups[0] + 3.0, groups[1] + 3.0)
    assert same.estimate == pytest.approx(0.0, abs=1e-12) and same.p == pytest.approx(1.0)
    assert interaction([1.0], [2.0, 3.0], [1.0, 2.0], [2.0, 3.0]) is None


def test_the_paper_schedule_sample_size_follows_its_pre_registered_rule():
    from cefc_mj.eval.prereg import PAPER_MIN_SEEDS, paper_planned_runs, paper_seed_count
    from cefc_mj.eval.stats import two_sample_power

    assert paper_seed_count(0.5, 4) == PAPER_MIN_SEEDS == 10  # never fewer than 10
    n = paper_seed_count(3.0, 4)
    upper = 3.0 * np.sqrt(4 / stats.chi2.ppf(0.2, 4))  # the one-sided 80 % upper limit, a factor of 1.56
    assert upper == pytest.approx(3.0 * 1.56, rel=0.01)
    assert (
        two_sample_power(4.3, n, n, upper, alpha=0.025) >= 0.9 > two_sample_power(4.3, n - 1, n - 1, upper, alpha=0.025)
    )
    runs = paper_planned_runs(n)
    assert (
        len(runs) == 2 * n and runs[0][0] == "cihrl_consmac_a_seed400" and runs[-1][0] == f"cihrl_mappo_seed{399 + n}"
    )
    assert all(args[:3] == ["highlevel", "--schedule", "paper"] for _, args in runs)
