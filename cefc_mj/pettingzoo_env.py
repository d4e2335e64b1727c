"""PettingZoo `ParallelEnv` over one env of `BatchedCEFCEnv` (either backend).

Spaces: each observation is a float32 `Box` with finite per-part bounds derived from the layout
(`observation_bounds`), the centralized state a `Box` too (`state_bounds`). Rendering:
`render_mode="rgb_array"` returns frames (`cefc_mj.viz.frames`: MuJoCo's offscreen renderer for
quadrotors, a numpy top-down drawing for particles); `"human"` streams every step to a live Rerun
viewer through the project's episode logging (`cefc_mj.viz.rerun_log`), as
`cefc_mj.viz.recorder.RerunRecorder` does for `.rrd` files.
User guide: docs/pettingzoo.md.

>>> import cefc_mj
>>> env = cefc_mj.make_env(backend="particle", n_agents=3, mode="formation", seed=0)
>>> observations, infos = env.reset(seed=0)
>>> all(env.observation_space(a).contains(o) for a, o in observations.items())
True
>>> env.state().shape == env.state_space.shape
True
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CefcError, ConfigError, SimulationDiverged
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.guard import guard_with
from cefc_mj.task.observation import layout_for
from cefc_mj.viz.frames import frame_renderer
from cefc_mj.viz.recorder import RerunRecorder, has_display, spawn_viewer

RENDER_MODES = ("rgb_array", "human")
RENDER_SIZE = (480, 480)
"""Default (height, width) of rgb_array frames in pixels."""
_DEVIATION_SIGMAS = 8.0  # |Normal(d, d/4)| exceeds d + 8 d/4 with probability ~1e-15
_NOISE_SIGMAS = 8.0  # the same margin for the particle world's Gaussian velocity kicks


class ResetNeeded(CefcError, gymnasium.error.ResetNeeded, RuntimeError):
    """`step()` was called before `reset()`, or after the episode ended: call `reset()` first."""


# ---------------------------------------------------------------------------------------- bounds
def physical_limits(config: TaskConfig, world) -> dict[str, float]:
    """Hard limits of the true state, per axis, that the space bounds are built from.

    speed / adversary_speed (m/s): the particle world clips speeds exactly (plus 8 sigma of its
    optional velocity kicks, which its response lag accumulates); a MuJoCo drone's speed limit is
    the flight controller's, which overshoots (bounces off obstacles, wind), so the bound is
    3 x the limit + half the strongest wind draw (measured: 1.8 m/s calm, 2.7 m/s at 8 m/s wind and
    5.4 m/s at 20 m/s for a 1 m/s limit, with random actions).
    reach / adversary_reach (m): |x|, |y| of a true position: the start square plus the distance
    the speed bound allows over the episode (twice that in the particle world, where an obstacle
    contact moves a UAV onto the obstacle's surface, up to one more step's distance).
    deviation (m): the largest sensing deviation (d + 8 d/4).
    These are guarantees, not typical ranges: far looser than what an episode visits.
    """
    dt = max(config.dt, float(getattr(world, "dt", config.dt)))
    if isinstance(world, ParticleWorld):
        speed, adversary_speed = config.speed_max, config.adversary_speed_max
        if config.velocity_noise > 0:
            keep = config.response_time / (config.dt + config.response_time)  # share of v kept per step
            speed += _NOISE_SIGMAS * config.velocity_noise / math.sqrt(1.0 - keep**2)
        travel = 2.0 * dt * config.steps
    else:
        wind = _strongest_wind(getattr(world, "wind_config", None))
        speed = 3.0 * config.speed_max + 0.5 * wind
        adversary_speed = 3.0 * config.adversary_speed_max + 0.5 * wind
        travel = dt * config.steps
    adversary_start = abs(config.adversary_start[0]) + config.start_half_size, abs(config.adversary_start[1])
    return {
        "speed": speed,
        "adversary_speed": adversary_speed,
        "reach": config.start_half_size + travel * speed,
        "adversary_reach": max(adversary_start) + travel * adversary_speed,
        "deviation": (1.0 + _DEVIATION_SIGMAS / 4.0) * config.deviation,
    }


def _strongest_wind(wind_config) -> float:
    """Largest wind speed (m/s) the wind field draws: mean + 5 sigma, clipped as the field clips it,
    plus a gust's mean + 5 sigma when one is configured."""
    if wind_config is None or wind_config.calm:
        return 0.0
    top = wind_config.mean_speed if wind_config.mean_speed_max is None else wind_config.mean_speed_max
    wind = min(wind_config.max_speed, top + 5.0 * wind_config.sigma_at(top))
    if wind_config.gust_duration > 0:
        wind += wind_config.gust_mean_speed + 5.0 * wind_config.gust_sigma
    return wind


