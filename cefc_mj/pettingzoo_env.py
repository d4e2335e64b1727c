"""PettingZoo `ParallelEnv` over one env of `BatchedCEFCEnv` (either backend).

Spaces: each observation is a float32 `Box` with finite per-part bounds derived from the layout
(`observation_bounds`), the centralized state a `Box` too (`state_bounds`). Rendering:
`render_mode="rgb_array"` returns frames (MuJoCo's offscreen renderer for quadrotors, a numpy
top-down drawing for particles); `"human"` streams every step to a live Rerun viewer through the
project's episode logging (`cefc_mj.viz.rerun_log`), as `RerunRecorder` does for `.rrd` files.
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

import atexit
import math
import os
import socket
import sys
import weakref
from collections.abc import Mapping
from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CefcError, ConfigError, SimulationDiverged
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.observation import layout_for

RENDER_MODES = ("rgb_array", "human")
RENDER_SIZE = (480, 480)
"""Default (height, width) of rgb_array frames in pixels."""
RERUN_VIEWER_PORT = 9876  # where rr.spawn starts (or finds) the viewer, and where rr.GrpcSink() sends
FLIGHT_ALTITUDE = 2.0  # the particle world is 2D; Rerun draws it at the quadrotors' altitude (m)
OBSTACLE_HEIGHT = 4.0  # likewise, the height of the drawn obstacle cylinders (m)
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
    if wind_config is None or (wind_config.mean_speed == 0 and wind_config.gust_duration == 0):
        return 0.0
    wind = min(wind_config.max_speed, wind_config.mean_speed + 5.0 * wind_config.sigma)
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
        rest = np.concatenate([[limits["adversary_reach"]] * 2, [limits["adversary_speed"]] * 2,
                               np.full(2 * j, config.target_corner)])
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
    if sys.platform.startswith("linux") and not _has_display() and "mujoco" not in sys.modules:
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

    def __init__(self, batched: BatchedCEFCEnv, render_mode: str | None = None,
                 render_size: tuple[int, int] = RENDER_SIZE):
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
            self._frames = _frame_renderer(batched, render_size)
        elif render_mode == "human":
            _spawn_viewer()
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


# ---------------------------------------------------------------------------------------- frames
def _frame_renderer(batched: BatchedCEFCEnv, size: tuple[int, int]):
    try:
        height, width = (int(v) for v in size)
    except (TypeError, ValueError):
        raise ConfigError(f"render_size={size!r}: must be (height, width) in pixels") from None
    if height < 16 or width < 16:
        raise ConfigError(f"render_size={size!r}: must be at least 16 x 16 pixels")
    if isinstance(batched.world, ParticleWorld):
        return TopDownFrames(batched.config, height, width)
    if hasattr(batched.world, "models") and hasattr(batched.world, "datas"):
        return MujocoFrames(batched.world, batched.config, height, width)
    raise ConfigError(f"render_mode='rgb_array': no renderer for a {type(batched.world).__name__}")


def _agent_colors(n: int) -> np.ndarray:
    """[n, 3] uint8: UAV i in tab10 colour i, as the top-down plots draw them."""
    import matplotlib

    return (np.asarray(matplotlib.colormaps["tab10"].colors)[np.arange(n) % 10] * 255).round().astype(np.uint8)


class TopDownFrames:
    """Particle-world frames: the arena from above, drawn with numpy (no GL, no figure).

    1 m grid, the arena's border, obstacles (grey), in formation mode the anchor and its 1 m zone
    (green), in cefc mode the target areas (gold) and the adversary (red), and each UAV as its
    footprint disc in its tab10 colour (cefc_mj.viz.plots' colours). The view spans the arena plus
    1 m; a UAV outside it is not drawn. x grows to the right, y upwards.
    """

    def __init__(self, config: TaskConfig, height: int, width: int):
        self.config = config
        half = config.arena_half_size + 1.0
        self.scale = min(height, width) / (2.0 * half)  # pixels per metre
        # world coordinates of the pixel centres
        self.x = (np.arange(width) + 0.5 - width / 2) / self.scale
        self.y = (height / 2 - np.arange(height) - 0.5) / self.scale
        self.colors = _agent_colors(config.n_agents)
        xx, yy = np.meshgrid(self.x, self.y)
        background = np.full((height, width, 3), 250, dtype=np.uint8)
        on_grid = (np.abs(xx - np.round(xx)) < 0.5 / self.scale) | (np.abs(yy - np.round(yy)) < 0.5 / self.scale)
        background[on_grid] = 225
        a = config.arena_half_size
        box_distance = np.maximum(np.abs(xx), np.abs(yy))
        background[(box_distance >= a) & (box_distance <= a + 1.0 / self.scale)] = 90  # the arena's border
        self.background = background

    def frame(self, batched: BatchedCEFCEnv) -> np.ndarray:
        cfg, world = self.config, batched.world
        img = self.background.copy()
        for centre in batched.obstacles[0]:
            self._disc(img, centre, cfg.obstacle_radius, (140, 140, 140))
        if cfg.mode == "formation":
            self._disc(img, batched.anchor[0], cfg.navigation_tolerance, (44, 160, 44), alpha=0.15)
            self._ring(img, batched.anchor[0], cfg.navigation_tolerance, (44, 160, 44))
            self._disc(img, batched.anchor[0], 0.15, (44, 160, 44))
        else:
            for target in batched.targets[0]:
                self._disc(img, target, cfg.target_radius, (230, 180, 0), alpha=0.2)
                self._ring(img, target, cfg.target_radius, (230, 180, 0))
            if cfg.adversary != "none":
                self._disc(img, world.adversary_pos[0], cfg.uav_radius * 1.2, (200, 0, 0))
        for i, pos in enumerate(world.agent_pos[0]):
            self._disc(img, pos, cfg.uav_radius + 1.0 / self.scale, (0, 0, 0))  # outline
            self._disc(img, pos, cfg.uav_radius, self.colors[i])
        return img

    def close(self) -> None:
        pass

    def _window(self, centre, radius):
        """Row and column index ranges of the pixels within `radius` of `centre` (maybe empty)."""
        cols = np.flatnonzero(np.abs(self.x - centre[0]) <= radius)
        rows = np.flatnonzero(np.abs(self.y - centre[1]) <= radius)
        return rows, cols

    def _distance(self, centre, radius):
        rows, cols = self._window(centre, radius)
        if not len(rows) or not len(cols):
            return None, None
        box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        d = np.hypot(self.x[cols][None, :] - centre[0], self.y[rows][:, None] - centre[1])
        return box, d

    def _disc(self, img, centre, radius, color, alpha: float = 1.0) -> None:
        box, d = self._distance(centre, radius)
        if box is None:
            return
        inside = d <= radius
        patch = img[box]
        patch[inside] = (1 - alpha) * patch[inside] + alpha * np.asarray(color, dtype=np.float64)

    def _ring(self, img, centre, radius, color) -> None:
        box, d = self._distance(centre, radius)
        if box is None:
            return
        img[box][np.abs(d - radius) <= 1.0 / self.scale] = color


class MujocoFrames:
    """MuJoCo-world frames from `mujoco.Renderer` on env 0's model and data.

    An oblique view of the whole arena; on top of the MuJoCo scene each UAV gets a marker ball in
    its tab10 colour, the anchor zone (formation mode) or the target areas (cefc mode) a flat disc.
    Needs OpenGL: headless, MUJOCO_GL=egl (`prefer_headless_gl`). The renderer is created here, so
    a missing GL fails at construction with ConfigError.
    """

    def __init__(self, world, config: TaskConfig, height: int, width: int):
        import mujoco

        self.mujoco = mujoco
        self.world = world
        self.config = config
        model = world.models[0]
        limit = (model.vis.global_.offheight, model.vis.global_.offwidth)
        if height > limit[0] or width > limit[1]:
            raise ConfigError(f"render_size=({height}, {width}): the MuJoCo scene renders at most "
                              f"{limit[0]} x {limit[1]}")
        try:
            self.renderer = mujoco.Renderer(model, height, width)
        except Exception as e:  # a missing GL surfaces as FatalError, GLError, ImportError, ... depending on MUJOCO_GL
            hint = str(e).strip().splitlines()[0][:160] if str(e).strip() else type(e).__name__
            raise ConfigError(
                f"render_mode='rgb_array' on MuJoCo needs OpenGL offscreen rendering ({hint}); headless, set "
                f"MUJOCO_GL=egl (or osmesa) before mujoco is imported, or use backend='particle'"
            ) from None
        atexit.register(_close_if_alive, weakref.ref(self))  # before EGL's own exit hook tears the display down
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            self.renderer.scene.flags[flag] = 0  # a third of the time per frame on a software GL
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = (0.0, -1.0, 0.0)
        self.camera.distance = 2.6 * config.arena_half_size + 2.0
        self.camera.elevation = -65.0
        self.camera.azimuth = 90.0  # looking along +y: x to the right, as in the top-down frames
        self.colors = np.concatenate([_agent_colors(config.n_agents) / 255.0, np.ones((config.n_agents, 1))], axis=1)

    def frame(self, batched: BatchedCEFCEnv) -> np.ndarray:
        mujoco, cfg = self.mujoco, self.config
        self.renderer.update_scene(self.world.datas[0], camera=self.camera)
        scene = self.renderer.scene
        drones = self.world.drone_positions[0, :cfg.n_agents]
        for i, pos in enumerate(drones):
            self._add(scene, mujoco.mjtGeom.mjGEOM_SPHERE, [0.25, 0, 0], pos + (0.0, 0.0, 0.15), self.colors[i])
        if cfg.mode == "formation":
            anchor = np.append(batched.anchor[0], 0.02)
            self._add(scene, mujoco.mjtGeom.mjGEOM_CYLINDER, [cfg.navigation_tolerance, 0.01, 0], anchor,
                      [0.17, 0.63, 0.17, 0.5])
        else:
            for target in batched.targets[0]:
                self._add(scene, mujoco.mjtGeom.mjGEOM_CYLINDER, [cfg.target_radius, 0.01, 0], np.append(target, 0.02),
                          [0.9, 0.7, 0.0, 0.35])
        return self.renderer.render()

    def _add(self, scene, geom_type, size, pos, rgba) -> None:
        if scene.ngeom >= scene.maxgeom:
            return
        self.mujoco.mjv_initGeom(scene.geoms[scene.ngeom], geom_type, np.asarray(size, dtype=np.float64),
                                 np.asarray(pos, dtype=np.float64), np.eye(3).ravel(),
                                 np.asarray(rgba, dtype=np.float32))
        scene.ngeom += 1

    def close(self) -> None:
        renderer, self.renderer = getattr(self, "renderer", None), None
        if renderer is not None:
            renderer.close()


def _close_if_alive(ref) -> None:
    frames = ref()
    if frames is not None:
        frames.close()


# ---------------------------------------------------------------------------------------- Rerun
def _has_display() -> bool:
    return any(os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"))


def _viewer_listening(port: int = RERUN_VIEWER_PORT) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _spawn_viewer() -> None:
    """Start a Rerun viewer (or find one listening); ConfigError when none can show up."""
    if _viewer_listening():
        return
    if sys.platform.startswith("linux") and not _has_display():
        raise ConfigError("render_mode='human': no display for a Rerun viewer (DISPLAY is unset) and none listening "
                          f"on port {RERUN_VIEWER_PORT}; use render_mode='rgb_array'")
    import rerun as rr

    try:
        rr.spawn(port=RERUN_VIEWER_PORT, connect=False)
    except Exception as e:  # the viewer executable is missing or cannot start
        raise ConfigError(f"render_mode='human': cannot start the Rerun viewer ({e}); "
                          "use render_mode='rgb_array'") from None


_SCALARS = ("hd_error", "anchor_distance", "wind_speed", "F_so_far", "N_so_far", "C_so_far")
"""The per-step series RerunRecorder logs under metrics/ (the names cefc-eval's recordings use)."""


class RerunRecorder:
    """Logs a `CEFCParallelEnv`'s episodes to Rerun step by step, with `cefc_mj.viz.rerun_log`
    (the same entities, timelines and blueprint as `cefc-eval --rrd/--spawn`).

    Call `capture()` after `reset()` and after every `step()` (render_mode="human" does it itself).
    Each episode is its own recording: sent to the viewer (`spawn=True`) and/or written to
    `rrd_path` for the first episode and `<stem>_<k><suffix>` for episode k >= 1.

    >>> import cefc_mj, tempfile, pathlib                       # doctest: +SKIP
    >>> env = cefc_mj.make_env(n_agents=3, mode="formation")    # doctest: +SKIP
    >>> with RerunRecorder(env, rrd_path=pathlib.Path(tempfile.mkdtemp()) / "ep.rrd") as rec:  # doctest: +SKIP
    ...     env.reset(seed=0); rec.capture()
    ...     while env.agents:
    ...         env.step({a: env.action_space(a).sample() for a in env.agents}); rec.capture()
    """

    def __init__(self, env: CEFCParallelEnv, rrd_path: str | os.PathLike | None = None, spawn: bool = False):
        if rrd_path is None and not spawn:
            raise ConfigError("RerunRecorder: give rrd_path, spawn=True, or both")
        self.env = env
        self.rrd_path = None if rrd_path is None else Path(rrd_path)
        self.spawn = spawn
        self.episodes = 0
        self.recording = None
        self._rows: dict[str, np.ndarray] = {}
        self._static: dict = {}
        self._airframe_parts = None  # the drone body for the 3D view, read once

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def capture(self) -> None:
        """Log the env's current state as step t = env.batched.t (t = 0 starts a new episode)."""
        from cefc_mj.viz.rerun_log import log_static, log_steps

        t = int(self.env.batched.t[0])
        if t == 0:
            self._start_episode()
            self._fill(0)
            log_static(self._record(1), self.recording)
            log_steps(self._record(1), self.recording, 0, 1)
            return
        if self.recording is None or t >= len(self._rows["agent_pos"]):
            raise ConfigError("RerunRecorder.capture: capture right after reset() and after every step()")
        self._fill(t)
        log_steps(self._record(t + 1), self.recording, t, t + 1)
        if t == self.env.config.steps:
            self._finish_recording()

    def close(self) -> None:
        self._finish_recording()

    # ------------------------------------------------------------------ internals
    def _episode_path(self) -> Path | None:
        if self.rrd_path is None or self.episodes == 0:
            return self.rrd_path
        return self.rrd_path.with_name(f"{self.rrd_path.stem}_{self.episodes}{self.rrd_path.suffix}")

    def _start_episode(self) -> None:
        from cefc_mj.eval.record import airframe_parts_from_mjcf
        from cefc_mj.paths import MJCF_DIR
        from cefc_mj.task.formation import formation_template
        from cefc_mj.viz.rerun_log import open_recording

        self._finish_recording()
        self.recording = open_recording(rrd_path=self._episode_path(), spawn=self.spawn)
        self.episodes += 1
        env, cfg = self.env.batched, self.env.config
        world = env.world
        rows, n, m = cfg.steps + 1, cfg.n_agents, cfg.n_lidar_rays
        self._rows = {
            "agent_pos": np.zeros((rows, n, 3)), "agent_quat": np.zeros((rows, n, 4)),
            "agent_vel": np.zeros((rows, n, 2)), "anchor": np.zeros((rows, 2)),
            "lidar_origins": np.zeros((rows, n, 2)), "lidar_ranges": np.zeros((rows, n, m)),
            "group_id": np.zeros((rows, n), dtype=np.int64), "template_world": np.full((rows, n, 2), np.nan),
            "collision": np.zeros((rows, n), dtype=bool), "adversary_pos": np.zeros((rows, 3)),
            **{name: np.zeros(rows) for name in _SCALARS},
        }
        wind = getattr(world, "wind_config", None)
        mujoco_config = None if isinstance(world, ParticleWorld) else getattr(world, "config", None)
        condition = []  # the paper's names, as cefc-eval writes them
        if wind is not None and wind.mean_speed:
            condition.append(f"Wind-{wind.mean_speed:g}")
        if cfg.deviation:
            condition.append(f"Deviation-{cfg.deviation:g}")
        if self._airframe_parts is None:
            airframe = MJCF_DIR / "iris.xml"
            self._airframe_parts = airframe_parts_from_mjcf(airframe) if airframe.is_file() else []
        seed = self.env.episode_seed
        self._static = dict(
            backend="particle" if isinstance(world, ParticleWorld) else "mujoco",
            condition="+".join(condition) or "SITL-S", formation=n, seed=-1 if seed is None else int(seed), dt=cfg.dt,
            flight_altitude=getattr(mujoco_config, "flight_altitude", FLIGHT_ALTITUDE),
            obstacles=env.obstacles[0].copy(), obstacle_radius=cfg.obstacle_radius,
            obstacle_height=getattr(mujoco_config, "obstacle_height", OBSTACLE_HEIGHT),
            targets=env.targets[0].copy(), lidar_range=cfg.lidar_range,
            airframe_parts=self._airframe_parts,
        )
        self._template = formation_template(n, cfg.formation_spacing) if cfg.mode == "formation" else None
        self._has_adversary = cfg.mode == "cefc" and cfg.adversary != "none"

    def _fill(self, t: int) -> None:
        """Row t of the episode buffers from the env's current state."""
        env, world, rows = self.env.batched, self.env.batched.world, self._rows
        n, alt = env.n_agents, self._static["flight_altitude"]
        if hasattr(world, "drone_positions"):  # quadrotors: 3D poses (UAVs first, then the adversary)
            rows["agent_pos"][t] = world.drone_positions[0, :n]
            rows["agent_quat"][t] = world.drone_quaternions[0, :n]
        else:
            rows["agent_pos"][t, :, :2] = world.agent_pos[0]
            rows["agent_pos"][t, :, 2] = alt
            rows["agent_quat"][t] = (1.0, 0.0, 0.0, 0.0)
        rows["agent_vel"][t] = world.agent_vel[0]
        rows["anchor"][t] = env.anchor[0]
        rows["lidar_origins"][t] = env.perceived_pos[0]
        rows["lidar_ranges"][t] = env.lidar[0]
        rows["group_id"][t] = env.labels[0]
        centre = world.agent_pos[0].mean(axis=0)
        if self._template is not None:
            rows["template_world"][t] = centre + self._template
        rows["collision"][t] = world.collisions()[0]
        rows["adversary_pos"][t] = (*world.adversary_pos[0], alt)
        rows["hd_error"][t] = np.nanmin(env.agent_error[0]) if np.isfinite(env.agent_error[0]).any() else np.nan
        rows["anchor_distance"][t] = np.linalg.norm(centre - env.anchor[0])
        rows["wind_speed"][t] = np.linalg.norm(world.wind_vector[0, :2]) if hasattr(world, "wind_vector") else 0.0
        metrics = env.episode_metrics()
        for key in ("F", "N", "C"):
            rows[f"{key}_so_far"][t] = metrics[key][0]

    def _record(self, length: int):
        """The episode's first `length` rows as an EpisodeRecord (views, no copies)."""
        from cefc_mj.eval.record import EpisodeRecord

        rows = self._rows
        scalars = {k: rows[k][:length] for k in _SCALARS}
        arrays = {k: rows[k][:length] for k in ("agent_pos", "agent_quat", "agent_vel", "anchor", "lidar_origins",
                                               "lidar_ranges", "group_id", "template_world", "collision")}
        adversary = rows["adversary_pos"][:length] if self._has_adversary else None
        return EpisodeRecord(**self._static, **arrays, scalars=scalars, adversary_pos=adversary)

    def _finish_recording(self) -> None:
        from cefc_mj.viz.rerun_log import close_recording

        recording, self.recording = self.recording, None
        if recording is not None:
            close_recording(recording)
