"""The statistics of Table V over training seeds: each row against CI-HRL (Welch, TOST, BH, MDD), the
adversary's strength and non-inferiority against the rule, the pre-registered primary comparison and
rliable's aggregates (docs/research/preregistration.md). They read only the rows' per-seed figures, so a report
flown before them can be re-analysed without flying (`add_comparisons`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from cefc_mj.game_protocol import COLUMNS

SEED_METRICS = (*COLUMNS, "E_agents")
"""The per-seed figures compared across methods: the paper's columns and E counted in agent-steps."""
HIGHER_IS_BETTER = {"R_H": True, "R_t": True, "R_n": True, "R_e": True, "E": False, "E_agents": False}
REFERENCE_METHOD = "CI-HRL"


def seed_block(per_seed: dict[int, dict], files: dict[int, Path]) -> dict:
    """Each training seed's episode means, and over the seeds their mean, sample std and 95 % CI."""
    from cefc_mj.eval.stats import seed_interval

    values = {m: [r[m] for r in per_seed.values()] for m in SEED_METRICS}
    ci = {m: seed_interval(v) for m, v in values.items()}
    return {
        "seeds": list(per_seed),
        "files": [files[k].name for k in per_seed],
        **values,
        "mean": {m: ci[m]["mean"] for m in SEED_METRICS},
        "std": {m: ci[m]["std"] for m in SEED_METRICS},
        "ci95": ci,
    }


def adversary_strength(e_adversary: list[float], e_rule: list[float]) -> dict:
    """Whether the game's adversary is weaker than the nearest-group rule against one method: the
    ratio of the means over training seeds of E (steps within 2 m) against each, and the one-sided
    paired t-test over the seeds that it is weaker (`eval.stats.weaker_p`)."""
    from cefc_mj.eval.stats import ALPHA, weaker_p

    ratio = float(np.mean(e_adversary) / np.mean(e_rule)) if np.mean(e_rule) > 0 else None
    p = weaker_p(e_adversary, e_rule)
    weaker = p is not None and p < ALPHA
    return {
        "ratio": ratio,
        "p_weaker": p,
        # Not being shown weaker is no evidence of strength: that takes the non-inferiority test.
        "verdict": "weaker than the rule" if weaker else "not shown weaker",
    }


MARGINS = {"E": 15.0, "R_H": 3500.0}
"""Equivalence margins of the comparisons against CI-HRL, in the per-seed figures' units (per-episode
sums): E +-15 steps (+-1.5 s), R_H +-3500 (+-350 on the paper's x dt scale); docs/research/preregistration.md
argues both. Metrics without a margin get no equivalence test."""
MARGIN_TEXT = {"E": "±1.5 s", "R_H": "±350 (x dt)"}
MARGIN_UNITS = {
    "E": "steps with an agent within 2 m of the adversary, summed over an episode (x dt: seconds, ±1.5 s)",
    "R_H": "R_H summed over an episode's 400 low-level steps (x dt: the paper's scale, ±350)",
}
"""What each margin of MARGINS is counted in (the report's `comparison.margins`)."""
SAME_RUNS = {"CI-HRL-wo-FT": REFERENCE_METHOD}
"""Rows whose training seeds are the same runs as another row's (the weights saved before fine-tuning):
besides the pre-registered Welch test, they are compared with that row by a paired t-test over the
seeds (`paired_comparison`), the test that fits runs which are not independent of the reference."""
ADVERSARY_MARGIN = 0.10
"""Relative non-inferiority margin of the game's adversary against the nearest-group rule: H0 its E
is below 0.9 x the rule's (docs/research/preregistration.md)."""
PRIMARY = ("MAPPO+AT-M", ("E", "R_H"))
"""The pre-registered primary comparison: CI-HRL against this row on these metrics, Holm-adjusted
over the two metrics (docs/research/preregistration.md)."""
AGGREGATE_METRICS = ("E", "R_H")
"""The metrics of the rliable-style aggregates (IQM, probability of improvement) of CI-HRL and PRIMARY's row."""


