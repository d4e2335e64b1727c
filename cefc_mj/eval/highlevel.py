"""The high level's evaluation: the paper's Table V (CI-HRL against high-level baselines) and
Table VI (CI-HRL against adversary strategies), in the particle world (the paper's MPE).

Protocol (paper Sec. V-C): the hierarchical CEFC game of `cefc_mj.hierarchy` with N = 8 UAVs, 2
targets drawn from the 4 corners, obstacles at 0.03 per m^2, 400 low-level steps (40 decisions of
10), 50 episodes in one batch with a fixed seed (every method sees the same episodes), the mode of
each anchor distribution, and the shipped distilled student (`atm_student`) as the low level.

Columns: R_H = R_t + R_n + R_e (the weighted reward terms) and E (steps in which some agent is
within 2 m of the adversary). Each is summed over an episode's 400 low-level steps (`per_episode`)
and reported also in seconds of flight (`x dt`, dt = 0.1 s): the paper's printed values fit the
second scale (its MAPPO+AT-M E of 8.78 against our 8.8 s; its R_n of -327 is impossible as a
400-step sum, since the urgency-weighted distances start at about 180 per step and both targets
cannot be covered in under 2 s). docs/research/high_level.md, "Units of Tables V and VI", has the argument.

>>> result = run_table5(episodes=50, seed=0)          # doctest: +SKIP
>>> print(format_highlevel_table(result))             # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cefc_mj import paths
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.eval.conditions import Conditions
from cefc_mj.eval.stats import paired_difference
from cefc_mj.hierarchy import (
    DECISION_INTERVAL,
    HierarchicalCEFCEnv,
    LowLevel,
    load_low_level,
    recorded_low_level,
)
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, load_highlevel_policy
from cefc_mj.nn.policy_io import resolve_policy_path
from cefc_mj.nn.registry import GAME_ADVERSARY, HIERARCHY_LOWLEVEL
from cefc_mj.provenance import display_path, file_sha256
from cefc_mj.task.config import ADVERSARIES, ADVERSARY_RULES, LEARNED_ADVERSARY, TaskConfig
from cefc_mj.task.messages import MessageChannel

EPISODES = 50
GAME_AGENTS = 8
GAME_DENSITY = 0.03
GAME_STEPS = 400
LOW_LEVEL = HIERARCHY_LOWLEVEL
DT = 0.1
"""Seconds per low-level step: the factor from our per-episode sums to the paper's scale."""
COLUMNS = ("R_H", "R_t", "R_n", "R_e", "E")
EXTRA = ("F", "C")
TABLE5_ROWS = (
    ("MAPPO+AT-M", "cihrl_mappo", "", "MAPPO+AT-M"),
    ("MASAC+AT-M (BenchMARL; stands in for HASAC)", "benchmarl_masac", "", "HASAC+AT-M"),
    ("TarMAC+AT-M", "cihrl_tarmac", "", "TarMAC+AT-M"),
    ("MASIA+AT-M", "cihrl_masia", "", "MASIA+AT-M"),
    ("NVIF+AT-M", "cihrl_nvif", "", "NVIF+AT-M"),
    ("CI-HRL-w-CL-M-wo-FT", "cihrl_consmac_a_clm", "_wo_ft", "CI-HRL-w-CL-M-wo-FT"),
    ("CI-HRL-w-CL-M", "cihrl_consmac_a_clm", "", "CI-HRL-w-CL-M"),
    ("CI-HRL-DT", "cihrl_consmac_a_dt", "", "CI-HRL-DT"),
    ("CI-HRL-wo-FT", "cihrl_consmac_a", "_wo_ft", "CI-HRL-wo-FT"),
    ("CI-HRL", "cihrl_consmac_a", "", "CI-HRL"),
    ("CI-HRL (ConsMAC-O)", "cihrl_consmac_o", "", None),
    ("MAPPO+AT-M (BenchMARL)", "benchmarl_mappo", "", None),
    ("CI-HRL (ConsMAC-wo-Com)", "cihrl_consmac_a_wo_com", "", None),
    ("CI-HRL (ConsMAC-wo-Mem)", "cihrl_consmac_a_wo_mem", "", None),
    ("CI-HRL (ConsMAC-wo-DE)", "cihrl_consmac_a_wo_de", "", None),
    ("CI-HRL (ConsMAC-wt-RL)", "cihrl_consmac_a_wt_rl", "", None),
    ("CI-HRL (ConsMAC-G)", "cihrl_consmac_a_consmac_g", "", None),
)
"""(our row, the stem of our policy file, its suffix, the paper's Table V row it is compared with or
None): seed 0 is <stem><suffix>.pt, seed k <stem>_seed<k><suffix>.pt (the names `cefc-train highlevel`
and `cefc-train highlevel-benchmarl` write). The paper's rows first, in its order; then the rows the
paper's Table V does not list: ConsMAC trained on the other label the paper defines (all agents'
relative positions and velocities), BenchMARL's MAPPO as a cross-check of ours, and the ablations of
the paper's Fig. 7 (which the paper shows as learning curves only). BenchMARL's MASAC stands in for
HASAC (docs/research/baselines.md); the row says so. Every file is flown over the student, except those whose
meta records a per-group low level (`hierarchy.recorded_low_level`): the CI-HRL-w-CL-M rows fly over
the CL-M policy of each agent's group size (what they were fine-tuned with, and the paper's pairing)."""
TABLE6_ROWS = (
    ("PPO", GAME_ADVERSARY, None),
    (
        "PPO (previous generation)",
        "adversary_ppo_nearest_group_member",
        "not in the paper: the previous game adversary (nearest_group_member)",
    ),
    ("PPO (first generation)", "adversary_ppo", "not in the paper: the first game adversary (nearest_group_strike)"),
    ("DDPG", "adversary_ddpg", None),
    ("R-Largest", "r_largest", None),
    ("R-Nearest", "r_nearest", None),
    ("Nearest-group rule", "nearest_group", "not in the paper: the rule the PPO adversary's reward describes"),
)
"""(the paper's column, our adversary (a rule, or a trained adversary's policy name), what differs)."""
TABLE6_TRAINED_LATER = {"adversary_ddpg": "cefc-train adversary-ddpg --install"}
"""Adversaries of TABLE6_ROWS not shipped from the start: flown once their file is in the policies folder,
else the report notes how to train them."""
TABLE7_SIZES = (8, 9, 10, 12, 15)
"""The swarm sizes N of Table VII."""
TABLE4_METHOD = {
    "mappo": "MAPPO",
    "tarmac": "TarMAC",
    "masia": "MASIA",
    "nvif": "NVIF",
    "consmac-a": "ConsMAC",
    "consmac-o": "ConsMAC",
}
"""The paper's Table IV row of each high-level variant (what it sends per decision)."""
GAME_POLICY = "cihrl_consmac_a"
"""The high-level policy Tables VI and VII play: CI-HRL (ConsMAC-A)."""
PAPER_CONDITIONS = Conditions("particle")
"""Where the paper plays the game: its MPE (particles), calm air, exact sensing."""