def observation_bounds(config: TaskConfig, world) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 [D] of one agent's observation, part by part of `layout_for(config)`:

    - anchor / targets: target or anchor minus the perceived position, so at most the anchor box
      (target corner) + the reach + the deviation; a target's urgency lies in [0, 1].
    - own_velocity: the speed bound.
    - neighbours (dx, dy, dvx, dvy per slot): a neighbour only counts within observation_distance,
      relative velocities within twice the speed bound; empty slots are 0.
    - neighbour_mask: [0, 1]. lidar: [0, lidar_range].
    - adversary: its relative position (both reaches + deviation) and relative velocity.
    """
    limits = physical_limits(config, world)
    speed, reach, dev = limits["speed"], limits["reach"], limits["deviation"]
    low, high = [], []
    for name, size in layout_for(config).parts:
        if name == "anchor":
            part_low, part_high = _symmetric(size, config.anchor_half_size + reach + dev)
        elif name == "own_velocity":
            part_low, part_high = _symmetric(size, speed)
        elif name == "neighbours":
            part_low, part_high = _symmetric_tile(size, [config.observation_distance] * 2 + [2.0 * speed] * 2)
        elif name == "neighbour_mask":
            part_low, part_high = np.zeros(size), np.ones(size)
        elif name == "lidar":
            part_low, part_high = np.zeros(size), np.full(size, config.lidar_range)
        elif name == "targets":
            relative = config.target_corner + reach + dev
            part_high = np.tile([relative, relative, 1.0], size // 3)
            part_low = np.tile([-relative, -relative, 0.0], size // 3)
        elif name == "adversary":
            relative = limits["adversary_reach"] + reach + dev
            part_low, part_high = _symmetric_tile(size, [relative] * 2 + [limits["adversary_speed"] + speed] * 2)
        else:
            raise ConfigError(f"observation part {name!r} has no known bounds (pettingzoo_env.observation_bounds)")
        low.append(part_low)
        high.append(part_high)
    return np.concatenate(low).astype(np.float32), np.concatenate(high).astype(np.float32)


def state_bounds(config: TaskConfig, world) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 [S] of `BatchedCEFCEnv.global_state` (the centralized critic's input):
    per agent its true position (relative to the anchor in formation mode, absolute in cefc mode),
    velocity and LiDAR; in cefc mode then the adversary's position and velocity, the targets and
    their urgencies."""
    limits = physical_limits(config, world)
    position = limits["reach"] + (config.anchor_half_size if config.mode == "formation" else 0.0)
    m = config.n_lidar_rays
    agent_high = np.concatenate([[position] * 2, [limits["speed"]] * 2, np.full(m, config.lidar_range)])
    agent_low = np.concatenate([[-position] * 2, [-limits["speed"]] * 2, np.zeros(m)])
    low, high = [np.tile(agent_low, config.n_agents)], [np.tile(agent_high, config.n_agents)]
    if config.mode == "cefc":
        j = config.n_targets
        rest = np.concatenate(
            [[limits["adversary_reach"]] * 2, [limits["adversary_speed"]] * 2, np.full(2 * j, config.target_corner)]
        )
        low += [-rest, np.zeros(j)]
        high += [rest, np.ones(j)]
    return np.concatenate(low).astype(np.float32), np.concatenate(high).astype(np.float32)


