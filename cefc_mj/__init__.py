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
from cefc_mj.sim.backends import BACKENDS, make_world
from cefc_mj.task.config import TaskConfig
from cefc_mj.version import __version__  # noqa: F401 (re-exported)


def make_task_config(n_agents: int = 8, **task_options) -> TaskConfig:
    """A validated TaskConfig; unknown option names raise ConfigError (a typo must fail loudly)."""
    known = {f.name for f in dataclasses.fields(TaskConfig)}
    unknown = sorted(set(task_options) - known)
    if unknown:
        raise ConfigError(f"unknown task option(s): {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    return TaskConfig(n_agents=n_agents, **task_options)


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
            site-mounted thrust motors and a PX4-style params file (docs/airframes.md).
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
    world = make_world(
        backend, config, n_envs=1, wind=wind, seed=seed, airframe=airframe, wind_direction=wind_direction
    )
    return CEFCParallelEnv(BatchedCEFCEnv(config, n_envs=1, seed=seed, world=world), render_mode=render_mode)


__all__ = ["make_env", "make_task_config", "make_world", "TaskConfig", "ConfigError", "BACKENDS"]
