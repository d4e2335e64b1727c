"""The high level's evaluation runs: the paper's Table V (CI-HRL against high-level baselines, over
training seeds), Table VI (CI-HRL against adversary strategies) and Table VII (swarm sizes), in the
particle world (the paper's MPE) or on quadrotors.

The game and its rollout are `cefc_mj.game_protocol`'s (N = 8 UAVs, 2 targets, obstacles at 0.03 per
m^2, 400 low-level steps, 50 episodes in one seeded batch, the mode of each anchor distribution, the
distilled student as the low level). The statistics over training seeds are
`cefc_mj.eval.highlevel_comparison`'s, the reports `cefc_mj.eval.highlevel_report`'s, and the
one-game-at-a-time SITL-M game `cefc_mj.eval.highlevel_sitl`'s.

Columns: R_H = R_t + R_n + R_e (the weighted reward terms) and E (steps in which some agent is
within 2 m of the adversary). Each is summed over an episode's 400 low-level steps (`per_episode`)
and reported also in seconds of flight (`x dt`, dt = 0.1 s): the paper's printed values fit the
second scale (its MAPPO+AT-M E of 8.78 against our 8.8 s; its R_n of -327 is impossible as a
400-step sum, since the urgency-weighted distances start at about 180 per step and both targets
cannot be covered in under 2 s). docs/research/high_level.md, "Units of Tables V and VI", has the argument.

>>> result = run_table5(episodes=50, seed=0)          # doctest: +SKIP
>>> from cefc_mj.eval.highlevel_report import format_highlevel_table
>>> print(format_highlevel_table(result))             # doctest: +SKIP
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from cefc_mj import paths
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.eval.conditions import Conditions
from cefc_mj.eval.highlevel_comparison import add_comparisons, adversary_strength, seed_block
from cefc_mj.game_protocol import (
    COLUMNS,
    DT,
    EPISODES,
    GAME_AGENTS,
    GAME_DENSITY,
    GAME_STEPS,
    LOW_LEVEL,
    evaluate_highlevel_episodes,
    game_task,
)
from cefc_mj.hierarchy import DECISION_INTERVAL, LowLevel, load_low_level, recorded_low_level
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.highlevel_policy import highlevel_policy_path, load_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.provenance import display_path, file_sha256
from cefc_mj.task.config import TaskConfig

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
GAME_POLICY = "cihrl_consmac_a"
"""The high-level policy Tables VI and VII play: CI-HRL (ConsMAC-A)."""
PAPER_CONDITIONS = Conditions("particle")
"""Where the paper plays the game: its MPE (particles), calm air, exact sensing."""


# ---------------------------------------------------------------------------- rows
def paper_table(key: str) -> dict:
    return json.loads((paths.EVAL_DIR / "paper_tables.json").read_text())[key]


def row_stats(per_episode: dict[str, np.ndarray]) -> dict:
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
    row = row_stats(
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
            f"trained against {adversary_text(trained_against)}, played here against {adversary_text(adversary)}"
        )
    return row


def protocol_record(
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


def table_low_level(task: TaskConfig, spec: str = LOW_LEVEL) -> LowLevel:
    """The shipped student, or the shipped low level `spec` names (wherever the high-level policies
    are read from)."""
    try:
        return load_low_level(spec, task)
    except CheckpointError as e:
        raise CheckpointError(f"the low level of Tables V-VI: {e}") from None


def where_text(proto: dict) -> str:
    text = "particle" if proto["backend"] == "particle" else "MuJoCo quadrotors"
    if proto["wind"]:
        text += f", wind {proto['wind']:g} m/s"
    if proto["deviation"]:
        text += f", deviation {proto['deviation']:g} m (fused estimate)"
    return text


def adversary_text(record) -> str:
    """A report's adversary: "per row" (Table VI), a rule, or a trained adversary's file."""
    if not record:
        return "per row"
    if isinstance(record, str):  # reports written before trained adversaries
        return record
    return record.get("rule") or f"{record['policy']} (trained)"


GameProgress = Callable[[int, int], None]
"""progress(games flown so far, games in all) of a table's run (`cefc-eval` draws it as a bar)."""


