"""cefc-mj: a MuJoCo multi-quadrotor testbed and learning system for Cooperative Evasion and
Formation Coverage (the CI-HRL paper).

>>> import cefc_mj
>>> env = cefc_mj.make_env(backend="particle", n_agents=8, seed=0)
>>> observations, infos = env.reset(seed=0)
>>> observations["uav_0"].shape
(69,)
"""

from __future__ import annotations

import dataclasses

from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig

__version__ = "0.1.0"

BACKENDS = ("particle", "mujoco")


def make_task_config(n_agents: int = 8, **task_options) -> TaskConfig:
    """A validated TaskConfig; unknown option names raise ConfigError (a typo must fail loudly)."""
    known = {f.name for f in dataclasses.fields(TaskConfig)}
    unknown = sorted(set(task_options) - known)
    if unknown:
        raise ConfigError(f"unknown task option(s): {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return TaskConfig(n_agents=n_agents, **task_options)


def make_world(backend: str, config: TaskConfig, n_envs: int = 1, wind: float = 0.0, seed: int | None = None,
               airframe: str | None = None, offboard: str | None = None, wind_direction: float | None = None,
               rotor_actuation: str | None = None):
    """The physics world for `backend` ("particle" or "mujoco"); wind (m/s mean speed), wind_direction
    (degrees the air moves towards, ENU: 0 = +x, 90 = +y; None = drawn per episode from the seed),
    airframe (a shipped name such as "iris" or "crazyflie", or an MJCF path; docs/mujoco_world.md) and
    offboard (what the PX4-like interface makes of a setpoint: "velocity", the default, or
    "acceleration") and rotor_actuation ("auto", the default, "actuators" or "external":
    docs/mujoco_world.md) are MuJoCo's."""
    if backend not in BACKENDS:
        raise ConfigError(f"backend={backend!r}: must be one of {', '.join(BACKENDS)}")
    if not isinstance(wind, (int, float)) or not wind == wind or wind < 0:
        raise ConfigError(f"wind={wind!r}: must be a number >= 0 (mean wind speed, m/s)")
    if backend == "particle":
        if wind:
            raise ConfigError("wind: the particle backend has no wind model; use backend='mujoco'")
        if wind_direction is not None:
            raise ConfigError("wind_direction: the particle backend has no wind model; use backend='mujoco'")
        if airframe is not None:
            raise ConfigError("airframe: the particle backend has no airframe; use backend='mujoco'")
        if offboard is not None:
            raise ConfigError("offboard: the particle backend has no offboard interface; use backend='mujoco'")
        if rotor_actuation is not None:
            raise ConfigError("rotor_actuation: the particle backend has no rotors; use backend='mujoco'")
        from cefc_mj.sim.particle import ParticleWorld

        return ParticleWorld(config, n_envs, seed=seed)
    from cefc_mj.sim.mujoco_world import MujocoWorldConfig, make_mujoco_world

    options = {k: v for k, v in (("offboard", offboard), ("rotor_actuation", rotor_actuation)) if v is not None}
    world_config = MujocoWorldConfig(**options) if options else None
    return make_mujoco_world(config, n_envs=n_envs, wind=wind, seed=seed, airframe=airframe, config=world_config,
                             wind_direction=wind_direction)


EVALUATOR_AGENT = {"position_estimator": "fused", "separation_guard": True}
"""The TaskConfig fields that make an agent the one cefc-eval flies (make_env(evaluator_agent=True))."""


def make_env(
    backend: str = "particle",
    n_agents: int = 8,
    *,
    wind: float = 0.0,
    wind_direction: float | None = None,
    deviation: float = 0.0,
    seed: int | None = None,
    render_mode: str | None = None,
    airframe: str | None = None,
    evaluator_agent: bool = False,
    **task_options,
):
    """The CEFC game as a PettingZoo `ParallelEnv` (agents `uav_0 .. uav_{N-1}`; docs/pettingzoo.md).

    Args:
        backend: "particle" (the paper's MPE, point masses) or "mujoco" (quadrotors with a PX4-like
            controller).
        n_agents: N, number of UAVs (>= 1; formation mode needs >= 3).
        wind: mean wind speed (m/s), MuJoCo backend only.
        wind_direction: the direction the wind blows towards, degrees (ENU: 0 = +x, 90 = +y); None (the
            default) draws it uniformly per episode from the seed. Needs wind > 0.
        deviation: sensing deviation d (m), both backends.
        seed: seeds the scenario, sensing noise and wind; the same seed gives the same rollout.
        render_mode: None, "rgb_array" (`env.render()` returns an [H, W, 3] uint8 frame; MuJoCo
            renders offscreen with OpenGL, EGL when there is no display) or "human" (streams every
            step to a live Rerun viewer).
        airframe: MuJoCo only: "iris" (default), "crazyflie", or your own MJCF quadrotor with four
            site-mounted thrust motors and a PX4-style params file (docs/mujoco_world.md).
        evaluator_agent: True makes each agent the one `cefc-eval` flies (mode="formation"): it acts on the
            fused position estimate (position_estimator="fused") and the env passes its actions through
            the separation guard (separation_guard=True) before they reach the physics. False (the
            default) is the paper's agent: raw fixes, the actions as given.
        **task_options: any `TaskConfig` field, e.g. mode="formation", obstacle_density=0.03.

    Raises:
        ConfigError (a ValueError) naming the bad argument.
    """
    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.pettingzoo_env import CEFCParallelEnv, check_render_mode, prefer_headless_gl

    if backend not in BACKENDS:
        raise ConfigError(f"backend={backend!r}: must be one of {', '.join(BACKENDS)}")
    check_render_mode(render_mode)
    if not isinstance(evaluator_agent, bool):
        raise ConfigError(f"evaluator_agent={evaluator_agent!r}: must be True or False")
    if evaluator_agent:
        for name, value in EVALUATOR_AGENT.items():
            if task_options.setdefault(name, value) != value:
                raise ConfigError(f"evaluator_agent=True sets {name}={value!r}; drop {name}={task_options[name]!r}")
    config = make_task_config(n_agents=n_agents, deviation=deviation, **task_options)
    if backend == "mujoco" and render_mode == "rgb_array":
        prefer_headless_gl()  # before the world imports mujoco, which reads MUJOCO_GL once
    world = make_world(backend, config, n_envs=1, wind=wind, seed=seed, airframe=airframe,
                       wind_direction=wind_direction)
    return CEFCParallelEnv(BatchedCEFCEnv(config, n_envs=1, seed=seed, world=world), render_mode=render_mode)


__all__ = ["make_env", "make_task_config", "make_world", "TaskConfig", "ConfigError", "BACKENDS"]
