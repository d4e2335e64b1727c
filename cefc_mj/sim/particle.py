"""The paper's MPE as a batched point-mass world: B envs x N agents in one process.

Per decision step (semi-implicit Euler, dt = 0.1 s): v <- v + a dt, then the speed is clipped to
speed_max (norm), then p <- p + v dt. With `TaskConfig.response_time` tau > 0 the action integrates
into a commanded velocity instead, which v follows as a first-order lag, v <- v + dt/(dt + tau)
(v_cmd - v): the quadrotor's velocity loop takes about 0.1 s to respond (docs/research/decisions.md). With
`velocity_noise` sigma > 0 every UAV's velocity then gets a Normal(0, sigma) kick per axis (drawn
from `rng`) before the position update, the residual tracking error of a real vehicle; the lag
carries it over into the next steps. A UAV whose disc overlaps an obstacle is in collision this
step; it is pushed back onto the obstacle's surface and loses its inward velocity (an inelastic
contact, so it cannot fly through obstacles). UAV-UAV overlaps are counted as collisions but not
resolved. There is no damping: the quadrotor has none either (docs/design.md §3).
"""

from __future__ import annotations

import numpy as np

from cefc_mj.task.adversary import clip_speed
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.kernels import particle_step_kernel
from cefc_mj.task.lidar import lidar_ranges


class ParticleWorld:
    """Batched point-mass physics implementing the `World` protocol."""

    def __init__(self, config: TaskConfig, n_envs: int, seed: int | None = 0):
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.n_envs = n_envs
        self.n_agents = config.n_agents
        self.dt = config.dt
        b, n = n_envs, config.n_agents
        self._pos = np.zeros((b, n, 2))
        self._vel = np.zeros((b, n, 2))
        self._vel_cmd = np.zeros((b, n, 2))
        self._response = config.dt / (config.dt + config.response_time)
        self._no_kick = np.zeros((b, n, 2))
        self._adv_pos = np.zeros((b, 2))
        self._adv_vel = np.zeros((b, 2))
        self.obstacles = np.zeros((b, config.n_obstacles, 2))
        self._collided = np.zeros((b, n), dtype=bool)

    agent_pos = property(lambda self: self._pos)
    agent_vel = property(lambda self: self._vel)
    adversary_pos = property(lambda self: self._adv_pos)
    adversary_vel = property(lambda self: self._adv_vel)

    def reset(self, env_mask, agent_pos, adversary_pos, obstacles) -> None:
        m = np.asarray(env_mask, dtype=bool)
        self._pos[m] = agent_pos[m]
        self._vel[m] = 0.0
        self._vel_cmd[m] = 0.0
        self._adv_pos[m] = adversary_pos[m]
        self._adv_vel[m] = 0.0
        self.obstacles[m] = obstacles[m]
        self._collided[m] = False

    def step(self, agent_accel: np.ndarray, adversary_accel: np.ndarray) -> None:
        cfg, dt = self.config, self.dt
        if cfg.velocity_noise > 0:
            kick = self.rng.normal(0.0, cfg.velocity_noise, self._vel.shape)
        else:
            kick = self._no_kick
        particle_step_kernel(
            self._pos,
            self._vel,
            self._vel_cmd,
            np.ascontiguousarray(agent_accel, dtype=np.float64),
            kick,
            self.obstacles,
            dt,
            cfg.speed_max,
            self._response,
            cfg.obstacle_radius + cfg.uav_radius,
            2 * cfg.uav_radius,
            self._collided,
        )
        self._adv_vel = clip_speed(self._adv_vel + adversary_accel * dt, cfg.adversary_speed_max)
        self._adv_pos = self._adv_pos + self._adv_vel * dt

    def lidar(self, origins: np.ndarray) -> np.ndarray:
        cfg = self.config
        return lidar_ranges(
            origins,
            self.obstacles,
            cfg.obstacle_radius,
            self._pos,
            cfg.uav_radius,
            cfg.n_lidar_rays,
            cfg.lidar_range,
            cfg.lidar_sees_agents,
        )

    def collisions(self) -> np.ndarray:
        return self._collided
