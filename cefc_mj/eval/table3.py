"""The paper's Table III protocol in the particle world (the paper's MPE).

One group of c agents flies to a random anchor for 100 steps at obstacle density 0.05 per m^2;
50 episodes (one batch of 50 envs, fixed seed, so every method sees the same episodes); the policy
acts deterministically (Gaussian mean). Columns as the paper prints them:

- R_L: the team reward R_L = 15 R_f + 4 R_n + 100 R_c per step, averaged over steps and episodes
  (R_n = -|centre - anchor|, the paper's low-level navigation reward);
- R_L^a: the same with the navigation term summed over the agents, -sum_i |p_i - anchor| (the paper's
  eq. 14 form); the paper's printed R_L values match this one (docs/research/baselines.md, "The unit of R_L");
- F, N: steps per episode in formation (HD < 1 m) / with the swarm centre within 1 m of the anchor;
- C: % of agent-steps in collision (a UAV disc overlapping an obstacle or another UAV).

>>> rows = run_table3([6], episodes=50, seed=0)          # doctest: +SKIP
>>> print(format_table3(rows))                           # doctest: +SKIP
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import torch

from cefc_mj import paths
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn import registry
from cefc_mj.nn.policy_io import Policy, load_policy
from cefc_mj.provenance import display_path, file_sha256
from cefc_mj.table3_protocol import TABLE3_DENSITY, TABLE3_EPISODES, TABLE3_STEPS, roll_out
from cefc_mj.task.config import TaskConfig

TABLE3_FORMATIONS = (6, 7, 8)
OBSTACLE_LIDAR_STEP1 = "AT-M-Step1 (obstacle LiDAR)"
METHODS = (
    "ORCA-F",
    "CL-M",
    OBSTACLE_LIDAR_STEP1,
    "AT-M-Step1",
    "AT-M-Step2",
    "AT-M-Step3",
    "AT-M-Safe",
    "AT-M-Nav",
    "Student",
)
"""Row names as the paper writes them (AT-M-Nav and the student are this project's additions;
ORCA-F is the baseline of cefc_mj/baselines/orca.py, CL-M the curriculum baseline trained by `cefc-train clm`,
docs/research/baselines.md). AT-M-Step1 is the Step 1 that Step 3 starts from, its LiDAR seeing obstacles and
UAVs; the obstacle-LiDAR row is Step 1 trained with a LiDAR that sees obstacles only, as the paper's
Step 1 evidently was (docs/research/layouts.md): both stand beside the paper's Step 1 row."""
PAPER_ROW = {OBSTACLE_LIDAR_STEP1: "AT-M-Step1"}
"""Our rows compared with a paper row of another name."""
COLUMNS = ("R_L", "F", "N", "C")
MADDPG = "MADDPG"
"""The paper's MADDPG row: BenchMARL's MADDPG on the formation task (`cefc-train formation-benchmarl`,
docs/formation_benchmarl.md), its policy files named MADDPG_FILE; not in METHODS until files ship."""
MADDPG_FILE = "benchmarl_maddpg_c{c}"
SEED_ROWS = frozenset({MADDPG})
"""Rows flown from every training seed's file (`<stem>.pt` for seed 0, `<stem>_seed<k>.pt`) and reported
as the mean and sample std over training seeds, not over one seed's episodes."""


def training_seed_paths(stem: str, policies_dir: Path) -> list[tuple[int, Path]]:
    """(seed, file) of each training seed's policy of one method in `policies_dir`, in seed order:
    `<stem>.pt` is seed 0 and `<stem>_seed<k>.pt` seed k (the names `cefc-train` gives)."""
    found = [(0, policies_dir / f"{stem}.pt")] if (policies_dir / f"{stem}.pt").is_file() else []
    for path in policies_dir.glob(f"{stem}_seed*.pt"):
        match = re.fullmatch(re.escape(stem) + r"_seed(\d+)", path.stem)
        if match:
            found.append((int(match.group(1)), path))
    return sorted(found)


def _paper_table3() -> dict[str, dict[str, dict[str, float]]]:
    """The paper's Table III AT-M, ORCA-F, CL-M and MADDPG rows from the shipped transcription
    (eval/paper_tables.json; MADDPG's R_L and C are not printed: None)."""
    raw = json.loads((paths.EVAL_DIR / "paper_tables.json").read_text())["table3_atm_mpe"]
    baselines = ("ORCA-F", "CL-M", MADDPG)
    return {
        c: {m: dict(zip(COLUMNS, v)) for m, v in rows.items() if m.startswith("AT-M") or m in baselines}
        for c, rows in raw.items()
        if c.isdigit()
    }