def game_task(adversary: str = "nearest_group", deviation: float = 0.0, n_agents: int = GAME_AGENTS) -> TaskConfig:
    """The CEFC game of Tables V and VI (the high level's training game, `HighLevelConfig.task`),
    optionally with sensing deviation (m; the agents then act on the fused position estimate, as in
    `cefc-eval`; without deviation the estimate is the exact position). adversary: a rule, or
    'learned' (the env then needs the adversary's policy: `resolve_adversary`). n_agents: the
    swarm's size (Table VII; the observations read the 7 nearest neighbours whatever N is). A rule
    adversary steers around the obstacles, as the PPO adversary learns to (it is penalised inside
    them): both play by the same physical rule (docs/research/high_level.md, "The adversary")."""
    if adversary not in ADVERSARIES:
        raise ConfigError(f"adversary={adversary!r}: must be one of {', '.join(ADVERSARIES)}")
    return TaskConfig(
        n_agents=n_agents,
        mode="cefc",
        obstacle_density=GAME_DENSITY,
        adversary=adversary,
        episode_steps=GAME_STEPS,
        deviation=deviation,
        position_estimator="fused",
        adversary_avoids_obstacles=True,
    )


def resolve_adversary(spec: str, policies_dir: Path | None = None) -> tuple[str, object, dict]:
    """(TaskConfig.adversary, the env's adversary_policy or None, a record for reports) of an
    adversary given as a rule name or as a trained adversary's policy name (in policies_dir, default
    the shipped folder) or file; CheckpointError (one line) for a missing or broken file."""
    if spec in ADVERSARY_RULES:
        return spec, None, {"rule": spec}
    from cefc_mj.nn.adversary_policy import load_adversary_policy

    try:
        path = resolve_policy_path(spec, policies_dir)
        policy, _ = load_adversary_policy(path)
    except CheckpointError as e:
        raise CheckpointError(
            f"adversary {spec}: {e} (a rule is one of {', '.join(ADVERSARY_RULES)}; a trained "
            "adversary comes from cefc-train adversary)"
        ) from None
    return LEARNED_ADVERSARY, policy.act, {"policy": path.name, "sha256": file_sha256(path)}


# ---------------------------------------------------------------------------- episodes
@torch.no_grad()
def play_highlevel(
    policy: HighLevelPolicy, game: HierarchicalCEFCEnv, seed: int, on_decision=None
) -> dict[str, np.ndarray]:
    """Play the game's B episodes (seeded by `seed`) to the end with the mode of each anchor
    distribution; returns per-episode [B] R_H and its weighted parts R_t, R_n, R_e (they sum to
    R_H), all summed over the episode's low-level steps, and the env's metrics E (steps with an
    agent within 2 m of the adversary), F and C. on_decision(inbox, index, message), if given, sees
    every decision (inbox None without communication)."""
    task = game.task
    channel = (
        MessageChannel(game.n_envs, task.n_agents, policy.message_dim, task.observation_distance)
        if policy.comm is not None
        else None
    )
    w = task.rewards
    weights = {"R_t": w.task_weight, "R_n": w.navigation_weight_high, "R_e": w.evasion_weight}
    obs = game.reset(seed=seed)
    total = np.zeros(game.n_envs)
    parts = {name: np.zeros(game.n_envs) for name in weights}
    done = np.zeros(game.n_envs, dtype=bool)
    info: dict = {}
    while not done.all():
        inbox = channel.receive(game.world.agent_pos) if channel is not None else None
        index, message = policy.decide(obs, inbox)
        if channel is not None:
            channel.send(message)
        if on_decision is not None:
            on_decision(inbox, index, message)
        obs, reward, done, info = game.step(index)
        total += reward
        for name, weight in weights.items():
            parts[name] += weight * info["reward_terms"][name]
    metrics = info["metrics"]
    return {"R_H": total, **parts, **{m: np.asarray(metrics[m], dtype=float) for m in ("E", "E_agents", "F", "C")}}


def evaluate_highlevel_episodes(
    policy: HighLevelPolicy,
    task: TaskConfig,
    low_level: LowLevel,
    episodes: int,
    seed: int = 0,
    decision_interval: int = DECISION_INTERVAL,
    world=None,
    adversary_policy=None,
) -> dict[str, np.ndarray]:
    """`play_highlevel` on `episodes` episodes in one batch (seeded by `seed`). world: a physics
    world of `episodes` envs (default the particle world); adversary_policy: the trained adversary
    of a task with adversary='learned'."""
    game = HierarchicalCEFCEnv(
        task,
        low_level,
        n_envs=episodes,
        seed=seed,
        decision_interval=decision_interval,
        world=world,
        adversary_policy=adversary_policy,
    )
    return play_highlevel(policy, game, seed)


def evaluate_highlevel(
    policy: HighLevelPolicy,
    task: TaskConfig,
    low_level: LowLevel,
    episodes: int,
    seed: int = 0,
    decision_interval: int = DECISION_INTERVAL,
    adversary_policy=None,
) -> dict[str, float]:
    """The means over episodes of `evaluate_highlevel_episodes`."""
    per_episode = evaluate_highlevel_episodes(
        policy, task, low_level, episodes, seed, decision_interval, adversary_policy=adversary_policy
    )
    return {name: float(values.mean()) for name, values in per_episode.items()}


# ---------------------------------------------------------------------------- rows
def _paper(key: str) -> dict:
    return json.loads((paths.EVAL_DIR / "paper_tables.json").read_text())[key]


def _stats(per_episode: dict[str, np.ndarray]) -> dict:
    """Means and sample std over episodes (per-episode sums), the same in seconds (x dt; C is a
    percentage and F a step count, left as they are), and the per-episode values."""
    from cefc_mj.eval.runner import episode_stats

    row = episode_stats(per_episode)
    row["seconds"] = {m: row[m] * DT for m in COLUMNS}
    row["seconds_std"] = {m: None if row[f"{m}_std"] is None else row[f"{m}_std"] * DT for m in COLUMNS}
    return row


def _seed_files(stem: str, suffix: str, policies_dir: Path) -> dict[int, Path]:
    """{seed: file} of the policies of one method: <stem><suffix>.pt (seed 0) and <stem>_seed<k><suffix>.pt."""
    found = {}
    if (policies_dir / f"{stem}{suffix}.pt").is_file():
        found[0] = policies_dir / f"{stem}{suffix}.pt"
    pattern = re.compile(re.escape(stem) + r"_seed(\d+)" + re.escape(suffix) + r"\.pt")
    for path in sorted(policies_dir.glob(f"{stem}_seed*{suffix}.pt")):
        match = pattern.fullmatch(path.name)
        if match:
            found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def highlevel_policy_path(policy: str, policies_dir: Path | None = None) -> Path:
    """The file of a high-level policy given by name (in policies_dir, default the shipped folder) or
    path (`resolve_policy_path`); CheckpointError (one line) when there is none."""
    try:
        return resolve_policy_path(policy, policies_dir)
    except CheckpointError as e:
        raise CheckpointError(
            f"--policy {policy}: no high-level policy file ({e}); train it with cefc-train highlevel"
        ) from None


def _evaluate_file(
    path: Path,
    task: TaskConfig,
    low_level: LowLevel,
    episodes: int,
    seed: int,
    where: Conditions,
    adversary_policy=None,
    adversary: dict | None = None,
) -> dict:
    """One policy file's row; adversary: the record (`resolve_adversary`) of the adversary played,
    noted in the row when the policy was trained against another one."""
    policy, meta = load_highlevel_policy(path)
    row = _stats(
        evaluate_highlevel_episodes(
            policy,
            task,
            low_level,
            episodes,
            seed=seed,
            decision_interval=int(meta.get("decision_interval", DECISION_INTERVAL)),
            world=where.world(task, episodes, seed),
            adversary_policy=adversary_policy,
        )
    )
    row.update({"policy": path.name, "sha256": file_sha256(path), "message_dim": policy.message_dim})
    trained_with = (meta.get("low_level") or {}).get("file", {}).get("sha256")
    low_file = (low_level.describe().get("file") or {}).get("sha256")
    if trained_with and low_file and trained_with != low_file:
        row["low_level_differs"] = "fine-tuned with another low-level file than the one evaluated here"
    # Files written before trained adversaries carry no record: they were trained against the rule.
    trained_against = meta.get("adversary", {"rule": "nearest_group"})
    if adversary is not None and trained_against != adversary:
        row["adversary_differs"] = (
            f"trained against {_adversary_text(trained_against)}, played here against {_adversary_text(adversary)}"
        )
    return row


