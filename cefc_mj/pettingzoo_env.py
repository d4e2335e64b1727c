"""PettingZoo `ParallelEnv` over one env of `BatchedCEFCEnv` (either backend)."""

from __future__ import annotations

import functools

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cefc_mj.env import BatchedCEFCEnv


class CEFCParallelEnv(ParallelEnv):
    """The CEFC game as a PettingZoo parallel env; agents are `uav_0 .. uav_{N-1}`.

    Action of each agent: its horizontal acceleration setpoint [a_x, a_y] (m/s^2), a `Box(2)` in
    [-accel_max, accel_max]. Observation: the flat vector of `env.layout` (docs/architecture.md).
    Reward: the team reward, the same for every agent. Each agent's info holds its true `position`
    and `velocity` (numpy, m and m/s) and, at episode end, the episode `metrics` (F, N, C, E).
    Episodes end by truncation after `config.steps` decision steps.
    """

    metadata = {"name": "cefc_v0", "render_modes": []}

    def __init__(self, batched: BatchedCEFCEnv):
        if batched.n_envs != 1:
            raise ValueError("CEFCParallelEnv wraps a BatchedCEFCEnv with n_envs=1")
        self.batched = batched
        self.config = batched.config
        self.possible_agents = [f"uav_{i}" for i in range(batched.n_agents)]
        self.agents: list[str] = []
        self.layout = batched.layout

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, shape=(self.layout.size,), dtype=np.float32)

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent: str) -> spaces.Box:
        a = self.config.accel_max
        return spaces.Box(-a, a, shape=(2,), dtype=np.float32)

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.batched.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return self._split(obs), self._infos(None)

    def step(self, actions: dict[str, np.ndarray]):
        stacked = np.zeros((1, self.batched.n_agents, 2))
        for i, agent in enumerate(self.possible_agents):
            if agent in actions:
                stacked[0, i] = np.asarray(actions[agent], dtype=np.float64).reshape(2)
        obs, reward, done, info = self.batched.step(stacked)
        observations = self._split(obs)
        rewards = {a: float(reward[0]) for a in self.agents}
        terminations = {a: False for a in self.agents}
        truncations = {a: bool(done[0]) for a in self.agents}
        infos = self._infos(info.get("metrics") if done[0] else None)
        if done[0]:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def _split(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[0, i].copy() for i, a in enumerate(self.possible_agents)}

    def _infos(self, metrics: dict | None) -> dict[str, dict]:
        world = self.batched.world
        infos = {}
        for i, a in enumerate(self.possible_agents):
            infos[a] = {"position": world.agent_pos[0, i].copy(), "velocity": world.agent_vel[0, i].copy()}
            if metrics is not None:
                infos[a]["metrics"] = {k: float(v[0]) for k, v in metrics.items()}
        return infos

    def state(self) -> np.ndarray:
        return self.batched.global_state()[0]
