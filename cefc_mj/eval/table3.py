"""The paper's Table III protocol in the particle world (the paper's MPE).

One group of c agents flies to a random anchor for 100 steps at obstacle density 0.05 per m^2;
50 episodes (one batch of 50 envs, fixed seed, so every method sees the same episodes); the policy
acts deterministically (Gaussian mean). Columns as the paper prints them:

- R_L: the team reward R_L = 15 R_f + 4 R_n + 100 R_c per step, averaged over steps and episodes;
- F, N: steps per episode in formation (HD < 1 m) / with the swarm centre within 1 m of the anchor;
- C: % of agent-steps in collision (a UAV disc overlapping an obstacle or another UAV).

>>> rows = run_table3([6], episodes=50, seed=0)          # doctest: +SKIP
>>> print(format_table3(rows))                           # doctest: +SKIP
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from cefc_mj import paths
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.policy_io import Policy, load_policy
from cefc_mj.task.config import TaskConfig

TABLE3_DENSITY = 0.05
TABLE3_EPISODES = 50
TABLE3_STEPS = 100
TABLE3_FORMATIONS = (6, 7, 8)
METHODS = ("AT-M-Step1", "AT-M-Step2", "AT-M-Step3", "AT-M-Safe", "AT-M-Robust", "AT-M-Quad", "Student")
"""Row names as the paper writes them (AT-M-Robust, AT-M-Quad and the student are this project's additions)."""
COLUMNS = ("R_L", "F", "N", "C")


def _paper_table3() -> dict[str, dict[str, dict[str, float]]]:
    """The paper's Table III AT-M rows from the shipped transcription (eval/paper_tables.json)."""
    raw = json.loads((paths.EVAL_DIR / "paper_tables.json").read_text())["table3_atm_mpe"]
    return {c: {m: dict(zip(COLUMNS, v)) for m, v in rows.items() if m.startswith("AT-M")} for c, rows in raw.items() if c.isdigit()}


PAPER_TABLE3 = _paper_table3()


def policy_file_for(method: str, formation: int) -> str:
    """The shipped policy name of a Table III method for formation c."""
    if method == "Student":
        return "atm_student"
    if method == "AT-M-Safe":
        return f"atm_c{formation}_safe"
    if method == "AT-M-Robust":
        return f"atm_c{formation}_robust"
    if method == "AT-M-Quad":
        return f"atm_c{formation}_quad"
    return f"atm_c{formation}_step{method[-1]}"


@torch.no_grad()
def evaluate_lowlevel(policy: Policy, formation: int, density: float = TABLE3_DENSITY, episodes: int = TABLE3_EPISODES,
                      seed: int = 0, steps: int = TABLE3_STEPS) -> dict[str, float]:
    """R_L, F, N, C of `policy` over `episodes` episodes of one group of `formation` agents."""
    task = TaskConfig(n_agents=formation, mode="formation", obstacle_density=density, episode_steps=steps)
    env = BatchedCEFCEnv(task, n_envs=episodes, seed=seed)
    if policy.obs_dim != env.layout.size:
        raise ConfigError(f"policy {policy.name}: observation size {policy.obs_dim}, the env gives {env.layout.size}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        obs = env.reset(seed=seed)
        total = np.zeros(episodes)
        done = np.zeros(episodes, dtype=bool)
        while not done.all():
            obs, reward, done, info = env.step(policy.act(obs))
            total += reward
        metrics = info["metrics"]
    finally:
        torch.set_num_threads(threads)
    return {
        "R_L": float(total.mean() / steps),
        "F": float(metrics["F"].mean()),
        "N": float(metrics["N"].mean()),
        "C": float(metrics["C"].mean()),
    }


def run_table3(formations=TABLE3_FORMATIONS, episodes: int = TABLE3_EPISODES, seed: int = 0,
               policies_dir: Path | None = None, json_path: Path | None = None) -> dict:
    """Evaluate every available Table III method for each formation c.

    Returns {"protocol": {...}, "6": {"AT-M-Step3": {"R_L", "F", "N", "C", "paper": {...} or None,
    "policy": file name}, ...}, ...}. A method whose policy file is missing is left out (listed in
    protocol["missing"]). Writes the same dict as JSON to json_path if given.
    """
    policies_dir = Path(policies_dir) if policies_dir is not None else paths.POLICIES_DIR
    formations = [int(c) for c in formations]
    for c in formations:
        if not 3 <= c <= 8:
            raise ConfigError(f"formation={c}: Table III policies exist for c = 3..8")
    if not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes={episodes!r}: must be an integer >= 1")
    result: dict = {
        "protocol": {"backend": "particle", "density": TABLE3_DENSITY, "episodes": episodes, "steps": TABLE3_STEPS,
                     "seed": seed, "policies_dir": str(policies_dir), "missing": []},
    }
    for c in formations:
        rows = {}
        for method in METHODS:
            name = policy_file_for(method, c)
            if not (policies_dir / f"{name}.pt").is_file():
                result["protocol"]["missing"].append(f"{c}/{method} ({name}.pt)")
                continue
            policy = load_policy(name, policies_dir)
            row = evaluate_lowlevel(policy, c, episodes=episodes, seed=seed)
            row["paper"] = PAPER_TABLE3.get(str(c), {}).get(method)
            row["policy"] = f"{name}.pt"
            rows[method] = row
        result[str(c)] = rows
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(Path(json_path), json.dumps(result, indent=2) + "\n")
    return result


def format_table3(result: dict) -> str:
    """A plain-text table: ours beside the paper's numbers (paper in parentheses, '-' if none)."""
    proto = result["protocol"]
    lines = [
        f"Table III protocol ({proto['backend']}, density {proto['density']}/m^2, {proto['episodes']} episodes x "
        f"{proto['steps']} steps, seed {proto['seed']}); ours (paper)",
        f"{'c':>2}  {'method':<11} {'R_L/step':>18} {'F (steps)':>16} {'N (steps)':>16} {'C (%)':>14}",
    ]

    def cell(ours: float, paper_value: float | None, width: int, fmt: str) -> str:
        ref = "-" if paper_value is None else format(paper_value, fmt)
        return f"{format(ours, fmt)} ({ref})".rjust(width)

    for c, rows in result.items():
        if c == "protocol":
            continue
        for method, row in rows.items():
            paper = row.get("paper") or {}
            lines.append(
                f"{c:>2}  {method:<11} {cell(row['R_L'], paper.get('R_L'), 18, '.2f')} {cell(row['F'], paper.get('F'), 16, '.2f')}"
                f" {cell(row['N'], paper.get('N'), 16, '.2f')} {cell(row['C'], paper.get('C'), 14, '.2f')}"
            )
    if proto.get("missing"):
        lines.append("missing policies: " + ", ".join(proto["missing"]))
    return "\n".join(lines)
