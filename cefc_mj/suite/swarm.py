"""The quadrotor swarm as a dm_control environment: `SwarmPhysics`, `SwarmTask`, `SwarmEnvironment`.

The task wraps the PettingZoo env of `cefc_mj.make_env(backend="mujoco", ...)` (one env of
`BatchedCEFCEnv` over a `MujocoWorld`), so observations, rewards, the wind, the sensing deviation,
the position estimate and the separation guard are the project's own code, and a dm_env episode
steps bit for bit like the PettingZoo one from the same seed and actions. The physics is a
`dm_control.mujoco.Physics` over the very MjModel / MjData the world steps (env 0's), so
`physics.render`, `physics.named` and `dm_control.viewer` see the real state.

Layout (multi-agent, in the style of dm_control's soccer: per-agent lists):

- action: one `BoundedArray` [N, 2] float64, row i the acceleration setpoint [a_x, a_y] (m/s^2) of
  `uav_i`, in [-accel_max, accel_max] (what `Policy.act` returns for an [N, D] observation).
- observation: a list of N `OrderedDict`s, agent i's the parts of its observation vector in the
  layout's order (formation: anchor, own_velocity, neighbours, neighbour_mask, lidar; game: targets,
  adversary, neighbours, neighbour_mask, lidar), float32 with the PettingZoo env's finite bounds.
  `stack_observations` joins them into the [N, D] matrix the shipped policies read.
- reward: a list of N float64 scalars, the team reward (the same for every agent).
- discount: a scalar, 1.0; the episode ends after the task's decision steps by truncation (LAST
  with discount 1.0).

One `env.step` is one decision step (0.1 s): the task's `before_step` hands the actions to the
PettingZoo env, whose world flies the drones through its PX4-like cascade and `mj_step` (the cascade
sets the rotor thrusts between MuJoCo steps, at 250 and 100 Hz, which a plain `mj_step` loop cannot
do). `SwarmPhysics.step`, which the environment calls next, therefore advances nothing: it checks that
the world has just run exactly that many physics steps, and refuses to be called on its own.
"""

from __future__ import annotations

import collections
import os
import sys

import numpy as np

from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.viz.frames import VIEW_AZIMUTH, VIEW_ELEVATION, VIEW_FOVY, fit_camera, view_box
from cefc_mj.viz.recorder import has_display

if sys.platform.startswith("linux") and not has_display():
    # dm_control picks its OpenGL backend when first imported: EGL when headless (as make_env does for MuJoCo)
    os.environ.setdefault("MUJOCO_GL", "egl")

from dm_control import mujoco  # noqa: E402
from dm_control.mujoco import wrapper  # noqa: E402
from dm_control.rl import control  # noqa: E402
from dm_env import specs  # noqa: E402

DEFAULT_VIEW_ASPECT = 320 / 240
"""Aspect ratio (width / height) the default free camera frames the arena for: `Physics.render`'s default size."""


class PhysicsStepRefused(CefcError, RuntimeError):
    """`SwarmPhysics.step` was called outside `env.step`: the swarm's physics advances only there."""


class SwarmPhysics(mujoco.Physics):
    """A dm_control `Physics` over env 0 of a `MujocoWorld`: the same MjModel and MjData objects.

    `from_world` also points the model's visual statistics at the arena (`frame_arena`), so that the
    free camera (`render(camera_id=-1)`, the viewer's start view) shows the arena rather than the
    parked obstacles. `render` draws every geom group by default (the UAV footprints are group 2,
    the adversary's group 4), unless given a scene_option.
    """

    _world = None
    _ticks = 0

    @classmethod
    def from_world(cls, world, task_config) -> SwarmPhysics:
        """The physics of env 0 of `world` (a MujocoWorld with n_envs = 1), framed for `task_config`."""
        if getattr(world, "n_envs", None) != 1 or not hasattr(world, "datas"):
            raise ConfigError("SwarmPhysics: needs a MujocoWorld with n_envs=1")
        physics = cls(wrapper.MjData(world.datas[0]))
        physics._world = world
        physics._ticks = physics.world_ticks()
        frame_arena(world.models[0], task_config, float(world.config.obstacle_height))
        return physics

    @property
    def world(self):
        """The MujocoWorld whose env 0 this physics is."""
        return self._world

    def world_ticks(self) -> int:
        """Physics steps the world has run in env 0 since its last reset."""
        return int(round(float(self._world.sim_time[0]) / self._world.config.physics_dt))

    def sync(self) -> None:
        """Record the world's physics step count (after a reset)."""
        self._ticks = self.world_ticks()

    def step(self, nstep: int = 1) -> None:
        """Checks that the world has just run `nstep` physics steps in the task's `before_step` (module
        docstring); PhysicsStepRefused otherwise, e.g. when called on its own."""
        now = self.world_ticks()
        ran, self._ticks = now - self._ticks, now
        if ran != nstep:
            raise PhysicsStepRefused(
                f"SwarmPhysics.step({nstep}): the world ran {ran} physics steps; the swarm's physics advances "
                "only through env.step(action) (its PX4-like cascade sets the rotor thrusts between MuJoCo steps)"
            )

    def render(self, height=240, width=320, camera_id=-1, scene_option=None, **kwargs):
        """`dm_control.mujoco.Physics.render`, with every geom group shown when no scene_option is given."""
        if scene_option is None:
            scene_option = wrapper.MjvOption()
            scene_option.geomgroup[:] = 1
        return super().render(height=height, width=width, camera_id=camera_id, scene_option=scene_option, **kwargs)