def _protocol(
    episodes: int, seed: int, low_level: LowLevel, policies_dir: Path, adversary: dict | None, where: Conditions
) -> dict:
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise ConfigError(f"episodes={episodes!r}: must be an integer >= 1")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"seed={seed!r}: must be an integer >= 0")
    return {
        **where.to_dict(),
        "n_agents": GAME_AGENTS,
        "density": GAME_DENSITY,
        "steps": GAME_STEPS,
        "decision_interval": DECISION_INTERVAL,
        "episodes": episodes,
        "seed": seed,
        "adversary": adversary,
        "low_level": low_level.describe() | {"name": low_level.name},
        "policies_dir": display_path(policies_dir),
        "anchors": "mode of the selector",
        "dt": DT,
        "comparable_to_paper": episodes == EPISODES and where.paper_like,
        "units": "per-episode sums over 400 low-level steps; 'seconds' = x dt, the scale of the paper's values",
        "missing": [],
    }


def _low_level(task: TaskConfig, spec: str = LOW_LEVEL) -> LowLevel:
    """The shipped student, or the shipped low level `spec` names (wherever the high-level policies
    are read from)."""
    try:
        return load_low_level(spec, task)
    except CheckpointError as e:
        raise CheckpointError(f"the low level of Tables V-VI: {e}") from None


SEED_METRICS = (*COLUMNS, "E_agents")
"""The per-seed figures compared across methods: the paper's columns and E counted in agent-steps."""
HIGHER_IS_BETTER = {"R_H": True, "R_t": True, "R_n": True, "R_e": True, "E": False, "E_agents": False}
REFERENCE_METHOD = "CI-HRL"


def _seed_block(per_seed: dict[int, dict], files: dict[int, Path]) -> dict:
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


def _adversary_strength(e_adversary: list[float], e_rule: list[float]) -> dict:
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
        "margins": dict(MARGINS),
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


def add_comparisons(result: dict) -> dict:
    """The statistics of a Table V result over training seeds, from its rows' per-seed figures (so a
    report flown before them can be re-analysed without flying): `_compare_with_reference` per row,
    each row's adversary non-inferiority against the rule (ADVERSARY_MARGIN), and result["comparison"]
    with the pooled SDs, the primary comparison and the aggregates. Returns `result`, changed in place."""
    from cefc_mj.eval.stats import noninferiority

    rows = result["rows"]
    for row in rows.values():
        if "training_seeds" in row and "against_rule" in row:
            test = noninferiority(row["training_seeds"]["E"], row["against_rule"]["E"], ADVERSARY_MARGIN)
            row["adversary_noninferiority"] = dataclasses.asdict(test)
    summary = _compare_with_reference(rows)
    if summary:
        summary["primary"] = _primary(rows)
        summary["aggregates"] = _aggregates(rows)
        result["comparison"] = summary
    return result


@dataclass(frozen=True)
class _FileJob:
    """One policy file's batch of games against one adversary: a picklable job of `run_table5`."""

    path: Path
    adversary: str
    """A rule or a trained adversary's name or file (`resolve_adversary`)."""
    low_level: str
    episodes: int
    seed: int
    where: Conditions
    policies_dir: Path


def _fly_file(job: _FileJob) -> dict:
    """`_evaluate_file` of one job, its game and low level built here (in a worker process, too)."""
    kind, adversary_policy, record = resolve_adversary(job.adversary, job.policies_dir)
    task = game_task(kind, deviation=job.where.deviation)
    low_level = _low_level(task, job.low_level)
    return _evaluate_file(job.path, task, low_level, job.episodes, job.seed, job.where, adversary_policy, record)


def run_table5(
    episodes: int = EPISODES,
    seed: int = 0,
    policies_dir: Path | None = None,
    policy: str | None = None,
    provenance: dict | None = None,
    where: Conditions | None = None,
    adversary: str = GAME_ADVERSARY,
    against_rule: bool = True,
    workers: int = 1,
) -> dict:
    """Table V: every method whose policy file exists (the others are listed in protocol["missing"]),
    or only `policy` (a file or a name in policies_dir, one row under its file name). Each row is
    its lowest training seed's policy (seed 0 where shipped) over `episodes` episodes; where files of
    other training seeds exist, row["training_seeds"] has each seed's means and their mean, sample
    std and 95 % CI, and row["vs_reference"] the comparison with CI-HRL per metric, result["comparison"]
    its summary (`add_comparisons`). where: backend, wind and deviation
    (default the paper's: particles, calm, exact sensing). adversary: a rule or a trained adversary
    (name in policies_dir, or file; default the PPO adversary). against_rule: also fly every seed's
    policy against the nearest-group rule (row["against_rule"]), the yardstick of the adversary's
    strength. workers: processes flying the policy files' batches (each batch is seeded on its own,
    so the figures do not depend on it)."""
    from cefc_mj.executors import ExecutorConfig, map_unordered

    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    where = where or PAPER_CONDITIONS
    kind, adversary_policy, record = resolve_adversary(adversary, policies_dir)
    task = game_task(kind, deviation=where.deviation)
    low_level = _low_level(task)
    result = {
        "schema": "cefc-eval/table5",
        "schema_version": 1,
        "protocol": _protocol(episodes, seed, low_level, policies_dir, record, where),
        "rows": {},
    }
    paper = _paper("table5_cihrl_mpe")
    if provenance is not None:
        result["provenance"] = provenance
    if policy is not None:
        path = highlevel_policy_path(policy, policies_dir)
        result["rows"][path.stem] = {
            **_evaluate_file(path, task, low_level, episodes, seed, where, adversary_policy, record),
            "paper": None,
        }
        return result
    rows = []  # (method, stem, paper_row, {seed: file})
    for method, stem, suffix, paper_row in TABLE5_ROWS:
        files = _seed_files(stem, suffix, policies_dir)
        if not files:
            result["protocol"]["missing"].append(f"{method} ({stem}{suffix}.pt)")
        else:
            rows.append((method, stem, paper_row, files))
    opponents = (adversary, "nearest_group") if against_rule else (adversary,)
    file_low_level = {
        f: recorded_low_level(load_highlevel_policy(f)[1], LOW_LEVEL) for *_, files in rows for f in files.values()
    }
    jobs = {
        (method, opponent, k): _FileJob(f, opponent, file_low_level[f], episodes, seed, where, policies_dir)
        for method, stem, _, files in rows
        for opponent in opponents
        for k, f in files.items()
    }
    flown = {job: row for job, row in map_unordered(_fly_file, list(jobs.values()), ExecutorConfig(workers=workers))}
    for method, stem, paper_row, files in rows:
        per_seed = {k: flown[jobs[method, adversary, k]] for k in files}
        first = next(iter(files))  # seed 0 where shipped; a run of seeds 100.. has no seed 0
        row = per_seed[first]
        row["paper"] = dict(zip(COLUMNS, paper[paper_row])) if paper_row is not None else None
        if file_low_level[files[first]] != LOW_LEVEL:
            low = _low_level(task, file_low_level[files[first]])
            row["low_level"] = low.describe() | {"name": low.name}
        row["training_seeds"] = _seed_block(per_seed, files)
        if against_rule:
            row["against_rule"] = _seed_block({k: flown[jobs[method, "nearest_group", k]] for k in files}, files)
            row["adversary_strength"] = _adversary_strength(row["training_seeds"]["E"], row["against_rule"]["E"])
        result["rows"][method] = row
    add_comparisons(result)
    return result


