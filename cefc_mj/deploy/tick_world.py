"""A world stepped at a control tick finer than the decision step, and taking UAVs out of a world.

`TickedWorld` implements the World protocol (docs/architecture.md) for the task core, whose decision
step stays 0.1 s, on top of an inner world built with a shorter step, the control tick (0.01 s by
default on MuJoCo: one period of the PX4-like position loop, the finest rate at which the offboard
interface consumes setpoints). Each decision step runs `n_ticks` inner steps; before each, a
`controller(j)` callback (the SITL-M simulator) says which setpoints are in force at tick j, so a
command that arrives 3 ms into a decision step takes effect at the next tick instead of waiting for
the next decision step. Without a controller the action given to `step` is held for the whole
decision step (the lock-step semantics). Collisions are OR-ed over the ticks, as the world reports
a contact at any physics step of a decision step.

With a constant action the MuJoCo offboard interface integrates the same velocity setpoint in ten
0.01 s pieces as in one 0.1 s piece (v_sp <- clip_norm(v_sp + a dt); the pieces differ only where
the speed limit clips), so a ticked world flies the lock-step trajectories up to float rounding.
The particle world is the paper's MPE, integrated only at the decision step: there the control tick
is the decision step.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig

PARK_ORIGIN = (1000.0, 1000.0)
"""Where removed UAVs are parked (m): far outside the arena, beyond every sensor's range."""
PARK_SPACING = 10.0


def make_ticked_world(
    backend: str,
    config: TaskConfig,
    control_tick_s: float,
    wind: float = 0.0,
    seed: int | None = None,
    airframe: str | None = None,
    wind_direction: float | None = None,
    rotor_actuation: str = "auto",
) -> "TickedWorld":
    """The world of `backend` for one env, stepped at `control_tick_s` inside each decision step."""
    from cefc_mj.sim.backends import make_world

    n_ticks = round(config.dt / control_tick_s)
    if n_ticks < 1 or abs(n_ticks * control_tick_s - config.dt) > 1e-9:
        raise ConfigError(f"control_tick_s={control_tick_s}: must divide the decision step {config.dt} s")
    if backend == "particle":
        if n_ticks != 1:
            raise ConfigError(
                f"control_tick_s={control_tick_s}: the particle world steps only at the decision step ({config.dt} s)"
            )
        return TickedWorld(
            make_world("particle", config, n_envs=1, seed=seed, wind_direction=wind_direction), 1, config.dt
        )
    if backend != "mujoco":
        return TickedWorld(make_world(backend, config, n_envs=1, seed=seed), 1, config.dt)  # make_world names the error
    from cefc_mj.sim.mujoco_world import MujocoWorldConfig, make_mujoco_world

    inner = make_mujoco_world(
        config,
        n_envs=1,
        wind=wind,
        seed=seed,
        airframe=airframe,
        config=MujocoWorldConfig(decision_dt=config.dt / n_ticks, rotor_actuation=rotor_actuation),
        wind_direction=wind_direction,
    )
    return TickedWorld(inner, n_ticks, config.dt)


class TickedWorld:
    """World protocol over `inner` (a world whose step is dt / n_ticks); see the module docstring."""

    def __init__(self, inner, n_ticks: int, dt: float):
        self.inner = inner
        self.n_ticks = int(n_ticks)
        self.dt = float(dt)
        self.tick_s = self.dt / self.n_ticks
        self.n_envs, self.n_agents = inner.n_envs, inner.n_agents
        self.controller: Callable[[int], np.ndarray] | None = None
        """Called with the tick index j (0..n_ticks-1) before each inner step; returns the agents'
        setpoints [B, N, 2] in force for that tick. None: hold the action given to step()."""
        self._collided = np.zeros((self.n_envs, self.n_agents), dtype=bool)

    def reset(self, env_mask, agent_pos, adversary_pos, obstacles) -> None:
        self.inner.reset(env_mask, agent_pos, adversary_pos, obstacles)
        self._collided[np.asarray(env_mask, dtype=bool)] = False

    def step(self, agent_accel: np.ndarray, adversary_accel: np.ndarray) -> None:
        self._collided[:] = False
        for j in range(self.n_ticks):
            accel = agent_accel if self.controller is None else self.controller(j)
            self.inner.step(accel, adversary_accel)
            self._collided |= self.inner.collisions()

    def collisions(self) -> np.ndarray:
        return self._collided.copy()

    def lidar(self, origins: np.ndarray) -> np.ndarray:
        return self.inner.lidar(origins)

    agent_pos = property(lambda self: self.inner.agent_pos)
    agent_vel = property(lambda self: self.inner.agent_vel)
    adversary_pos = property(lambda self: self.inner.adversary_pos)
    adversary_vel = property(lambda self: self.inner.adversary_vel)

    def __getattr__(self, name: str):  # read-only extras (drone_positions, wind_vector, sim_time, ...)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def brake_accel(self, accel_max: float) -> np.ndarray:
        """[B, N, 2] setpoints that bring each UAV's velocity setpoint to zero within the per-axis
        acceleration limit (PX4's hold: zero velocity setpoint, same limits). MuJoCo "velocity"
        offboard brakes the interface's own velocity setpoint; otherwise the measured velocity."""
        inner = self.inner
        if getattr(getattr(inner, "config", None), "offboard", None) == "velocity":
            velocity = inner.velocity_setpoints[:, : self.n_agents]
        else:
            velocity = inner.agent_vel
        return np.clip(-velocity / self.tick_s, -accel_max, accel_max)

    def park(self, env: int, agents) -> None:
        """Take UAVs out of the arena (see `park_agents`)."""
        park_agents(self.inner, env, agents)


def park_agents(world, env: int, agents) -> None:
    """Move UAVs `agents` of env `env` to PARK_ORIGIN (spaced PARK_SPACING apart), at rest: a UAV that
    has left the swarm (landed and carried off) is then beyond every neighbour's radio range and
    LiDAR, and collides with nothing. Works on MujocoWorld, ParticleWorld and TickedWorld."""
    if isinstance(world, TickedWorld):
        world.park(env, agents)
        return
    agents = [int(i) for i in agents]
    spots = {i: (PARK_ORIGIN[0] + PARK_SPACING * i, PARK_ORIGIN[1]) for i in agents}
    if hasattr(world, "datas"):  # MujocoWorld: drones are bodies 1..D with one free joint each
        import mujoco

        model, data = world.models[env], world.datas[env]
        for i in agents:
            data.qpos[7 * i : 7 * i + 2] = spots[i]
            data.qvel[6 * i : 6 * i + 6] = 0.0
        mujoco.mj_forward(model, data)
        return
    pos, vel = world.agent_pos, world.agent_vel  # ParticleWorld: its own arrays
    for i in agents:
        pos[env, i] = spots[i]
        vel[env, i] = 0.0
    if hasattr(world, "_vel_cmd"):  # the commanded velocity of the response-time lag
        world._vel_cmd[env, agents] = 0.0