def frame_arena(model, task_config, obstacle_height: float, aspect: float = DEFAULT_VIEW_ASPECT) -> None:
    """Point the model's free camera at the arena: `stat.center` and `stat.extent` (which MuJoCo's free
    camera, its near and far planes and dm_control's viewer read; the world compiles them from the
    obstacles parked 1 km away) and `vis.global_` azimuth, elevation and fovy, as the project's frames
    look (cefc_mj.viz.frames.fit_camera). Visual statistics only: the dynamics never read them (the
    suite's tests step this model bit for bit like an untouched one)."""
    box = view_box(task_config, obstacle_height)
    lookat, distance = fit_camera(box, VIEW_ELEVATION, VIEW_AZIMUTH, VIEW_FOVY, aspect)
    model.stat.center[:] = lookat
    model.stat.extent = distance / 1.5  # mjv_defaultFreeCamera's distance is 1.5 x extent
    model.vis.global_.azimuth = VIEW_AZIMUTH
    model.vis.global_.elevation = VIEW_ELEVATION
    model.vis.global_.fovy = VIEW_FOVY


class SwarmTask(control.Task):
    """The CEFC task of a PettingZoo env (`cefc_mj.make_env(backend="mujoco", ...)`) as a dm_control Task.

    Args:
        parallel_env: the `CEFCParallelEnv` whose world `SwarmPhysics` wraps.
        seed: the first episode's seed (`parallel_env.reset(seed=seed)`); later episodes continue the
            env's random streams, as dm_control's suite tasks continue theirs.

    Attributes: `parallel_env`; `infos` (the PettingZoo infos of the last reset or step: each agent's
    true `position` and `velocity`, and the episode `metrics` F, N, C, E at its end).
    """

    def __init__(self, parallel_env, seed: int | None = None):
        self.parallel_env = parallel_env
        self.agents = list(parallel_env.possible_agents)
        self.layout = parallel_env.layout
        self._seed = seed
        self._episodes = 0
        self._observations: dict[str, np.ndarray] | None = None
        self._rewards: dict[str, float] | None = None
        self._truncated = False
        self.infos: dict[str, dict] = {}
        a = parallel_env.config.accel_max
        self._action_spec = specs.BoundedArray((len(self.agents), 2), np.float64, -a, a, name="acceleration")
        self._observation_spec = [
            self._split_spec(parallel_env.observation_space(agent), agent) for agent in self.agents
        ]
        self._reward_spec = [specs.Array((), np.float64, name=agent) for agent in self.agents]

    # ------------------------------------------------------------------ dm_control Task
    def initialize_episode(self, physics: SwarmPhysics) -> None:
        seed = self._seed if self._episodes == 0 else None
        self._observations, self.infos = self.parallel_env.reset(seed=seed)
        self._episodes += 1
        self._rewards, self._truncated = None, False
        physics.sync()

    def before_step(self, action, physics: SwarmPhysics) -> None:
        actions = np.asarray(action, dtype=np.float64)
        if actions.shape != self._action_spec.shape:
            raise ConfigError(
                f"action: expected shape {list(self._action_spec.shape)} (row i = uav_i's [a_x, a_y], m/s^2), "
                f"got {list(actions.shape)}"
            )
        observations, rewards, _, truncations, infos = self.parallel_env.step(
            {agent: actions[i] for i, agent in enumerate(self.agents)}
        )
        self._observations, self._rewards, self.infos = observations, rewards, infos
        self._truncated = any(truncations.values())

    def get_observation(self, physics: SwarmPhysics) -> list[collections.OrderedDict]:
        parts = [(name, self.layout[name]) for name in self.layout.names()]
        obs = self._observations
        return [collections.OrderedDict((name, obs[agent][part]) for name, part in parts) for agent in self.agents]

    def get_reward(self, physics: SwarmPhysics) -> list[np.float64]:
        return [np.float64(self._rewards[agent]) for agent in self.agents]

    def get_termination(self, physics: SwarmPhysics) -> float | None:
        return 1.0 if self._truncated else None

    def action_spec(self, physics: SwarmPhysics) -> specs.BoundedArray:
        return self._action_spec

    def observation_spec(self, physics: SwarmPhysics) -> list[collections.OrderedDict]:
        return self._observation_spec

    def reward_spec(self, physics: SwarmPhysics) -> list[specs.Array]:
        """One scalar float64 spec per agent, named after it."""
        return self._reward_spec

    # ------------------------------------------------------------------ helpers
    def _split_spec(self, space, agent: str) -> collections.OrderedDict:
        parts = collections.OrderedDict()
        for name in self.layout.names():
            part = self.layout[name]
            parts[name] = specs.BoundedArray(
                (part.stop - part.start,), np.float32, space.low[part], space.high[part], name=f"{agent}/{name}"
            )
        return parts


class SwarmEnvironment(control.Environment):
    """`dm_control.rl.control.Environment` with the task's per-agent reward spec; `close` frees the
    physics (its rendering contexts) and closes the PettingZoo env: the environment is done with."""

    def reward_spec(self):
        return self._task.reward_spec(self._physics)

    def close(self) -> None:
        if hasattr(self._physics, "_data"):  # not freed yet
            self._physics.free()  # its rendering contexts; the world keeps its MjData
        self._task.parallel_env.close()


__all__ = [
    "PhysicsStepRefused",
    "SwarmEnvironment",
    "SwarmPhysics",
    "SwarmTask",
    "frame_arena",
]
