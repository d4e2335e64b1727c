"""The pre-registered Table V's plan (docs/research/preregistration.md): every training run it asks for, by the
policy file the run writes, and the check that the test flight waits for all of them.

`examples/prereg_table5.py` trains the runs in this order; `cefc-eval --preregistered-flight` refuses
to fly the pre-registered test batch until every file is in its --policies-dir.
"""

from __future__ import annotations

from pathlib import Path

PRIMARY_SEEDS = range(100, 120)
"""Training seeds of CI-HRL and MAPPO+AT-M, the primary pair (20 each)."""
OTHER_SEEDS = range(100, 105)
"""Training seeds of every other row (5 each)."""


def _stem(base: str, seed: int) -> str:
    return f"{base}_seed{seed}"


def planned_runs() -> list[tuple[str, list[str]]]:
    """(policy file stem, `cefc-train` arguments without the common ones) of every run, the primary
    pair's seeds first, interleaved."""
    runs = []
    for k in PRIMARY_SEEDS:
        runs.append((_stem("cihrl_consmac_a", k), ["highlevel", "--variant", "consmac-a"]))
        runs.append((_stem("cihrl_mappo", k), ["highlevel", "--variant", "mappo"]))
    for k in OTHER_SEEDS:
        runs.append((_stem("cihrl_consmac_a_dt", k), ["highlevel", "--variant", "consmac-a", "--pretrain-share", "0"]))
        for variant in ("tarmac", "consmac-o", "masia", "nvif"):
            runs.append((_stem(f"cihrl_{variant.replace('-', '_')}", k), ["highlevel", "--variant", variant]))
        for ablation in ("wo-com", "wo-mem", "wo-de", "wt-rl", "consmac-g"):
            stem = _stem(f"cihrl_consmac_a_{ablation.replace('-', '_')}", k)
            runs.append((stem, ["highlevel", "--variant", "consmac-a", "--ablation", ablation]))
        clm = ["highlevel", "--variant", "consmac-a", "--low-level", "clm-per-group"]
        runs.append((_stem("cihrl_consmac_a_clm", k), clm))
        for algorithm in ("mappo", "masac"):
            benchmarl = ["highlevel-benchmarl", "--algorithm", algorithm, "--budget", "1500ep"]
            runs.append((_stem(f"benchmarl_{algorithm}", k), benchmarl))
    return [(stem, [*args, "--seed", stem.rsplit("_seed", 1)[1]]) for stem, args in runs]


# ---------------------------------------------------------------------------- the second pre-registration
# CI-HRL against MAPPO+AT-M at the paper's schedule (docs/research/preregistration_paper_schedule.md).
PAPER_FIRST_SEED = 400
"""The first training seed of the paper-schedule runs (seeds 400, 401, ...; both methods)."""
PAPER_MIN_SEEDS = 10
"""The fewest seeds per method, whatever the pilot says."""
PAPER_GAP_E_S = 4.3
"""The paper's gap in E the sample size is powered for: MAPPO+AT-M 8.78 s against CI-HRL 4.46 s."""
PAPER_POWER, PAPER_ALPHA = 0.9, 0.025
"""Power to detect that gap, at the first step of Holm over E and R_H (0.05 / 2)."""
PILOT_UPPER_CONFIDENCE = 0.8
"""The pilot's pooled SD enters as its one-sided upper confidence limit at this level."""


def paper_seed_count(pilot_sd_s: float, pilot_df: int) -> int:
    """Seeds per method of the second pre-registration from the pilot (the budget ladder's 1,500 rung):
    the pooled SD of E over training seeds (in seconds, df as pooled) taken at its one-sided 80 % upper
    confidence limit s sqrt(df / chi2_{0.2, df}); the fewest n with power PAPER_POWER to detect
    PAPER_GAP_E_S in Student's two-sided two-sample test at PAPER_ALPHA; at least PAPER_MIN_SEEDS."""
    import math

    from scipy import stats

    from cefc_mj.eval.stats import two_sample_power

    if not pilot_sd_s > 0 or pilot_df < 1:
        raise ValueError(f"paper_seed_count: needs a pilot SD > 0 and df >= 1 (got {pilot_sd_s}, {pilot_df})")
    upper = pilot_sd_s * math.sqrt(pilot_df / stats.chi2.ppf(1 - PILOT_UPPER_CONFIDENCE, pilot_df))
    n = next(
        n for n in range(2, 10_000) if two_sample_power(PAPER_GAP_E_S, n, n, upper, alpha=PAPER_ALPHA) >= PAPER_POWER
    )
    return max(PAPER_MIN_SEEDS, n)


def paper_planned_runs(seeds: int) -> list[tuple[str, list[str]]]:
    """(policy file stem, `cefc-train` arguments without the common ones) of the paper-schedule runs
    for `seeds` seeds per method, the two methods interleaved by seed."""
    runs = []
    for k in range(PAPER_FIRST_SEED, PAPER_FIRST_SEED + seeds):
        for base, variant in (("cihrl_consmac_a", "consmac-a"), ("cihrl_mappo", "mappo")):
            runs.append((_stem(base, k), ["highlevel", "--schedule", "paper", "--variant", variant, "--seed", str(k)]))
    return runs


def missing_runs(policies_dir: Path) -> list[str]:
    """The planned runs whose policy file is not in `policies_dir`."""
    return [stem for stem, _ in planned_runs() if not (Path(policies_dir) / f"{stem}.pt").is_file()]