def _progress_reporter(progress: GameProgress | None, total: int) -> Callable[[int], None]:
    """A counter that tells `progress` (if any) the games flown, starting at 0 of `total`."""
    flown = 0
    if progress is not None:
        progress(0, total)

    def report(games: int) -> None:
        nonlocal flown
        flown += games
        if progress is not None:
            progress(flown, total)

    return report


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
    low_level = table_low_level(task, job.low_level)
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
    progress: GameProgress | None = None,
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
    so the figures do not depend on it). progress(games flown, games in all), if given, is called
    before the first batch and after each."""
    from cefc_mj.executors import ExecutorConfig, map_unordered

    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    where = where or PAPER_CONDITIONS
    kind, adversary_policy, record = resolve_adversary(adversary, policies_dir)
    task = game_task(kind, deviation=where.deviation)
    low_level = table_low_level(task)
    result = {
        "schema": "cefc-eval/table5",
        "schema_version": 1,
        "protocol": protocol_record(episodes, seed, low_level, policies_dir, record, where),
        "rows": {},
    }
    paper = paper_table("table5_cihrl_mpe")
    if provenance is not None:
        result["provenance"] = provenance
    if policy is not None:
        path = highlevel_policy_path(policy, policies_dir)
        report = _progress_reporter(progress, episodes)
        result["rows"][path.stem] = {
            **_evaluate_file(path, task, low_level, episodes, seed, where, adversary_policy, record),
            "paper": None,
        }
        report(episodes)
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
    report = _progress_reporter(progress, len(jobs) * episodes)
    flown = {}
    for job, row in map_unordered(_fly_file, list(jobs.values()), ExecutorConfig(workers=workers)):
        flown[job] = row
        report(episodes)
    for method, stem, paper_row, files in rows:
        per_seed = {k: flown[jobs[method, adversary, k]] for k in files}
        first = next(iter(files))  # seed 0 where shipped; a run of seeds 100.. has no seed 0
        row = per_seed[first]
        row["paper"] = dict(zip(COLUMNS, paper[paper_row])) if paper_row is not None else None
        if file_low_level[files[first]] != LOW_LEVEL:
            low = table_low_level(task, file_low_level[files[first]])
            row["low_level"] = low.describe() | {"name": low.name}
        row["training_seeds"] = seed_block(per_seed, files)
        if against_rule:
            row["against_rule"] = seed_block({k: flown[jobs[method, "nearest_group", k]] for k in files}, files)
            row["adversary_strength"] = adversary_strength(row["training_seeds"]["E"], row["against_rule"]["E"])
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
    progress: GameProgress | None = None,
) -> dict:
    """Table VI: one high-level policy (default CI-HRL) against each adversary strategy, the same
    episodes otherwise. Columns R_t, R_e, E as the paper prints them (R_H, R_n ride along); a row
    without a paper column (the nearest-group rule) has paper None. An adversary of TABLE6_TRAINED_LATER
    (DDPG) whose file is not in policies_dir is left out; protocol["missing"] says how to train it.
    progress: as in `run_table5`."""
    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    path = highlevel_policy_path(policy, policies_dir)
    untrained = {name for name in TABLE6_TRAINED_LATER if not (policies_dir / f"{name}.pt").is_file()}
    rows = [row for row in TABLE6_ROWS if row[1] not in untrained]
    adversaries = {column: resolve_adversary(adversary, policies_dir) for column, adversary, _ in rows}
    where = where or PAPER_CONDITIONS
    low_level = table_low_level(game_task())
    result = {
        "schema": "cefc-eval/table6",
        "schema_version": 1,
        "protocol": protocol_record(episodes, seed, low_level, policies_dir, None, where),
        "rows": {},
    }
    result["protocol"]["policy"] = path.name
    result["protocol"]["missing"] += [
        f"{column} ({name}.pt: not trained yet; train it with `{TABLE6_TRAINED_LATER[name]}`)"
        for column, name, _ in TABLE6_ROWS
        if name in untrained
    ]
    paper = paper_table("table6_adversaries")
    if provenance is not None:
        result["provenance"] = provenance
    report = _progress_reporter(progress, len(rows) * episodes)
    for column, adversary, differs in rows:
        kind, adversary_policy, record = adversaries[column]
        row = _evaluate_file(path, game_task(kind, where.deviation), low_level, episodes, seed, where, adversary_policy)
        report(episodes)
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
    progress: GameProgress | None = None,
) -> dict:
    """Table VII: one high-level policy (default CI-HRL, trained with N = 8) in games of N UAVs for
    each N in `sizes`, the same adversary, targets and obstacle density; each row adds the per-agent
    averages (R_H, R_t, R_n, R_e and E in seconds, divided by N), the paper's columns. progress: as in
    `run_table5`."""
    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    path = highlevel_policy_path(policy, policies_dir)
    where = where or PAPER_CONDITIONS
    if not sizes or any(not isinstance(n, int) or isinstance(n, bool) or not 3 <= n <= 32 for n in sizes):
        raise ConfigError(f"sizes={sizes!r}: must be swarm sizes in [3, 32]")
    kind, adversary_policy, record = resolve_adversary(adversary, policies_dir)
    low_level = table_low_level(game_task(kind))
    result = {
        "schema": "cefc-eval/table7",
        "schema_version": 1,
        "protocol": protocol_record(episodes, seed, low_level, policies_dir, record, where),
        "rows": {},
    }
    result["protocol"].update({"policy": path.name, "n_agents": list(sizes)})
    paper = paper_table("table7_large_scale")
    if provenance is not None:
        result["provenance"] = provenance
    report = _progress_reporter(progress, len(sizes) * episodes)
    for n in sizes:
        task = game_task(kind, where.deviation, n_agents=n)
        row = _evaluate_file(path, task, low_level, episodes, seed, where, adversary_policy, record)
        report(episodes)
        row["n_agents"] = n
        row["per_agent"] = {m: row["seconds"][m] / n for m in COLUMNS}
        row["per_agent_std"] = {
            m: row["seconds_std"][m] / n if row["seconds_std"][m] is not None else None for m in COLUMNS
        }
        row["paper"] = dict(zip(COLUMNS, paper[str(n)])) if str(n) in paper else None
        result["rows"][f"N = {n}"] = row
    return result