PAPER_TABLE3 = _paper_table3()


def policy_file_for(method: str, formation: int) -> str | None:
    """The shipped policy name of a Table III method for formation c (None for ORCA-F, which has no file)."""
    if method == "ORCA-F":
        return None
    if method == "Student":
        return registry.STUDENT
    if method == "CL-M":
        return registry.clm_name(formation)
    if method == MADDPG:
        return MADDPG_FILE.format(c=formation)
    if method == OBSTACLE_LIDAR_STEP1:
        return registry.lowlevel_name(formation, "step1") + "_obstacle_lidar"
    kind = {"AT-M-Safe": "safe", "AT-M-Nav": "nav"}.get(method, f"step{method[-1]}")
    return registry.lowlevel_name(formation, kind)


@torch.no_grad()
def evaluate_lowlevel_episodes(
    policy: Policy,
    formation: int,
    density: float = TABLE3_DENSITY,
    episodes: int = TABLE3_EPISODES,
    seed: int = 0,
    steps: int = TABLE3_STEPS,
) -> dict[str, np.ndarray]:
    """Per-episode R_L (per step), F, N, C [episodes] of `policy` for one group of `formation` agents."""
    task = policy.task_for(
        TaskConfig(n_agents=formation, mode="formation", obstacle_density=density, episode_steps=steps)
    )
    env = BatchedCEFCEnv(task, n_envs=episodes, seed=seed)
    if policy.obs_dim != env.layout.size:
        raise ConfigError(f"policy {policy.name}: observation size {policy.obs_dim}, the env gives {env.layout.size}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return roll_out(env, env.reset(seed=seed), policy.act, steps)
    finally:
        torch.set_num_threads(threads)


def evaluate_lowlevel(
    policy: Policy,
    formation: int,
    density: float = TABLE3_DENSITY,
    episodes: int = TABLE3_EPISODES,
    seed: int = 0,
    steps: int = TABLE3_STEPS,
) -> dict[str, float]:
    """R_L, F, N, C of `policy` averaged over `episodes` episodes of one group of `formation` agents."""
    per_episode = evaluate_lowlevel_episodes(policy, formation, density, episodes, seed, steps)
    return {m: float(v.mean()) for m, v in per_episode.items()}


POLICY_CHOICES = {
    "atm": "AT-M-Step3",
    "safe": "AT-M-Safe",
    "nav": "AT-M-Nav",
    "student": "Student",
    "orca": "ORCA-F",
    "clm": "CL-M",
    "maddpg": MADDPG,
}
"""cefc-eval's --policy aliases and the Table III row each one is."""


def _row(per_episode: dict[str, np.ndarray], c: int, method: str) -> dict:
    """Means, sample std and per-episode values of each metric, with the paper's row."""
    from cefc_mj.eval.runner import episode_stats

    return {**episode_stats(per_episode), "paper": _paper_row(c, method)}


def _paper_row(c: int, method: str) -> dict | None:
    """The paper's Table III row a method of ours stands beside, None where the paper has none."""
    return PAPER_TABLE3.get(str(c), {}).get(PAPER_ROW.get(method, method))


def _seeds_row(per_seed: list[tuple[int, Path, dict[str, np.ndarray]]], c: int, method: str) -> dict:
    """One row from several training seeds: each metric's mean over the seeds' episode means and its sample
    std over seeds (`<metric>_std`, None for one seed), the seeds' own means, files and SHA-256 under
    "seeds", every episode under "per_episode" (seed after seed)."""
    from cefc_mj.eval.runner import episode_stats

    seeds = [
        {"seed": k, "policy": path.name, "sha256": file_sha256(path), **{m: float(np.mean(v)) for m, v in ep.items()}}
        for k, path, ep in per_seed
    ]
    metrics = list(per_seed[0][2])
    row = episode_stats({m: [s[m] for s in seeds] for m in metrics})  # one value per seed: stats over seeds
    row["per_episode"] = {m: [float(v) for _, _, ep in per_seed for v in ep[m]] for m in metrics}
    return {
        "spread": "training seeds",
        "training_seeds": len(seeds),
        **row,
        "seeds": seeds,
        "paper": _paper_row(c, method),
    }


def _orca_row(c: int, episodes: int, seed: int, steps: int, required: bool, progress=None) -> dict | None:
    """ORCA-F's row (same episodes as the policies'), or None when pyrvo is missing and not required."""
    from cefc_mj.baselines.orca import PYRVO_MISSING, evaluate_orca_episodes, pyrvo_available

    if not pyrvo_available():  # pyrvo is imported only when the simulators are built: check before any work
        if required:
            raise ConfigError(f"--policy orca: {PYRVO_MISSING}")
        return None
    _flying(progress, c, "ORCA-F")
    per_episode = evaluate_orca_episodes(c, episodes=episodes, seed=seed, steps=steps)
    return {**_row(per_episode, c, "ORCA-F"), "policy": "ORCA-F (pyrvo, RVO2)", "sha256": None}


def _flying(progress, c: int, method: str) -> None:
    """Name the batch now flying beside the bar (only a method that is flown is named)."""
    if progress is not None:
        progress.set_postfix_str(f"c = {c} {method}")


def _advance(progress, episodes: int) -> None:
    if progress is not None:
        progress.update(episodes)


def _skip(progress, episodes: int) -> None:
    """Take a method that is not flown (its file is missing) off the bar's total."""
    if progress is not None:
        progress.total -= episodes
        progress.refresh()


def run_table3(
    formations=TABLE3_FORMATIONS,
    episodes: int = TABLE3_EPISODES,
    seed: int = 0,
    policies_dir: Path | None = None,
    json_path: Path | None = None,
    steps: int = TABLE3_STEPS,
    policy: str | None = None,
    provenance: dict | None = None,
    progress=None,
) -> dict:
    """Evaluate every available Table III method for each formation c (or only `policy`).

    `policy`: None = every method in METHODS; an alias of POLICY_CHOICES = that method's row; any
    other name or .pt path = one row under the policy file's name (no paper row). Returns
    {"schema", "schema_version", "protocol": {...}, "6": {"AT-M-Step3": {"R_L", "F", "N", "C"
    (means), "R_L_std", ... (sample std over episodes), "per_episode": {metric: [...]}, "paper":
    {...} or None, "policy": file name, "sha256"}, ...}, ...}. A row of SEED_ROWS is flown from every training
    seed's file and holds the mean and sample std over training seeds instead ("spread": "training
    seeds", each seed's means, file and SHA-256 under "seeds"). A method whose policy file is missing
    is left out (listed in protocol["missing"]). `provenance` (library versions, commit) rides
    along. Writes the same dict as JSON to json_path if given. `progress` (a tqdm bar, or anything
    with its `reset(total)`, `update(n)` and `set_postfix_str(text)`) counts the episodes as each
    method's batch finishes.
    """
    from cefc_mj.nn.policy_io import resolve_policy_path

    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    formations = [int(c) for c in formations]
    for c in formations:
        if not 3 <= c <= 8:
            raise ConfigError(f"formation={c}: Table III policies exist for c = 3..8")
    if not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes={episodes!r}: must be an integer >= 1")
    if not isinstance(steps, int) or steps < 1:
        raise ConfigError(f"steps={steps!r}: must be an integer >= 1")
    result: dict = {
        "schema": "cefc-eval/table3",
        "schema_version": 2,
        "protocol": {
            "backend": "particle",
            "density": TABLE3_DENSITY,
            "episodes": episodes,
            "steps": steps,
            "seed": seed,
            "policies_dir": display_path(policies_dir),
            "policy": policy,
            "comparable_to_paper": steps == TABLE3_STEPS,
            "missing": [],
        },
    }
    if provenance is not None:
        result["provenance"] = provenance
    plan = []
    for c in formations:
        if policy is None:
            wanted = [(method, policy_file_for(method, c)) for method in METHODS]
        elif policy in POLICY_CHOICES:
            wanted = [(POLICY_CHOICES[policy], policy_file_for(POLICY_CHOICES[policy], c))]
        else:
            path = resolve_policy_path(policy, policies_dir)
            wanted = [(path.stem, str(path))]
        plan.append((c, wanted))
    if progress is not None:  # an upper bound: a method whose file (or pyrvo) is missing is taken off
        progress.reset(total=episodes * sum(len(wanted) for _, wanted in plan))
    for c, wanted in plan:
        rows = {}
        for method, name in wanted:
            if method == "ORCA-F":
                row = _orca_row(c, episodes, seed, steps, required=policy is not None, progress=progress)
                if row is None:
                    result["protocol"]["missing"].append(
                        f"{c}/ORCA-F (pyrvo not installed: pip install -e '.[baselines]')"
                    )
                    _skip(progress, episodes)
                else:
                    rows[method] = row
                    _advance(progress, episodes)
                continue
            if method in SEED_ROWS:
                seed_files = training_seed_paths(name, policies_dir)
                if seed_files:
                    if progress is not None:  # one batch per training seed
                        progress.total += episodes * (len(seed_files) - 1)
                    per_seed = []
                    for k, path in seed_files:
                        _flying(progress, c, f"{method} seed {k}")
                        flown = evaluate_lowlevel_episodes(
                            load_policy(path), c, episodes=episodes, seed=seed, steps=steps
                        )
                        per_seed.append((k, path, flown))
                        _advance(progress, episodes)
                    rows[method] = {**_seeds_row(per_seed, c, method), "policy": f"{name}[_seed<k>].pt"}
                    continue
            try:
                path = resolve_policy_path(name, policies_dir)
            except CheckpointError:
                if policy is not None:
                    raise
                hint = {
                    "CL-M": f": train it with cefc-train clm --formation {c}",
                    MADDPG: f": train it with cefc-train formation-benchmarl --formation {c}",
                }.get(method, "")
                result["protocol"]["missing"].append(f"{c}/{method} ({name}.pt{hint})")
                _skip(progress, episodes)
                continue
            _flying(progress, c, method)
            per_episode = evaluate_lowlevel_episodes(load_policy(path), c, episodes=episodes, seed=seed, steps=steps)
            rows[method] = {**_row(per_episode, c, method), "policy": path.name, "sha256": file_sha256(path)}
            _advance(progress, episodes)
        result[str(c)] = rows
    if json_path is not None:
        write_atomic(Path(json_path), json.dumps(result, indent=2) + "\n")
    return result


def format_table3(result: dict) -> str:
    """A plain-text table: ours (mean ± std over episodes) beside the paper's numbers ('-' if none)."""
    from cefc_mj.eval.runner import format_mean_std

    proto = result["protocol"]
    lines = [
        f"Table III protocol ({proto['backend']}, density {proto['density']}/m^2, {proto['episodes']} episodes x "
        f"{proto['steps']} steps, seed {proto['seed']}). R_L: team reward per step; F, N: steps in formation / "
        "with the swarm centre within 1 m of the anchor; C: % of agent-steps in collision. R_L^a: R_L with the "
        "navigation term summed over the agents, the form the paper's R_L values match.",
        "ours: mean ± sample std over episodes; paper: the paper's Table III row ('-': the paper has none).",
    ]
    if any(row.get("spread") == "training seeds" for c, rows in result.items() if c.isdigit() for row in rows.values()):
        lines.append(
            "A row marked (n seeds): mean ± sample std over n training seeds, each seed's value its mean over "
            "the episodes."
        )
    if proto["steps"] != TABLE3_STEPS:
        lines.append(f"F, N over {proto['steps']} steps; the paper's are over {TABLE3_STEPS}: not comparable.")
    table = [["c", "method", "", "R_L/step", "R_L^a/step", "F (steps)", "N (steps)", "C (%)"]]
    for c, rows in result.items():
        if not c.isdigit():
            continue
        for method, row in rows.items():
            paper = row.get("paper") or {}
            n = row.get("training_seeds")
            label = f"{method} ({n} seed{'s' * (n != 1)})" if row.get("spread") == "training seeds" else method
            table.append(
                [c, label, "ours"]
                + [
                    format_mean_std(row[m], row.get(f"{m}_std"), ".2f") if m in row else "-"
                    for m in ("R_L", "R_L_agents", *COLUMNS[1:])
                ]
            )
            # the paper prints one R_L; its values match R_L^a, so it stands in that column
            table.append(
                ["", "", "paper", "-"] + ["-" if paper.get(m) is None else format(paper[m], ".2f") for m in COLUMNS]
            )
    widths = [max(len(r[i]) for r in table) for i in range(len(table[0]))]
    for r in table:
        lines.append(
            "  ".join(
                cell.ljust(w) if i in (1, 2) else cell.rjust(w) for i, (cell, w) in enumerate(zip(r, widths))
            ).rstrip()
        )
    if proto.get("missing"):
        lines.append("missing policies: " + ", ".join(proto["missing"]))
    return "\n".join(lines)
