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
from collections.abc import Callable

import numpy as np
import torch

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.nn.atm import ATMActor, Critic
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import PPOConfig
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, learner_state, load_learner_state, ppo_epochs
from cefc_mj.train.rollout import (  # noqa: F401 - iteration_seed and Rollout are part of this module's API
    Rollout,
    agent_rewards,
    collect_shard,
    iteration_seed,
    merge_shards,
    particle_env,
)


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
        make_env: Callable[[TaskConfig, int, int], BatchedCEFCEnv] = particle_env,
        rollout_workers: int = 1,
    ):
        """make_env(task, n_envs, seed): the batched env the rollouts step (a picklable module-level
        function or partial: with rollout_workers > 1 each worker process builds its share with it).
        rollout_workers: processes that collect the episodes, n_envs / rollout_workers envs each
        (1: collected here). Call close() when done with workers."""
        self.task_cfg = task_cfg
        self.ppo = ppo
        self.seed = seed
        # With rollout workers the episodes are stepped there: here only a one-env probe for the checks.
        self.env = make_env(task_cfg, ppo.n_envs if rollout_workers == 1 else 1, seed)
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
        self.critic_warmup = 0
        """The first this many iterations train only the critic (a fresh critic under a trained actor)."""
        self.workers = None
        if rollout_workers > 1:
            from cefc_mj.train.rollout_workers import RolloutWorkers

            self.workers = RolloutWorkers(
                rollout_workers, make_env, task_cfg, ppo.n_envs // rollout_workers, actor.cfg, ppo.collision_credit
            )
        self.iteration = 0
        self.agent_steps = 0
        self.elapsed = 0.0

    # ------------------------------------------------------------------ rollout
    def collect(self) -> Rollout:
        """Run `episodes_per_iteration` whole episodes in every env with the current policy: here, or
        on the rollout workers (each stepping its share of the envs) when the trainer has them."""
        steps = self.ppo.episodes_per_iteration * self.task_cfg.steps
        if self.workers is None:
            env_seed = iteration_seed(self.seed, self.iteration)
            shards = [collect_shard(self.env, self.actor, self.generator, steps, self.ppo.collision_credit, env_seed)]
        else:
            shards = self.workers.collect(self.actor.state_dict(), self.seed, self.iteration, steps)
        return merge_shards(shards, self.task_cfg.steps)

    def agent_rewards(self, team_reward: np.ndarray, team_collision: np.ndarray, own: np.ndarray, w) -> np.ndarray:
        """Per-agent learning rewards [B, N] (see `agent_rewards`)."""
        return agent_rewards(self.ppo.collision_credit, team_reward, team_collision, own, w)

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
            train_policy=self.iteration >= self.critic_warmup,
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

    def close(self) -> None:
        """Stop the rollout workers (if any)."""
        if self.workers is not None:
            self.workers.close()
            self.workers = None

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
