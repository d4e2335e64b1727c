"""The paper's Table III protocol (density, episodes, steps) and its rollout: what the Table III
evaluator (`cefc_mj.eval.table3`) and the ORCA-F baseline (`cefc_mj.baselines.orca`) both fly."""

from __future__ import annotations

import numpy as np

from cefc_mj.env import BatchedCEFCEnv

TABLE3_DENSITY = 0.05
TABLE3_EPISODES = 50
TABLE3_STEPS = 100


def roll_out(env: BatchedCEFCEnv, obs: np.ndarray, act, steps: int) -> dict[str, np.ndarray]:
    """Fly every episode of a reset `env` to its end with `act(obs) -> actions`; per-episode R_L (team
    reward per step), F, N, C [episodes]: the Table III numbers of any controller."""
    total = np.zeros(env.n_envs)
    navigation_swap = np.zeros(env.n_envs)  # R_L^a - R_L: the navigation term summed over the agents
    w_n = env.config.rewards.navigation_weight_low
    done = np.zeros(env.n_envs, dtype=bool)
    while not done.all():
        obs, reward, done, info = env.step(act(obs))
        total += reward
        per_agent = -np.linalg.norm(env.world.agent_pos - env.anchor[:, None], axis=-1).sum(axis=-1)
        navigation_swap += w_n * (per_agent - info["reward_terms"]["R_n"])
    metrics = info["metrics"]
    return {
        "R_L": total / steps,
        "R_L_agents": (total + navigation_swap) / steps,
        **{m: np.asarray(metrics[m], dtype=np.float64) for m in ("F", "N", "C")},
    }