def _symmetric(size: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
    return np.full(size, -bound), np.full(size, bound)


def _symmetric_tile(size: int, pattern: list[float]) -> tuple[np.ndarray, np.ndarray]:
    high = np.tile(pattern, size // len(pattern))
    return -high, high


# ---------------------------------------------------------------------------------------- env
def check_render_mode(render_mode) -> None:
    """ConfigError unless render_mode is None or one of RENDER_MODES."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ConfigError(f"render_mode={render_mode!r}: must be None or one of {', '.join(RENDER_MODES)}")


def prefer_headless_gl() -> None:
    """Pick EGL for MuJoCo's offscreen renderer when there is no display (MUJOCO_GL, if unset).

    MuJoCo reads MUJOCO_GL once, when it is first imported; later this has no effect.
    """
    if sys.platform.startswith("linux") and not has_display() and "mujoco" not in sys.modules:
        os.environ.setdefault("MUJOCO_GL", "egl")


class CEFCParallelEnv(ParallelEnv):
    """The CEFC game as a PettingZoo parallel env; agents are `uav_0 .. uav_{N-1}`.

    Action of each agent: its horizontal acceleration setpoint [a_x, a_y] (m/s^2), a `Box(2)` in
    [-accel_max, accel_max]; `step` needs one for every live agent. Observation: the flat vector of
    `env.layout` (docs/architecture.md) in a float32 `Box` with the finite bounds of
    `observation_bounds`. `state()`: the centralized state of `BatchedCEFCEnv.global_state` in
    `state_space` (`state_bounds`). Reward: the team reward, the same for every agent. Each agent's
    info holds its true `position` and `velocity` (numpy, m and m/s) and, at episode end, the
    episode `metrics` (F, N, C, E). Episodes end by truncation after `config.steps` decision steps.

    Args:
        batched: the BatchedCEFCEnv (n_envs=1) to expose.
        render_mode: None, "rgb_array" (`render()` returns a [H, W, 3] uint8 frame) or "human"
            (every reset and step streams to a Rerun viewer, spawned if none is listening).
        render_size: (height, width) of rgb_array frames in pixels.

    Raises:
        ConfigError: bad render_mode or size, no OpenGL for MuJoCo frames, no display for a viewer.
    """

    metadata = {"name": "cefc_v0", "render_modes": list(RENDER_MODES), "render_fps": 10}

    def __init__(
        self, batched: BatchedCEFCEnv, render_mode: str | None = None, render_size: tuple[int, int] = RENDER_SIZE
    ):
        if batched.n_envs != 1:
            raise ConfigError("CEFCParallelEnv wraps a BatchedCEFCEnv with n_envs=1")
        check_render_mode(render_mode)
        self.batched = batched
        self.config = batched.config
        self.layout = batched.layout
        self.render_mode = render_mode
        self.possible_agents = [f"uav_{i}" for i in range(batched.n_agents)]
        self.agents: list[str] = []
        self._started = False
        self.episode_seed: int | None = None
        """The seed given to the last reset() (None if none was)."""
        low, high = observation_bounds(self.config, batched.world)
        self._observation_spaces = {a: spaces.Box(low, high, dtype=np.float32) for a in self.possible_agents}
        a = self.config.accel_max
        self._action_spaces = {agent: spaces.Box(-a, a, shape=(2,), dtype=np.float32) for agent in self.possible_agents}
        low, high = state_bounds(self.config, batched.world)
        self.state_space = spaces.Box(low, high, dtype=np.float32)
        self._frames = None
        self._recorder = None
        if render_mode == "rgb_array":
            self._frames = frame_renderer(batched, render_size)
        elif render_mode == "human":
            spawn_viewer()
            self._recorder = RerunRecorder(self, spawn=True)

    def observation_space(self, agent: str) -> spaces.Box:
        return self._observation_spaces[self._known(agent)]

    def action_space(self, agent: str) -> spaces.Box:
        return self._action_spaces[self._known(agent)]

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.batched.reset(seed=seed)
        self.episode_seed = seed
        self.agents = list(self.possible_agents)
        self._started = True
        if self._recorder is not None:
            self._recorder.capture()
        return self._split(obs), self._infos(None)

    def step(self, actions: dict[str, np.ndarray]):
        if not self.agents:
            if not self._started:
                raise ResetNeeded("step() called before reset(): call reset() first")
            raise ResetNeeded("the episode ended (truncated, or the simulation diverged): call reset() first")
        stacked = self._stack_actions(actions)
        cfg = self.batched.config
        if cfg.separation_guard:  # each agent's guard on its own observation, in float32 as cefc-eval's agents
            stacked = guard_with(cfg, self.batched.observation, stacked.astype(np.float32))
        try:
            obs, reward, done, info = self.batched.step(stacked)
        except SimulationDiverged:
            self.agents = []  # the physics cannot go on: the next step() asks for a reset
            raise
        observations = self._split(obs)
        rewards = {a: float(reward[0]) for a in self.agents}
        terminations = {a: False for a in self.agents}
        truncations = {a: bool(done[0]) for a in self.agents}
        infos = self._infos(info.get("metrics") if done[0] else None)
        if self._recorder is not None:
            self._recorder.capture()
        if done[0]:
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """rgb_array: the current scene as a [H, W, 3] uint8 frame. human: None (each step has been
        streamed already)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode to make_env")
            return None
        if self._frames is not None:
            return self._frames.frame(self.batched)
        return None

    def close(self) -> None:
        if self._frames is not None:
            self._frames.close()
            self._frames = None
        if self._recorder is not None:
            self._recorder.close()
            self._recorder = None

    def state(self) -> np.ndarray:
        return self.batched.global_state()[0]

    # ------------------------------------------------------------------ helpers
    def _known(self, agent: str) -> str:
        if agent not in self._action_spaces:
            raise ConfigError(f"unknown agent {agent!r}: agents are {self._agent_range()}")
        return agent

    def _agent_range(self) -> str:
        return f"{self.possible_agents[0]} .. {self.possible_agents[-1]}"

    def _stack_actions(self, actions) -> np.ndarray:
        """{agent: [a_x, a_y]} -> [1, N, 2], every live agent present, nothing else."""
        if not isinstance(actions, Mapping):
            raise ConfigError(f"actions: expected a dict {{agent: [a_x, a_y]}}, got {type(actions).__name__}")
        unknown = [a for a in actions if a not in self._action_spaces]
        if unknown:
            raise ConfigError(f"actions for unknown agent(s) {unknown}: agents are {self._agent_range()}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ConfigError(f"actions missing for agent(s) {missing}: every live agent needs an action")
        stacked = np.zeros((1, self.batched.n_agents, 2))
        for i, agent in enumerate(self.possible_agents):
            try:
                action = np.asarray(actions[agent], dtype=np.float64)
            except (TypeError, ValueError):
                raise ConfigError(f"actions[{agent!r}]: not numbers ({actions[agent]!r:.60})") from None
            if action.shape != (2,):
                raise ConfigError(f"actions[{agent!r}]: expected shape (2,) = [a_x, a_y] in m/s^2, got {action.shape}")
            if not np.isfinite(action).all():
                raise ConfigError(f"actions[{agent!r}]: contains NaN or inf")
            stacked[0, i] = action
        return stacked

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