def run_table6(
    episodes: int = EPISODES,
    seed: int = 0,
    policies_dir: Path | None = None,
    policy: str = GAME_POLICY,
    provenance: dict | None = None,
    where: Conditions | None = None,
) -> dict:
    """Table VI: one high-level policy (default CI-HRL) against each adversary strategy, the same
    episodes otherwise. Columns R_t, R_e, E as the paper prints them (R_H, R_n ride along); a row
    without a paper column (the nearest-group rule) has paper None. An adversary of TABLE6_TRAINED_LATER
    (DDPG) whose file is not in policies_dir is left out; protocol["missing"] says how to train it."""
    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    path = highlevel_policy_path(policy, policies_dir)
    untrained = {name for name in TABLE6_TRAINED_LATER if not (policies_dir / f"{name}.pt").is_file()}
    rows = [row for row in TABLE6_ROWS if row[1] not in untrained]
    adversaries = {column: resolve_adversary(adversary, policies_dir) for column, adversary, _ in rows}
    where = where or PAPER_CONDITIONS
    low_level = _low_level(game_task())
    result = {
        "schema": "cefc-eval/table6",
        "schema_version": 1,
        "protocol": _protocol(episodes, seed, low_level, policies_dir, None, where),
        "rows": {},
    }
    result["protocol"]["policy"] = path.name
    result["protocol"]["missing"] += [
        f"{column} ({name}.pt: not trained yet; train it with `{TABLE6_TRAINED_LATER[name]}`)"
        for column, name, _ in TABLE6_ROWS
        if name in untrained
    ]
    paper = _paper("table6_adversaries")
    if provenance is not None:
        result["provenance"] = provenance
    for column, adversary, differs in rows:
        kind, adversary_policy, record = adversaries[column]
        row = _evaluate_file(path, game_task(kind, where.deviation), low_level, episodes, seed, where, adversary_policy)
        row.update(
            {
                "adversary": adversary,
                "adversary_record": record,
                "paper": dict(zip(("R_t", "R_e", "E"), paper[column])) if column in paper else None,
            }
        )
        if differs:
            row["differs"] = differs
        result["rows"][column] = row
    return result


def run_table7(
    episodes: int = EPISODES,
    seed: int = 0,
    policies_dir: Path | None = None,
    policy: str = GAME_POLICY,
    provenance: dict | None = None,
    where: Conditions | None = None,
    adversary: str = GAME_ADVERSARY,
    sizes: tuple[int, ...] = TABLE7_SIZES,
) -> dict:
    """Table VII: one high-level policy (default CI-HRL, trained with N = 8) in games of N UAVs for
    each N in `sizes`, the same adversary, targets and obstacle density; each row adds the per-agent
    averages (R_H, R_t, R_n, R_e and E in seconds, divided by N), the paper's columns."""
    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    path = highlevel_policy_path(policy, policies_dir)
    where = where or PAPER_CONDITIONS
    if not sizes or any(not isinstance(n, int) or isinstance(n, bool) or not 3 <= n <= 32 for n in sizes):
        raise ConfigError(f"sizes={sizes!r}: must be swarm sizes in [3, 32]")
    kind, adversary_policy, record = resolve_adversary(adversary, policies_dir)
    low_level = _low_level(game_task(kind))
    result = {
        "schema": "cefc-eval/table7",
        "schema_version": 1,
        "protocol": _protocol(episodes, seed, low_level, policies_dir, record, where),
        "rows": {},
    }
    result["protocol"].update({"policy": path.name, "n_agents": list(sizes)})
    paper = _paper("table7_large_scale")
    if provenance is not None:
        result["provenance"] = provenance
    for n in sizes:
        task = game_task(kind, where.deviation, n_agents=n)
        row = _evaluate_file(path, task, low_level, episodes, seed, where, adversary_policy, record)
        row["n_agents"] = n
        row["per_agent"] = {m: row["seconds"][m] / n for m in COLUMNS}
        row["per_agent_std"] = {
            m: row["seconds_std"][m] / n if row["seconds_std"][m] is not None else None for m in COLUMNS
        }
        row["paper"] = dict(zip(COLUMNS, paper[str(n)])) if str(n) in paper else None
        result["rows"][f"N = {n}"] = row
    return result


# ---------------------------------------------------------------------------- one game at a time (SITL-M)
GAME_METRICS = ("R_H", "R_t", "R_n", "R_e", "E", "E_agents", "F", "C")
"""The per-episode figures of one game (`play_highlevel`'s)."""


@dataclass(frozen=True)
class GameSpec:
    """One game of Table V played alone (one env), as the SITL-M game plays it: every UAV's hierarchy
    in its own process (`cefc_mj.deploy.game.run_sitl_game`), or here in one process (`play_game`)."""

    policy: str = GAME_POLICY
    """The high-level policy (name in policies/ or file)."""
    seed: int = 0
    """The game's seed (scenario, adversary, sensing)."""
    where: Conditions = PAPER_CONDITIONS
    """Backend, wind, deviation."""
    adversary: str = GAME_ADVERSARY
    """A rule or a trained adversary's name or file."""
    n_agents: int = GAME_AGENTS
    """N, the swarm's size."""
    steps: int = GAME_STEPS
    """Low-level steps (a multiple of the decision interval); the game ends there."""

    def __post_init__(self) -> None:
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ConfigError(f"seed={self.seed!r}: must be an integer >= 0")
        if not isinstance(self.n_agents, int) or isinstance(self.n_agents, bool) or not 3 <= self.n_agents <= 32:
            raise ConfigError(f"n_agents={self.n_agents!r}: must be a swarm size in [3, 32]")
        if (
            not isinstance(self.steps, int)
            or isinstance(self.steps, bool)
            or self.steps < DECISION_INTERVAL
            or self.steps % DECISION_INTERVAL
        ):
            raise ConfigError(f"steps={self.steps!r}: must be a positive multiple of {DECISION_INTERVAL}")

    def game(self, policies_dir: Path | None = None) -> tuple[TaskConfig, object, dict]:
        """(the game's TaskConfig, the adversary's policy or None, the adversary's record)."""
        kind, adversary_policy, record = resolve_adversary(self.adversary, policies_dir)
        task = dataclasses.replace(
            game_task(kind, deviation=self.where.deviation, n_agents=self.n_agents), episode_steps=self.steps
        )
        return task, adversary_policy, record


def game_figures(total: float, parts: dict, metrics: dict) -> dict[str, float]:
    """One game's figures (GAME_METRICS) from its summed R_H, the weighted parts and the env's metrics."""
    return {"R_H": float(total), **{m: float(v) for m, v in parts.items()}} | {
        m: float(np.asarray(metrics[m]).reshape(-1)[0]) for m in ("E", "E_agents", "F", "C")
    }