def _compare_with_reference(rows: dict) -> dict:
    """row["vs_reference"]: per metric, Welch's p over training seeds against CI-HRL with the old
    verdict (unadjusted p < 0.05), p adjusted over every row compared on that metric (`p_fdr`,
    Benjamini-Hochberg); the difference of means with its Welch CI, the TOST p against the metric's
    margin (MARGINS) and its adjustment over the rows (`tost_p_fdr`), the minimum detectable
    difference at 80 % power for the row's and CI-HRL's seed counts and the SD pooled over every
    row's seeds (`mdd`), and the verdict from the adjusted p's (`decision`: better, worse,
    equivalent within the margin, or undecided). Returns the summary (pooled SDs, margins, levels);
    {} without a CI-HRL row over training seeds."""
    from cefc_mj.eval.stats import (
        ALPHA,
        POWER,
        comparison_verdict,
        fdr_adjusted,
        minimum_detectable_difference,
        pooled_sd,
        tost_p,
        verdict,
        welch_difference,
        welch_p,
    )

    reference = rows.get(REFERENCE_METHOD, {}).get("training_seeds")
    if reference is None:
        return {}
    pooled = {}
    for m in SEED_METRICS:
        try:
            sd, df = pooled_sd([row["training_seeds"][m] for row in rows.values() if "training_seeds" in row])
            pooled[m] = {"sd": sd, "df": df}
        except ValueError:
            pooled[m] = None

    def mdd(n: int, m: str) -> float | None:
        n_ref = len(reference[m])
        if n < 2 or n_ref < 2 or pooled[m] is None or not pooled[m]["sd"] > 0:
            return None
        return minimum_detectable_difference(n, n_ref, pooled[m]["sd"])

    for method, row in rows.items():
        if method == REFERENCE_METHOD or "training_seeds" not in row:
            continue
        ours = row["training_seeds"]
        vs = {"method": REFERENCE_METHOD}
        for m in SEED_METRICS:
            diff = welch_difference(ours[m], reference[m])
            vs[m] = {
                "p": welch_p(ours[m], reference[m]),
                "verdict": verdict(ours[m], reference[m], HIGHER_IS_BETTER[m]),
                "difference": None if diff is None else dataclasses.asdict(diff),
                "margin": MARGINS.get(m),
                "tost_p": tost_p(ours[m], reference[m], MARGINS[m]) if m in MARGINS else None,
                "mdd": mdd(len(ours[m]), m),
            }
        row["vs_reference"] = vs
    compared = [row["vs_reference"] for row in rows.values() if "vs_reference" in row]
    for m in SEED_METRICS:
        for vs, q, t in zip(
            compared, fdr_adjusted([vs[m]["p"] for vs in compared]), fdr_adjusted([vs[m]["tost_p"] for vs in compared])
        ):
            diff = vs[m]["difference"]
            vs[m]["p_fdr"], vs[m]["tost_p_fdr"] = q, t
            vs[m]["decision"] = comparison_verdict(
                None if diff is None else diff["difference"], q, t, HIGHER_IS_BETTER[m], MARGIN_TEXT.get(m, "")
            )
    return {
        "reference": REFERENCE_METHOD,
        "alpha": ALPHA,
        "power": POWER,
        "rows_compared": len(compared),
        "adjustment": "Benjamini-Hochberg over the rows compared, per metric; Welch and TOST p's separately",
        "margins": {m: {"value": v, "unit": MARGIN_UNITS[m]} for m, v in MARGINS.items()},
        "pooled_sd": pooled,
        "mdd_method": "noncentral t of Student's two-sample test, df n1 + n2 - 2, pooled SD over every row's seeds",
    }


def _primary(rows: dict) -> dict | None:
    """The pre-registered primary comparison (PRIMARY): CI-HRL against its row on its metrics, the Welch
    and TOST p's Holm-adjusted over those metrics, and the verdict from them; None without the row."""
    from cefc_mj.eval.stats import comparison_verdict, holm_adjusted

    method, metrics = PRIMARY
    vs = rows.get(method, {}).get("vs_reference")
    if not vs:
        return None
    out = {"method": method, "reference": REFERENCE_METHOD, "adjustment": f"Holm over {', '.join(metrics)}"}
    p = holm_adjusted([vs[m]["p"] for m in metrics])
    q = holm_adjusted([vs[m]["tost_p"] for m in metrics])
    for m, p_m, q_m in zip(metrics, p, q):
        diff = vs[m]["difference"]
        out[m] = {
            "difference": diff,
            "p_holm": p_m,
            "tost_p_holm": q_m,
            "decision": comparison_verdict(
                None if diff is None else diff["difference"], p_m, q_m, HIGHER_IS_BETTER[m], MARGIN_TEXT.get(m, "")
            ),
        }
    return out


def _aggregates(rows: dict) -> dict | None:
    """rliable's aggregates over training seeds for CI-HRL and PRIMARY's row: per metric each one's
    IQM with its stratified-bootstrap 95 % interval, and the probability that a CI-HRL seed does better
    than one of the other row (lower E is better); None without both rows over two seeds or more."""
    from cefc_mj.eval.stats import BOOTSTRAP_REPS, improvement_interval, iqm_interval

    other = PRIMARY[0]
    seeds = {m: rows.get(m, {}).get("training_seeds") for m in (REFERENCE_METHOD, other)}
    if any(s is None or len(s["seeds"]) < 2 for s in seeds.values()):
        return None
    out = {"methods": [REFERENCE_METHOD, other], "reps": BOOTSTRAP_REPS, "scores": "per training seed (one task)"}
    for m in AGGREGATE_METRICS:
        sign = 1.0 if HIGHER_IS_BETTER[m] else -1.0
        out[m] = {
            "iqm": {name: dataclasses.asdict(iqm_interval(s[m])) for name, s in seeds.items()},
            "probability_of_improvement": dataclasses.asdict(
                improvement_interval(sign * np.asarray(seeds[REFERENCE_METHOD][m]), sign * np.asarray(seeds[other][m]))
            ),
        }
    return out


