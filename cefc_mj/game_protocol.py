"""The high level's game (the paper's Sec. V-C protocol) and its rollout: what Tables V-VII
(`cefc_mj.eval.highlevel`), the adversaries' and the high level's training, the recorders and the
SITL-M agents all play. The twin of `cefc_mj.table3_protocol` for the hierarchical game.

Protocol: the hierarchical CEFC game of `cefc_mj.hierarchy` with N = 8 UAVs, 2 targets drawn from
the 4 corners, obstacles at 0.03 per m^2, 400 low-level steps (40 decisions of 10), 50 episodes in
one batch with a fixed seed (every method sees the same episodes), the mode of each anchor
distribution, and the shipped distilled student (`atm_student`) as the low level.

Figures: R_H = R_t + R_n + R_e (the weighted reward terms) and E (steps in which some agent is
within 2 m of the adversary), each summed over an episode's 400 low-level steps; x dt (0.1 s) gives
the paper's scale (docs/research/high_level.md, "Units of Tables V and VI").
"""

from __future__ import annotations

import numpy as np
import torch

from cefc_mj.errors import ConfigError
from cefc_mj.hierarchy import DECISION_INTERVAL, HierarchicalCEFCEnv, LowLevel
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.nn.registry import HIERARCHY_LOWLEVEL
from cefc_mj.task.config import ADVERSARIES, TaskConfig
from cefc_mj.task.messages import MessageChannel

EPISODES = 50
GAME_AGENTS = 8
GAME_DENSITY = 0.03
GAME_STEPS = 400
LOW_LEVEL = HIERARCHY_LOWLEVEL
DT = 0.1
"""Seconds per low-level step: the factor from our per-episode sums to the paper's scale."""
COLUMNS = ("R_H", "R_t", "R_n", "R_e", "E")
"""The paper's columns of Tables V-VII."""
GAME_METRICS = ("R_H", "R_t", "R_n", "R_e", "E", "E_agents", "F", "C")
"""The per-episode figures of one game (`play_highlevel`'s)."""


def game_task(adversary: str = "nearest_group", deviation: float = 0.0, n_agents: int = GAME_AGENTS) -> TaskConfig:
    """The CEFC game of Tables V-VII: the high level's training game (`HighLevelConfig.task`) except
    that here a rule adversary steers around the obstacles and the agents act on the fused position
    estimate (as in `cefc-eval`; without sensing deviation, in m, the estimate is the exact position).
    adversary: a rule, or 'learned' (the env then needs the adversary's policy:
    `nn.adversary_policy.resolve_adversary`). n_agents: the swarm's size (Table VII; the observations
    read the 7 nearest neighbours whatever N is). A rule adversary steers around the obstacles, as the
    PPO adversary learns to (it is penalised inside them): both play by the same physical rule
    (docs/research/high_level.md, "The adversary")."""
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