def play_game(spec: GameSpec, policies_dir: Path | None = None) -> dict[str, float]:
    """The lock-step game of `spec` in this process (one env, `play_highlevel`): its figures."""
    task, adversary_policy, _ = spec.game(policies_dir)
    path = highlevel_policy_path(spec.policy, policies_dir)
    policy, meta = load_highlevel_policy(path)
    game = HierarchicalCEFCEnv(
        task,
        _low_level(task),
        n_envs=1,
        seed=spec.seed,
        decision_interval=int(meta.get("decision_interval", DECISION_INTERVAL)),
        world=spec.where.world(task, 1, spec.seed),
        adversary_policy=adversary_policy,
    )
    return {m: float(v[0]) for m, v in play_highlevel(policy, game, spec.seed).items()}


def run_table5_sitl(
    runner: Callable,
    sitl,
    episodes: int = 1,
    seed: int = 0,
    policy: str = GAME_POLICY,
    provenance: dict | None = None,
    where: Conditions | None = None,
    adversary: str = GAME_ADVERSARY,
    lockstep: bool = True,
    steps: int = GAME_STEPS,
) -> dict:
    """Table V's row of one policy played as the SITL-M game: each UAV's whole hierarchy in its own
    process, one game per seed (seed, seed + 1, ...). runner(GameSpec, sitl) -> result with
    `figures` (GAME_METRICS), `sitl` (a summary dict) and `faults()` (the SITL-M row's "faults", "valid"
    False when any) is `cefc_mj.deploy.game.run_sitl_game`, passed
    in by cefc-eval (evaluation never imports the agent-process layer). lockstep: also play each
    seed's game in one process (`play_game`) and report the paired difference SITL-M - lock-step
    (mean and its standard error)."""
    where = where or PAPER_CONDITIONS
    path = highlevel_policy_path(policy)
    specs = [GameSpec(policy, seed + e, where, adversary, steps=steps) for e in range(episodes)]
    task, _, record = specs[0].game()
    low_level = _low_level(task)
    result = {
        "schema": "cefc-eval/table5",
        "schema_version": 1,
        "protocol": _protocol(episodes, seed, low_level, paths.POLICIES_DIR, record, where),
        "rows": {},
    }
    result["protocol"].update({"steps": steps, "sitl_m": True, "seeds": [s.seed for s in specs]})
    if provenance is not None:
        result["provenance"] = provenance
    games = [runner(spec, sitl) for spec in specs]
    per_episode = {m: np.array([g.figures[m] for g in games]) for m in GAME_METRICS}
    row = _stats(per_episode)
    row.update({"policy": path.name, "sha256": file_sha256(path), "paper": None, "condition": "SITL-M"})
    row["message_dim"] = games[0].message_dim
    row["variant"] = load_highlevel_policy(path)[0].variant
    row["sitl"] = [g.sitl for g in games]
    row["sitl_pooled"] = pooled_game_timing(games)
    row["faults"] = [f"seed {g.spec.seed}: {line}" for g in games for line in g.faults()]
    row["valid"] = not row["faults"]
    result["rows"][f"{path.stem} (SITL-M)"] = row
    if lockstep:
        reference = [play_game(spec) for spec in specs]
        ref = {m: np.array([r[m] for r in reference]) for m in GAME_METRICS}
        ref_row = _stats(ref)
        ref_row.update({"policy": path.name, "sha256": file_sha256(path), "paper": None, "condition": "lock-step"})
        result["rows"][f"{path.stem} (lock-step)"] = ref_row
        result["paired_difference"] = {m: paired_difference(per_episode[m], ref[m]) for m in GAME_METRICS}
        result["fidelity"] = sitl_fidelity(per_episode, ref, result["paired_difference"])
    return result


SITL_RT_SHARE = 0.95
"""Fidelity target: the SITL-M game's mean R_t at least this share of the lock-step game's."""


def sitl_fidelity(sitl: dict, lockstep: dict, diff: dict) -> dict:
    """The SITL-M game's fidelity targets on the same seeds: mean R_t >= SITL_RT_SHARE x the lock-step
    mean, and mean E no worse than the lock-step mean + one standard error of the paired difference
    (E counts steps near the adversary: lower is better)."""
    rt, rt_ref = float(np.mean(sitl["R_t"])), float(np.mean(lockstep["R_t"]))
    e, e_ref, e_se = float(np.mean(sitl["E"])), float(np.mean(lockstep["E"])), diff["E"]["se"]
    return {
        "R_t_share": rt / rt_ref if rt_ref > 0 else None,
        "R_t_target": SITL_RT_SHARE,
        "R_t_met": bool(rt >= SITL_RT_SHARE * rt_ref),
        "E_limit": e_ref + (e_se or 0.0),
        "E_met": bool(e <= e_ref + (e_se or 0.0)),
    }


def pooled_game_timing(games) -> dict:
    """Over games: p50/p99 of the low- and high-level decision latencies and round trips (pooled
    samples), and bytes per simulated second per UAV on the wire."""
    out = {}
    for name in ("low_latency_ms", "high_latency_ms", "low_round_trip_ms", "high_round_trip_ms"):
        values = np.concatenate([np.asarray(g.samples[name], dtype=np.float64) for g in games])
        out[name] = (
            {
                "p50": float(np.percentile(values, 50)),
                "p99": float(np.percentile(values, 99)),
                "count": int(values.size),
            }
            if values.size
            else {"p50": None, "p99": None, "count": 0}
        )
    for name in ("bytes_per_s_per_uav", "message_bytes_per_s_per_uav"):
        out[name] = float(np.mean([g.sitl[name] for g in games]))
    return out


