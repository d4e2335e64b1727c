"""One iteration's episodes: collected by a batch of envs (`collect_shard`, in the learner's process
or a rollout worker's) and merged into the `Rollout` the MAPPO update reads (`merge_shards`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.nn.atm import ATMActor
from cefc_mj.seeds import TRAINING
from cefc_mj.task.config import TaskConfig


def iteration_seed(seed: int, iteration: int, stream: int = 0) -> int:
    """The env seed of one iteration's episodes: independent streams per (run seed, iteration[, stream
    > 0 for further batches of the same iteration]), inside the training block of game seeds
    (cefc_mj.seeds.TRAINING), so no training game is a validation or test game."""
    drawn = int(np.random.SeedSequence([seed, iteration, *([stream] if stream else [])]).generate_state(1)[0])
    return TRAINING.start + drawn % TRAINING.size


@dataclass
class Rollout:
    """One iteration's data, time-major: T steps x B envs (x N agents)."""

    obs: torch.Tensor  # [T, B, N, D]
    next_obs: torch.Tensor  # [T, B, N, D] observation after each step (an episode's final one before reset)
    actions: torch.Tensor  # [T, B, N, A] sampled (unclipped) actions
    logp: torch.Tensor  # [T, B, N] log-probability of the actions under the acting policy
    states: torch.Tensor  # [T, B, S] global state before each step
    next_states: torch.Tensor  # [T, B, S] global state after each step (an episode's final state before reset)
    rewards: torch.Tensor  # [T, B, N] each agent's learning reward (see the module docstring)
    episode_end: torch.Tensor  # [T, B] bool, the step ended an episode (time limit)
    stats: dict[str, float]  # episode statistics (returns, reward terms, F/N/C)


def agent_rewards(credit: str, team_reward: np.ndarray, team_collision: np.ndarray, own: np.ndarray, w) -> np.ndarray:
    """Per-agent learning rewards [B, N] from the team reward [B] and each agent's collision penalty
    CR_i >= 0 [B, N] under collision credit `credit` (see the module docstring)."""
    n = own.shape[-1]
    if credit == "team":
        return np.repeat(team_reward[:, None], n, axis=1).astype(np.float32)
    shared = team_reward - w.collision_weight * team_collision  # 15 R_f + 4 R_n
    return (shared[:, None] - w.collision_weight * own).astype(np.float32)


@dataclass
class Shard:
    """What one batch of envs collected in one iteration: time-major tensors and episode tallies."""

    buf: dict[str, torch.Tensor]  # Rollout's fields, [T, B_shard, ...]
    returns: list[float]  # team return of every finished episode
    metrics: dict[str, list[float]]  # F, N, C, ... of every finished episode
    term_sums: dict[str, float]  # each reward term summed over steps and envs


@torch.no_grad()
def collect_shard(
    env: BatchedCEFCEnv, actor: ATMActor, generator: torch.Generator, steps: int, credit: str, env_seed: int
) -> Shard:
    """`steps` steps of every env of `env` (whole episodes), actions sampled from `actor` with
    `generator`; the episodes are seeded by `env_seed` (the world's own draws too, such as wind).

    An env whose episode ends at the last step is not reset here: the next shard starts every env
    afresh with `env.reset(seed=...)` (which reseeds all its draws), so that reset, a whole MuJoCo
    settle in wind, would be thrown away."""
    reseed_world = getattr(env.world, "reseed", None)
    if reseed_world is not None:
        reseed_world((env_seed, 1))
    obs = env.reset(seed=env_seed).copy()
    state = env.global_state()
    buf = {k: [] for k in ("obs", "next_obs", "actions", "logp", "states", "next_states", "rewards", "episode_end")}
    w = env.config.rewards
    episode_return = np.zeros(env.n_envs)
    term_sums: dict[str, float] = {}
    returns, metrics = [], {}
    std = actor.log_std.exp()
    for t in range(steps):
        obs_t = torch.from_numpy(obs)
        mean = actor(obs_t)
        action = mean + std * torch.randn(mean.shape, generator=generator)
        logp = torch.distributions.Normal(mean, std).log_prob(action).sum(-1)
        next_obs, reward, done, info = env.step(actor.to_acceleration(action, obs_t).numpy())
        next_state = env.global_state()
        own_reward = agent_rewards(credit, reward, info["reward_terms"]["R_c"], env.agent_collision_penalty, w)
        for k, v in (
            ("obs", obs_t),
            ("next_obs", torch.from_numpy(next_obs.copy())),
            ("actions", action),
            ("logp", logp),
            ("states", torch.from_numpy(state)),
            ("next_states", torch.from_numpy(next_state)),
            ("rewards", torch.from_numpy(own_reward)),
            ("episode_end", torch.from_numpy(done.copy())),
        ):
            buf[k].append(v)
        episode_return += reward
        for name, value in info["reward_terms"].items():
            term_sums[name] = term_sums.get(name, 0.0) + float(np.sum(value))
        obs, state = next_obs.copy(), next_state
        if done.any():
            returns.extend(episode_return[done].tolist())
            episode_return[done] = 0.0
            for name, value in info["metrics"].items():
                metrics.setdefault(name, []).extend(value[done].tolist())
            if t < steps - 1:
                obs = env.reset(mask=done).copy()
                state = env.global_state()
    return Shard({k: torch.stack(v) for k, v in buf.items()}, returns, metrics, term_sums)


def merge_shards(shards: list[Shard], episode_steps: int) -> Rollout:
    """One Rollout from the shards of an iteration, envs side by side in shard order."""
    buf = {k: torch.cat([s.buf[k] for s in shards], dim=1) for k in shards[0].buf}
    returns = [r for s in shards for r in s.returns]
    metrics: dict[str, list[float]] = {}
    term_sums: dict[str, float] = {}
    for s in shards:
        for name, values in s.metrics.items():
            metrics.setdefault(name, []).extend(values)
        for name, total in s.term_sums.items():
            term_sums[name] = term_sums.get(name, 0.0) + total
    n_steps = buf["episode_end"].numel()
    stats = {
        "episode_return": float(np.mean(returns)),
        "reward_per_step": float(np.mean(returns)) / episode_steps,
        **{f"term/{name}": total / n_steps for name, total in term_sums.items()},
        **{f"metric/{name}": float(np.mean(v)) for name, v in metrics.items() if name != "E"},
        "episodes": len(returns),
    }
    return Rollout(**buf, stats=stats)


def particle_env(task_cfg: TaskConfig, n_envs: int, seed: int) -> BatchedCEFCEnv:
    """The training env of the paper: `n_envs` particle-world episodes."""
    return BatchedCEFCEnv(task_cfg, n_envs=n_envs, seed=seed)
