"""Table V's game one game at a time (SITL-M): each UAV's whole hierarchy in its own process
(`cefc_mj.deploy.game.run_sitl_game`, passed in by cefc-eval) beside the same game in one process
(`play_game`), their paired difference, the fidelity targets, the timing and the bytes on the wire."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from cefc_mj import paths
from cefc_mj.errors import ConfigError
from cefc_mj.eval.conditions import Conditions
from cefc_mj.eval.highlevel import (
    GAME_POLICY,
    PAPER_CONDITIONS,
    adversary_text,
    paper_table,
    protocol_record,
    row_stats,
    table_low_level,
    where_text,
)
from cefc_mj.eval.stats import paired_difference
from cefc_mj.game_protocol import GAME_AGENTS, GAME_METRICS, GAME_STEPS, game_task, play_highlevel
from cefc_mj.hierarchy import DECISION_INTERVAL, HierarchicalCEFCEnv
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.highlevel_policy import highlevel_policy_path, load_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.provenance import file_sha256
from cefc_mj.task.config import TaskConfig

TABLE4_METHOD = {
    "mappo": "MAPPO",
    "tarmac": "TarMAC",
    "masia": "MASIA",
    "nvif": "NVIF",
    "consmac-a": "ConsMAC",
    "consmac-o": "ConsMAC",
}
"""The paper's Table IV row of each high-level variant (what it sends per decision)."""


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
        table_low_level(task),
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
    low_level = table_low_level(task)
    result = {
        "schema": "cefc-eval/table5",
        "schema_version": 1,
        "protocol": protocol_record(episodes, seed, low_level, paths.POLICIES_DIR, record, where),
        "rows": {},
    }
    result["protocol"].update({"steps": steps, "sitl_m": True, "seeds": [s.seed for s in specs]})
    if provenance is not None:
        result["provenance"] = provenance
    games = [runner(spec, sitl) for spec in specs]
    per_episode = {m: np.array([g.figures[m] for g in games]) for m in GAME_METRICS}
    row = row_stats(per_episode)
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
        ref_row = row_stats(ref)
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
        f"Table V game over SITL-M ({where_text(proto)}, N = {proto['n_agents']}, {proto['episodes']} game(s) x "
        f"{proto['steps']} steps, seeds {proto['seeds'][0]}..{proto['seeds'][-1]}, adversary "
        f"{adversary_text(proto['adversary'])}, low level {proto['low_level']['name']}).",
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
        f"floats per decision (paper's Table IV, {method}: {paper_table('table4_comm_dims').get(method, '-')})",
    ]
    return "\n".join(lines)