def format_sitl_game(result: dict) -> str:
    """Plain text of `run_table5_sitl`: each row's figures (mean ± std over the games, per-episode
    sums), the paired difference, the timing and the bytes on the wire beside Table IV's size."""
    from cefc_mj.eval.runner import format_mean_std

    proto = result["protocol"]
    lines = [
        f"Table V game over SITL-M ({_where_text(proto)}, N = {proto['n_agents']}, {proto['episodes']} game(s) x "
        f"{proto['steps']} steps, seeds {proto['seeds'][0]}..{proto['seeds'][-1]}, adversary "
        f"{_adversary_text(proto['adversary'])}, low level {proto['low_level']['name']}).",
        "Per-episode sums (not x dt); mean ± sample std over games. SITL-M: every UAV's hierarchy in its own process.",
    ]
    names = ("R_H", "R_t", "R_n", "R_e", "E", "F", "C")
    table = [["row", *names]]
    for label, row in result["rows"].items():
        flag = "" if row.get("valid", True) else " (NOT A MEASUREMENT: faults below)"
        table.append([label + flag, *(format_mean_std(row[m], row[f"{m}_std"], ".1f") for m in names)])
    if "paired_difference" in result:
        diff = result["paired_difference"]
        table.append(
            [
                "SITL-M - lock-step",
                *(
                    f"{diff[m]['mean']:.1f}" + ("" if diff[m]["se"] is None else f" ± {diff[m]['se']:.1f} (se)")
                    for m in names
                ),
            ]
        )
        table.append(["paired t-test p", *("-" if diff[m].get("p") is None else f"{diff[m]['p']:.2f}" for m in names)])
    widths = [max(len(r[i]) for r in table) for i in range(len(table[0]))]
    for r in table:
        lines.append("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))))
    if "fidelity" in result:
        fid, e = result["fidelity"], result["paired_difference"]["E"]
        share = "-" if fid["R_t_share"] is None else f"{100 * fid['R_t_share']:.1f} %"
        lines.append(
            f"fidelity: mean R_t {share} of lock-step (target >= {100 * fid['R_t_target']:.0f} %: "
            f"{'met' if fid['R_t_met'] else 'not met'}); E {e['mean']:+.1f} steps (target: at most lock-step + one "
            f"se of the difference, {fid['E_limit']:.1f}: {'met' if fid['E_met'] else 'not met'})"
        )
    sitl_row = next(r for r in result["rows"].values() if r.get("condition") == "SITL-M")
    pooled = sitl_row["sitl_pooled"]
    method = TABLE4_METHOD.get(sitl_row.get("variant", "consmac-a"), "ConsMAC")  # reports before the field: CI-HRL

    def p(name):
        v = pooled[name]
        return "-" if v["p50"] is None else f"{v['p50']:.2f} / {v['p99']:.2f} ms"

    lines += [
        f"latency p50 / p99: low level {p('low_latency_ms')}, high level {p('high_latency_ms')}; "
        f"round trip low {p('low_round_trip_ms')}, high {p('high_round_trip_ms')}",
        f"wire: {pooled['bytes_per_s_per_uav']:.0f} B/s per UAV in all, of which {method} messages "
        f"{pooled['message_bytes_per_s_per_uav']:.0f} B/s (sent and received); message {sitl_row['message_dim']} "
        f"floats per decision (paper's Table IV, {method}: {_paper('table4_comm_dims').get(method, '-')})",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------------------- reports
def _where_text(proto: dict) -> str:
    text = "particle" if proto["backend"] == "particle" else "MuJoCo quadrotors"
    if proto["wind"]:
        text += f", wind {proto['wind']:g} m/s"
    if proto["deviation"]:
        text += f", deviation {proto['deviation']:g} m (fused estimate)"
    return text


def _adversary_text(record) -> str:
    """A report's adversary: "per row" (Table VI), a rule, or a trained adversary's file."""
    if not record:
        return "per row"
    if isinstance(record, str):  # reports written before trained adversaries
        return record
    return record.get("rule") or f"{record['policy']} (trained)"


def format_highlevel_table(result: dict) -> str:
    """Plain text: per method ours (mean ± std over episodes, in seconds of flight) and the paper's row."""
    from cefc_mj.eval.runner import format_mean_std

    proto = result["protocol"]
    per_agent = result["schema"] == "cefc-eval/table7"
    table_name = {"cefc-eval/table6": "Table VI", "cefc-eval/table7": "Table VII"}.get(result["schema"], "Table V")
    adversary = _adversary_text(proto["adversary"])
    lines = [
        f"{table_name} protocol ({_where_text(proto)}, N = "
        f"{', '.join(map(str, proto['n_agents'])) if per_agent else proto['n_agents']}, "
        f"density {proto['density']}/m^2, "
        f"{proto['episodes']} "
        f"episodes x {proto['steps']} steps, seed {proto['seed']}, adversary {adversary}, low level "
        f"{proto['low_level']['name']}).",
        "R_H = R_t + R_n + R_e (weighted reward terms) and E (time with an agent within 2 m of the adversary), "
        "summed over each episode and given in seconds of flight (x 0.1 s), the scale of the paper's values; "
        "ours: mean ± sample std over episodes."
        + (f" Table VII: per agent (divided by N), {proto['policy']} trained with N = 8." if per_agent else ""),
    ]
    if proto["episodes"] != EPISODES:
        lines.append(f"{proto['episodes']} episodes; the paper evaluates {EPISODES}.")
    if proto["backend"] != "particle" or proto["wind"] or proto["deviation"]:
        lines.append(
            "The paper's rows are from its MPE (particles, calm, exact sensing): shown for scale, not like-for-like."
        )
    header = [f"{m}/N" for m in COLUMNS] if per_agent else list(COLUMNS)
    table = [["method", "", *header, "F (steps)", "C (%)"]]
    for method, row in result["rows"].items():
        label = method if result["schema"] != "cefc-eval/table6" else f"{method} ({row['adversary']})"
        figures, spread = (
            (row["per_agent"], row["per_agent_std"]) if per_agent else (row["seconds"], row["seconds_std"])
        )
        table.append(
            [label, "ours"]
            + [format_mean_std(figures[m], spread[m], ".2f" if per_agent else ".1f") for m in COLUMNS]
            + [format_mean_std(row["F"], row["F_std"], ".0f"), format_mean_std(row["C"], row["C_std"], ".2f")]
        )
        seeds = row.get("training_seeds")
        if seeds and len(seeds["seeds"]) > 1:
            table.append(
                [f"  {len(seeds['seeds'])} training seeds", "ours"]
                + [format_mean_std(seeds["mean"][m] * DT, seeds["std"][m] * DT, ".1f") for m in COLUMNS]
                + ["", ""]
            )
        paper = row.get("paper") or {}
        table.append(
            ["", "paper"] + ["-" if paper.get(m) is None else format(paper[m], ".2f") for m in COLUMNS] + ["-", "-"]
        )
    widths = [max(len(r[i]) for r in table) for i in range(len(table[0]))]
    for r in table:
        lines.append(
            "  ".join(cell.ljust(w) if i < 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths))).rstrip()
        )
    for method, row in result["rows"].items():
        for key in ("differs", "low_level_differs", "adversary_differs"):
            if row.get(key):
                lines.append(f"{method}: {row[key]}")
        if row.get("low_level"):
            lines.append(f"{method}: flown over {row['low_level']['name']} ({row['low_level']['kind']})")
    if proto.get("missing"):
        lines.append("missing policies: " + ", ".join(proto["missing"]))
    if result["schema"] == "cefc-eval/table5" and table4_line(result):
        lines.append(table4_line(result))
    if result["schema"] == "cefc-eval/table5" and any("training_seeds" in r for r in result["rows"].values()):
        lines += seed_table_lines(result)
    return "\n".join(lines)


def _ci_text(ci: dict, scale: float = 1.0, fmt: str = ".1f") -> str:
    mean = format(ci["mean"] * scale, fmt)
    if ci["ci_low"] is None:
        return f"{mean} (1 seed)"
    return f"{mean} [{format(ci['ci_low'] * scale, fmt)}, {format(ci['ci_high'] * scale, fmt)}]"