def paired_comparison(values, reference, confidence: float = 0.95) -> dict:
    """The paired t-test of two rows over the same training seeds (values[i] and reference[i] from one
    run): `eval.stats.paired_difference` (n, mean difference, its se, two-sided p) and the Student's t
    interval of the mean difference (None bounds without a spread)."""
    from scipy import stats as scipy_stats

    from cefc_mj.eval.stats import paired_difference

    out = paired_difference(values, reference)
    low = high = None
    if out["se"] is not None and out["se"] > 0:
        low, high = (
            float(x) for x in scipy_stats.t.interval(confidence, df=out["n"] - 1, loc=out["mean"], scale=out["se"])
        )
    return out | {"ci_low": low, "ci_high": high, "confidence": confidence}


def _paired_with_same_runs(rows: dict) -> dict | None:
    """Per row of SAME_RUNS present with the same seeds as its runs' row: the paired comparison per
    metric (row minus that row), kept in row["vs_reference"]["paired"] and summarised here."""
    compared = []
    for method, other in SAME_RUNS.items():
        mine, theirs = rows.get(method, {}).get("training_seeds"), rows.get(other, {}).get("training_seeds")
        vs = rows.get(method, {}).get("vs_reference")
        if not mine or not theirs or vs is None or mine["seeds"] != theirs["seeds"]:
            continue
        vs["paired"] = {"method": other} | {m: paired_comparison(mine[m], theirs[m]) for m in SEED_METRICS}
        compared.append(method)
    if not compared:
        return None
    return {
        "rows": compared,
        "test": "paired t-test over the training seeds (the row is the same runs' weights before fine-tuning)",
        "note": "beside the pre-registered Welch test and its adjustment, which stay as registered",
    }


def _holm_level_mdd(rows: dict, pooled: dict) -> dict | None:
    """The primary comparison's minimum detectable difference at the level of Holm's first step
    (alpha over the number of primary metrics), for the primary row's and CI-HRL's seed counts and
    the pooled SD: the difference the Holm-adjusted test detects with POWER at worst."""
    from cefc_mj.eval.stats import ALPHA, POWER, minimum_detectable_difference

    method, metrics = PRIMARY
    seeds = [rows.get(name, {}).get("training_seeds") for name in (method, REFERENCE_METHOD)]
    if any(s is None or len(s["seeds"]) < 2 for s in seeds):
        return None
    n, n_ref = (len(s["seeds"]) for s in seeds)
    alpha = ALPHA / len(metrics)
    out = {"alpha": alpha, "power": POWER, "seeds": [n, n_ref]}
    for m in metrics:
        sd = (pooled.get(m) or {}).get("sd")
        out[m] = minimum_detectable_difference(n, n_ref, sd, alpha=alpha) if sd and sd > 0 else None
    return out


def label_row_episodes(row: dict) -> None:
    """row["episodes_of"]: what a Table V row's top-level figures (R_H ... E, their _std, `seconds`,
    `per_episode`) are when the row has training seeds: the episodes of one seed's policy (its first
    training seed's), not the row over seeds (that is row["training_seeds"])."""
    seeds = row.get("training_seeds")
    if not seeds:
        return
    row["episodes_of"] = {
        "training_seed": seeds["seeds"][0],
        "policy": row.get("policy"),
        "what": (
            "the top-level figures, their _std, seconds and per_episode are this one training seed's "
            "episodes (mean and sample std over episodes); the row over its training seeds is training_seeds"
        ),
    }


def add_comparisons(result: dict) -> dict:
    """The statistics of a Table V result over training seeds, from its rows' per-seed figures (so a
    report flown before them can be re-analysed without flying): each row's `label_row_episodes`,
    `_compare_with_reference` per row, each row's adversary non-inferiority against the rule
    (ADVERSARY_MARGIN), and result["comparison"] with the pooled SDs, the margins with their units, the
    primary comparison (with its Holm-level MDD), the paired comparison of SAME_RUNS and the
    aggregates. Returns `result`, changed in place."""
    from cefc_mj.eval.stats import noninferiority

    rows = result["rows"]
    for row in rows.values():
        label_row_episodes(row)
        if "training_seeds" in row and "against_rule" in row:
            test = noninferiority(row["training_seeds"]["E"], row["against_rule"]["E"], ADVERSARY_MARGIN)
            row["adversary_noninferiority"] = dataclasses.asdict(test)
    summary = _compare_with_reference(rows)
    if summary:
        summary["primary"] = _primary(rows)
        if summary["primary"] is not None:
            summary["primary"]["mdd_holm"] = _holm_level_mdd(rows, summary["pooled_sd"])
        summary["paired"] = _paired_with_same_runs(rows)
        summary["aggregates"] = _aggregates(rows)
        result["comparison"] = summary
    return result
