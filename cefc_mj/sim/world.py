"""The interface between the CEFC task core and a physics backend (docs/architecture.md)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class World(Protocol):
    """A batched physics world: B envs x N UAVs, one adversary per env, K cylinder obstacles.

    >>> from cefc_mj.task.config import TaskConfig
    >>> from cefc_mj.sim.particle import ParticleWorld
    >>> isinstance(ParticleWorld(TaskConfig(n_agents=3), n_envs=2), World)
    True
    """

    n_envs: int
    n_agents: int
    dt: float

    def reset(
        self, env_mask: np.ndarray, agent_pos: np.ndarray, adversary_pos: np.ndarray, obstacles: np.ndarray
    ) -> None:
        """Place the masked envs' agents [B,N,2], adversary [B,2] and obstacles [B,K,2]; zero velocities."""
        ...

    def step(self, agent_accel: np.ndarray, adversary_accel: np.ndarray) -> None:
        """Advance one decision step with acceleration setpoints [B,N,2] and [B,2] (m/s^2)."""
        ...

    @property
    def agent_pos(self) -> np.ndarray:
        """[B,N,2] true positions (m)."""
        ...

    @property
    def agent_vel(self) -> np.ndarray:
        """[B,N,2] true velocities (m/s)."""
        ...

    @property
    def adversary_pos(self) -> np.ndarray:
        """[B,2]."""
        ...

    @property
    def adversary_vel(self) -> np.ndarray:
        """[B,2]."""
        ...

    def lidar(self, origins: np.ndarray) -> np.ndarray:
        """Ranges [B,N,M] of agent i's beams cast from origins[b, i] (its true or perceived position)."""
        ...

    def collisions(self) -> np.ndarray:
        """[B,N] bool: agent in collision (obstacle or other UAV) during the last step."""
        ...