def seed_table_lines(result: dict) -> list[str]:
    """Over training seeds: mean [95 % CI] of each metric against the game's adversary and E against
    the nearest-group rule, and Welch's p against CI-HRL with the verdict (p < 0.05, else "no
    significant difference"); the differences that survive the adjustment; where the result has them
    (`add_comparisons`), the comparison that can say "alike" (`equivalence_lines`), the adversary's
    non-inferiority beside its strength, and the aggregates (`aggregate_lines`)."""
    from cefc_mj.eval.stats import ALPHA

    lines = [
        "",
        f"Over training seeds (each seed's mean over the {result['protocol']['episodes']} episodes; mean "
        "[95 % CI of the mean, Student's t]). E: steps with any agent within 2 m of the adversary, in steps "
        "and in seconds (x 0.1 s); E_agents: agent-steps within 2 m. R_* are per-episode sums, not "
        "scaled; R_e sums over the agents, R_e/N is its per-agent mean. p: Welch's t-test against CI-HRL "
        "over the seeds; a difference counts only where "
        f"p < {ALPHA}.",
    ]
    header = [
        "method",
        "seeds",
        "R_H",
        "R_t",
        "R_n",
        "R_e",
        "R_e/N",
        "E (steps)",
        "E (s)",
        "E_agents",
        "E vs rule (s)",
        "p R_H",
        "p R_t",
        "p E",
        "vs CI-HRL (R_H / E)",
    ]
    table = [header]
    for method, row in result["rows"].items():
        seeds = row.get("training_seeds")
        if not seeds:
            continue
        ci = seeds["ci95"]
        rule = row.get("against_rule", {}).get("ci95", {}).get("E")
        vs = row.get("vs_reference")

        def p(m, vs=vs):
            return "-" if not vs or vs[m]["p"] is None else f"{vs[m]['p']:.3f}"

        table.append(
            [
                method,
                str(len(seeds["seeds"])),
                _ci_text(ci["R_H"], fmt=".0f"),
                _ci_text(ci["R_t"]),
                _ci_text(ci["R_n"], fmt=".0f"),
                _ci_text(ci["R_e"], fmt=".0f"),
                _ci_text(ci["R_e"], 1 / result["protocol"]["n_agents"], ".0f"),
                _ci_text(ci["E"]),
                _ci_text(ci["E"], DT, ".2f"),
                _ci_text(ci["E_agents"], fmt=".0f"),
                "-" if rule is None else _ci_text(rule, DT, ".2f"),
                p("R_H"),
                p("R_t"),
                p("E"),
                "reference"
                if method == REFERENCE_METHOD
                else "-"
                if not vs
                else f"{vs['R_H']['verdict']} / {vs['E']['verdict']}",
            ]
        )
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines += [
        "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths)))
        for r in table
    ]
    lines += _fdr_lines(result["rows"])
    lines += equivalence_lines(result)
    strength = {m: r["adversary_strength"] for m, r in result["rows"].items() if r.get("adversary_strength")}
    if strength:
        rows = result["rows"]
        noninferior = any("adversary_noninferiority" in rows[m] for m in strength)
        lines += [
            "",
            "Adversary strength: E against the game's adversary over E against the nearest-group rule (means "
            "over training seeds, the same policies and games); p: one-sided paired t-test over the seeds "
            f"that the adversary is weaker than the rule (weaker where p < {ALPHA})."
            + (
                f" Non-inferiority: one-sided paired t-test over the seeds of H0 E(adversary) <= "
                f"{1 - ADVERSARY_MARGIN:g} x E(rule) (the adversary more than {100 * ADVERSARY_MARGIN:g} % weaker), "
                f"rejected where p < {ALPHA}."
                if noninferior
                else ""
            ),
            *(
                f"  {m}: {'-' if a['ratio'] is None else format(a['ratio'], '.2f')}, p "
                f"{'-' if a['p_weaker'] is None else format(a['p_weaker'], '.3f')}: {a['verdict']}"
                + _noninferiority_text(rows[m].get("adversary_noninferiority"))
                for m, a in strength.items()
            ),
        ]
    lines += aggregate_lines(result)
    return lines


def _p_text(p: float | None, adjusted: float | None = None) -> str:
    if p is None:
        return "-"
    return f"{p:.3f}" + ("" if adjusted is None else f" ({adjusted:.3f})")


def _difference_text(d: dict | None, m: str) -> str:
    """A difference of means [95 % Welch CI] (`eval.stats.welch_difference`) in metric m's printed unit."""
    if d is None:
        return "-"
    factor, unit, fmt = _scale(m)
    return (
        f"{format(d['difference'] * factor, '+' + fmt)}{unit} "
        f"[{format(d['ci_low'] * factor, fmt)}, {format(d['ci_high'] * factor, fmt)}]"
    )


def _noninferiority_text(test: dict | None) -> str:
    if not test:
        return ""
    return f"; non-inferiority p {_p_text(test['p'])}: {test['verdict']}"


def _scale(m: str) -> tuple[float, str, str]:
    """(factor from the per-seed figure to the printed one, unit, format) of a compared metric."""
    return (DT, " s", ".2f") if m == "E" else (DT, "", ".0f") if m in ("R_H", "R_t", "R_n", "R_e") else (1.0, "", ".1f")


def equivalence_lines(result: dict) -> list[str]:
    """The comparison with CI-HRL that can say "alike": per row and metric of MARGINS the difference of
    means [95 % Welch CI], Welch's p and the TOST p with their adjustments over the rows, the verdict;
    then the minimum detectable differences and the primary comparison. [] for a result without them."""
    from cefc_mj.eval.stats import ALPHA, POWER

    comparison = result.get("comparison")
    if not comparison:
        return []
    metrics = [m for m in MARGINS if m in SEED_METRICS]
    units = ", ".join(f"{m} {'in s' if m == 'E' else 'per episode x 0.1 s'}, margin {MARGIN_TEXT[m]}" for m in metrics)
    lines = [
        "",
        f"Against {REFERENCE_METHOD}: the row's mean over training seeds minus {REFERENCE_METHOD}'s [95 % Welch CI]; "
        "p: Welch's two-sided t-test; TOST p: two one-sided Welch tests of equivalence within the margin; in "
        f"brackets each adjusted over the {comparison['rows_compared']} rows (Benjamini-Hochberg); verdict from "
        f"the adjusted p's at {ALPHA}: better / worse where p is below it, else equivalent where the TOST p is, "
        f"else undecided (underpowered). {units}.",
    ]
    header = ["method", "seeds"]
    for m in metrics:
        header += [f"{m} difference [95 % CI]", f"p {m}", f"TOST p {m}", f"verdict {m}"]
    table = [header]
    for method, row in result["rows"].items():
        vs = row.get("vs_reference")
        if not vs:
            continue
        cells = [method, str(len(row["training_seeds"]["seeds"]))]
        for m in metrics:
            cells += [
                _difference_text(vs[m].get("difference"), m),
                _p_text(vs[m]["p"], vs[m].get("p_fdr")),
                _p_text(vs[m].get("tost_p"), vs[m].get("tost_p_fdr")),
                vs[m].get("decision", "-"),
            ]
        table.append(cells)
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines += [
        "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths))).rstrip()
        for r in table
    ]
    pooled = comparison["pooled_sd"]
    sds = ", ".join(
        f"{m} {format(pooled[m]['sd'] * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}" for m in metrics if pooled.get(m)
    )
    pairs: dict[tuple[int, int], dict[str, float]] = {}
    for row in result["rows"].values():
        vs = row.get("vs_reference")
        if vs:
            key = (
                len(row["training_seeds"]["seeds"]),
                len(result["rows"][REFERENCE_METHOD]["training_seeds"]["seeds"]),
            )
            pairs.setdefault(key, {m: vs[m]["mdd"] for m in metrics})
    mdds = "; ".join(
        f"{n} vs {n_ref} seeds: "
        + ", ".join(
            f"{m} {format(v * _scale(m)[0], _scale(m)[2])}{_scale(m)[1]}" for m, v in values.items() if v is not None
        )
        for (n, n_ref), values in sorted(pairs.items())
    )
    if mdds and sds:
        df = next(pooled[m]["df"] for m in metrics if pooled.get(m))
        lines.append(
            f"Minimum detectable difference ({100 * POWER:.0f} % power, two-sided alpha {ALPHA}, unadjusted; "
            f"noncentral t of Student's two-sample test with the SD pooled over every row's seeds, {sds}, df {df}): "
            f"{mdds}. "
            "A true difference smaller than these is more likely to read undecided than different."
        )
    lines += _primary_lines(result)
    return lines


