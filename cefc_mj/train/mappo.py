"""MAPPO for the low-level game (CTDE, parameter sharing, centralized critic), CleanRL-style.

One `MAPPO` object owns the batched env, the shared actor (every agent runs the same AT-M network
on its own observation), the centralized critic, their Adam optimizers, the value normalizer and a
torch RNG. One iteration = collect whole episodes in all envs (`collect`), then PPO epochs over them
(`update`).

Critic and credit. The critic is MAPPO's agent-specific centralized critic V(s, z_i): the env's
global state s concatenated with agent i's observation z_i, one value per agent. With
`collision_credit="team"` every agent learns from the paper's team reward R_L. With "agent" (the
default) the collision term is credited to the agent it belongs to: agent i learns from
    r_i = 15 R_f + 4 R_n - 100 CR_i,
where R_c = -sum_i CR_i (eq. 16). R_f and R_n are group terms and stay shared. The other agents'
CR_j depend on agent i's action only through contacts, so dropping them from i's signal removes
N - 1 agents' collision noise from its advantage while keeping the weight of its own collisions;
with 100 x R_c dominating R_L this is what lets formation and navigation be learned within our
budget. Logged returns are always the team R_L. `state_dict()` holds everything a resumed run needs;
every iteration's episodes are seeded from (seed, iteration), so a resumed run replays exactly what
the uninterrupted one would have done.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.nn.atm import ATMActor, Critic
from cefc_mj.seeds import TRAINING
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import PPOConfig
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, learner_state, load_learner_state, ppo_epochs


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


class MAPPO:
    """The MAPPO learner for one low-level training stage."""

    def __init__(
        self,
        task_cfg: TaskConfig,
        ppo: PPOConfig,
        actor: ATMActor,
        critic: Critic,
        seed: int,
        value_norm: ValueNorm | None = None,
    ):
        self.task_cfg = task_cfg
        self.ppo = ppo
        self.seed = seed
        self.env = BatchedCEFCEnv(task_cfg, n_envs=ppo.n_envs, seed=seed)
        if critic.state_dim != self.env.state_size + self.env.layout.size:
            raise ValueError(
                f"critic input {critic.state_dim} != global state {self.env.state_size} + "
                f"observation {self.env.layout.size}"
            )
        self.actor = actor
        self.critic = critic
        self.value_norm = value_norm if value_norm is not None else ValueNorm()
        self.actor_opt = torch.optim.Adam(actor.parameters(), lr=ppo.lr, eps=1e-5)
        self.critic_opt = torch.optim.Adam(critic.parameters(), lr=ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(seed)
        self.iteration = 0
        self.agent_steps = 0
        self.elapsed = 0.0

    # ------------------------------------------------------------------ rollout
    @torch.no_grad()
    def collect(self) -> Rollout:
        """Run `episodes_per_iteration` whole episodes in every env with the current policy."""
        env, steps = self.env, self.ppo.episodes_per_iteration * self.task_cfg.steps
        obs = env.reset(seed=iteration_seed(self.seed, self.iteration)).copy()
        state = env.global_state()
        buf = {k: [] for k in ("obs", "next_obs", "actions", "logp", "states", "next_states", "rewards", "episode_end")}
        w = self.task_cfg.rewards
        episode_return = np.zeros(env.n_envs)
        term_sums: dict[str, np.ndarray] = {}
        returns, metrics = [], {}
        std = self.actor.log_std.exp()
        for _ in range(steps):
            obs_t = torch.from_numpy(obs)
            mean = self.actor(obs_t)
            action = mean + std * torch.randn(mean.shape, generator=self.generator)
            logp = torch.distributions.Normal(mean, std).log_prob(action).sum(-1)
            next_obs, reward, done, info = env.step(self.actor.to_acceleration(action, obs_t).numpy())
            next_state = env.global_state()
            agent_reward = self.agent_rewards(reward, info["reward_terms"]["R_c"], env.agent_collision_penalty, w)
            for k, v in (
                ("obs", obs_t),
                ("next_obs", torch.from_numpy(next_obs.copy())),
                ("actions", action),
                ("logp", logp),
                ("states", torch.from_numpy(state)),
                ("next_states", torch.from_numpy(next_state)),
                ("rewards", torch.from_numpy(agent_reward)),
                ("episode_end", torch.from_numpy(done.copy())),
            ):
                buf[k].append(v)
            episode_return += reward
            for name, value in info["reward_terms"].items():
                term_sums[name] = term_sums.get(name, 0.0) + value
            obs, state = next_obs.copy(), next_state
            if done.any():
                returns.extend(episode_return[done].tolist())
                episode_return[done] = 0.0
                for name, value in info["metrics"].items():
                    metrics.setdefault(name, []).extend(value[done].tolist())
                obs = env.reset(mask=done).copy()
                state = env.global_state()
        n_steps = steps * env.n_envs
        stats = {
            "episode_return": float(np.mean(returns)),
            "reward_per_step": float(np.mean(returns)) / self.task_cfg.steps,
            **{f"term/{name}": float(np.sum(total) / n_steps) for name, total in term_sums.items()},
            **{f"metric/{name}": float(np.mean(v)) for name, v in metrics.items() if name != "E"},
            "episodes": len(returns),
        }
        return Rollout(**{k: torch.stack(v) for k, v in buf.items()}, stats=stats)

    def agent_rewards(self, team_reward: np.ndarray, team_collision: np.ndarray, own: np.ndarray, w) -> np.ndarray:
        """Per-agent learning rewards [B, N] from the team reward [B] and each agent's collision
        penalty CR_i >= 0 [B, N] (see the module docstring)."""
        n = self.env.n_agents
        if self.ppo.collision_credit == "team":
            return np.repeat(team_reward[:, None], n, axis=1).astype(np.float32)
        shared = team_reward - w.collision_weight * team_collision  # 15 R_f + 4 R_n
        return (shared[:, None] - w.collision_weight * own).astype(np.float32)

    def critic_input(self, states: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """[..., S] global states and [..., N, D] observations -> [..., N, S + D]."""
        return torch.cat([states.unsqueeze(-2).expand(*obs.shape[:-1], states.shape[-1]), obs], dim=-1)

    # ------------------------------------------------------------------ update
    def update(self, ro: Rollout) -> dict[str, float]:
        """PPO epochs over one rollout; returns loss and health statistics."""
        ppo = self.ppo
        t, b, n = ro.logp.shape
        with torch.no_grad():
            critic_in = self.critic_input(ro.states, ro.obs)  # [T, B, N, S + D]
            values = self.critic(critic_in)
            next_values = self.critic(self.critic_input(ro.next_states, ro.next_obs))
            end = ro.episode_end.unsqueeze(-1).expand_as(ro.rewards)
            advantages, targets, ev = advantages_and_targets(ro.rewards, values, next_values, end, ppo, self.value_norm)

        # Flatten time and env: a sample is one env-step with all its N agents.
        obs = ro.obs.reshape(t * b, n, -1)
        actions = ro.actions.reshape(t * b, n, -1)
        old_logp = ro.logp.reshape(t * b, n)
        adv = advantages.reshape(t * b, n)
        critic_in = critic_in.reshape(t * b, n, -1)
        targets = targets.reshape(t * b, n)

        def policy_terms(mb):
            dist = self.actor.distribution(obs[mb])
            return dist.log_prob(actions[mb]).sum(-1), dist.entropy().sum(-1).mean()

        stats = ppo_epochs(
            t * b,
            ppo,
            self.generator,
            policy_terms,
            old_logp,
            adv,
            self.actor_opt,
            list(self.actor.parameters()),
            self.critic,
            critic_in,
            targets,
            self.critic_opt,
        )
        stats["explained_variance"] = ev
        stats["action_std"] = float(self.actor.log_std.detach().exp().mean())
        return stats

    # ------------------------------------------------------------------ one iteration
    def iterate(self) -> dict[str, float]:
        """collect + update, with timings and counters; returns the iteration's log row."""
        t0 = time.perf_counter()
        torch.set_num_threads(self.ppo.rollout_threads)
        rollout = self.collect()
        t1 = time.perf_counter()
        torch.set_num_threads(self.ppo.update_threads)
        stats = self.update(rollout)
        t2 = time.perf_counter()
        samples = rollout.logp.numel()
        self.iteration += 1
        self.agent_steps += samples
        self.elapsed += t2 - t0
        return {
            "iteration": self.iteration,
            "agent_steps": self.agent_steps,
            "wall_s": self.elapsed,
            **rollout.stats,
            **stats,
            "env_sps": samples / (t1 - t0),
            "update_sps": samples * self.ppo.epochs / (t2 - t1),
            "sps": samples / (t2 - t0),
        }

    # ------------------------------------------------------------------ checkpoint state
    def state_dict(self) -> dict:
        return {
            **learner_state(self),
            "counters": {"iteration": self.iteration, "agent_steps": self.agent_steps, "elapsed": self.elapsed},
        }

    def load_state_dict(self, state: dict) -> None:
        load_learner_state(self, state)
        counters = state["counters"]
        self.iteration = int(counters["iteration"])
        self.agent_steps = int(counters["agent_steps"])
        self.elapsed = float(counters["elapsed"])