def table5_markdown(result: dict) -> str:
    """Table V's comparison with CI-HRL as a Markdown table (the report's `.md` and the README's):
    per row the seeds, E against the game's adversary and against the rule, the adversary's
    non-inferiority p, R_H, and per metric of MARGINS the difference [95 % Welch CI], Welch / TOST p
    (Benjamini-Hochberg-adjusted) and verdict; then the primary comparison. "" without a comparison."""
    from cefc_mj.eval.stats import ALPHA

    if not result.get("comparison"):
        return ""
    metrics = [m for m in MARGINS if m in SEED_METRICS]

    def interval(block: dict, m: str) -> str:
        factor, _, fmt = _scale(m)
        return _ci_text(block["ci95"][m], factor, fmt)

    header = ["method", "seeds", "E vs adversary (s)", "E vs rule (s)", "adversary non-inferior: p", "R_H (x 0.1 s)"]
    for m in metrics:
        header += [f"{m} minus {REFERENCE_METHOD} [95 % CI]", f"p / TOST p {m} (BH)", f"verdict {m}"]
    header.append("paper E / R_H")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method, row in result["rows"].items():
        seeds = row.get("training_seeds")
        if not seeds:
            continue
        rule = row.get("against_rule")
        test = row.get("adversary_noninferiority")
        cells = [
            f"**{method}**" if method == REFERENCE_METHOD else method,
            str(len(seeds["seeds"])),
            interval(seeds, "E"),
            interval(rule, "E") if rule else "-",
            "-"
            if not test
            else _p_text(test["p"]) + ("" if test["p"] is not None and test["p"] < ALPHA else " (not shown)"),
            interval(seeds, "R_H"),
        ]
        vs = row.get("vs_reference")
        for m in metrics:
            if not vs:
                cells += ["reference", "-", "-"]
                continue
            cells += [
                _difference_text(vs[m].get("difference"), m),
                f"{_p_text(vs[m].get('p_fdr'))} / {_p_text(vs[m].get('tost_p_fdr'))}",
                vs[m].get("decision", "-"),
            ]
        paper = row.get("paper")
        cells.append(f"{paper['E']:g} / {paper['R_H']:g}" if paper else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines + _primary_lines(result))


def _primary_lines(result: dict) -> list[str]:
    from cefc_mj.eval.stats import ALPHA
    from cefc_mj.seeds import GAME_PREREGISTERED_TEST_SEED

    primary = (result.get("comparison") or {}).get("primary")
    if not primary:
        return []
    status = (
        "confirmatory: the pre-registered batch"
        if result["protocol"]["seed"] == GAME_PREREGISTERED_TEST_SEED
        else f"exploratory here: batch seed {result['protocol']['seed']}, not the pre-registered one"
    )
    parts = []
    for m in PRIMARY[1]:
        factor, unit, fmt = _scale(m)
        c = primary[m]
        d = c["difference"]
        diff = "-" if d is None else f"{format(d['difference'] * factor, '+' + fmt)}{unit}"
        parts.append(f"{m} {diff}, p {_p_text(c['p_holm'])}, TOST p {_p_text(c['tost_p_holm'])}: {c['decision']}")
    return [
        "",
        f"Primary comparison (docs/research/preregistration.md; {status}): {primary['method']} against "
        f"{primary['reference']} ({primary['method']} minus {primary['reference']}, "
        f"the verdict {primary['method']}'s), "
        f"p's Holm-adjusted over {', '.join(PRIMARY[1])}, verdicts at {ALPHA}: " + "; ".join(parts) + ".",
    ]


def aggregate_lines(result: dict) -> list[str]:
    """rliable's aggregates of the result (`_aggregates`), one line; [] without them."""
    agg = (result.get("comparison") or {}).get("aggregates")
    if not agg:
        return []
    a, b = agg["methods"]
    parts = []
    for m in AGGREGATE_METRICS:
        factor, unit, fmt = _scale(m)

        def iv(x, factor=factor, unit=unit, fmt=fmt):
            return (
                f"{format(x['estimate'] * factor, fmt)}{unit} [{format(x['ci_low'] * factor, fmt)}, "
                f"{format(x['ci_high'] * factor, fmt)}]"
            )

        poi = agg[m]["probability_of_improvement"]
        parts.append(
            f"{m}: IQM {a} {iv(agg[m]['iqm'][a])}, {b} {iv(agg[m]['iqm'][b])}; "
            f"P({a} better than {b}) {poi['estimate']:.2f} [{poi['ci_low']:.2f}, {poi['ci_high']:.2f}]"
        )
    return [
        "",
        f"Aggregates over training seeds (rliable's: interquartile mean, probability of improvement, 95 % "
        f"stratified-bootstrap percentile intervals, {agg['reps']} resamples; lower E is better): "
        + "; ".join(parts)
        + ".",
    ]


def _fdr_lines(rows: dict) -> list[str]:
    """Which differences from CI-HRL hold once p is adjusted over every row compared (per metric)."""
    from cefc_mj.eval.stats import ALPHA

    compared = {method: row["vs_reference"] for method, row in rows.items() if "vs_reference" in row}
    if not compared:
        return []

    def held(m: str) -> str:
        found = [
            f"{method} ({vs[m]['verdict']}, adjusted p {vs[m]['p_fdr']:.3f})"
            for method, vs in compared.items()
            if vs[m].get("p_fdr") is not None and vs[m]["p_fdr"] < ALPHA
        ]
        return "; ".join(found) or "none"

    return [
        "",
        f"Adjusted for the {len(compared)} comparisons per metric (Benjamini-Hochberg over the rows, "
        f"scipy.stats.false_discovery_control), the differences from CI-HRL with adjusted p < {ALPHA}:",
        *(f"  {m}: {held(m)}" for m in ("R_H", "R_t", "E")),
    ]


def table4_line(result: dict) -> str | None:
    """The paper's Table IV (numbers each agent sends per decision) for the methods of a Table V
    result, read from the policy files, beside the paper's; None without such a method (--policy)."""
    paper = _paper("table4_comm_dims")
    named = {
        "MAPPO+AT-M": "MAPPO",
        "MASAC+AT-M (BenchMARL; stands in for HASAC)": "HASAC",
        "TarMAC+AT-M": "TarMAC",
        "MASIA+AT-M": "MASIA",
        "NVIF+AT-M": "NVIF",
        "CI-HRL": "ConsMAC",
    }
    cells = [
        f"{method} {row['message_dim']} (paper {paper[named[method]]})"
        for method, row in result["rows"].items()
        if method in named and "message_dim" in row
    ]
    return "Table IV, message size per agent and decision: " + ", ".join(cells) if cells else None


def plot_highlevel_table(result: dict, path: Path) -> Path:
    """Bars of R_t and E (seconds scale; Table VII per agent) per row, ours with the std over
    episodes beside the paper's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    names = list(rows)
    key = "per_agent" if result["schema"] == "cefc-eval/table7" else "seconds"
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(4 + 1.6 * len(names), 3.6))
    for ax, m in zip(axes, ("R_t", "E")):
        ours = [rows[n][key][m] for n in names]
        err = [rows[n][f"{key}_std"][m] or 0.0 for n in names]
        paper = [
            np.nan if not rows[n].get("paper") or rows[n]["paper"].get(m) is None else rows[n]["paper"][m]
            for n in names
        ]
        ax.bar(x - 0.2, ours, 0.4, yerr=err, capsize=3, label="ours")
        ax.bar(x + 0.2, paper, 0.4, label="paper")
        ax.set_xticks(x, names, rotation=20, ha="right", fontsize=8)
        ax.set_title(f"{m}{'/N' if key == 'per_agent' else ''} ({'higher' if m == 'R_t' else 'lower'} is better)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
