"""dm_control environments of the quadrotor swarm, loaded like dm_control's suite (docs/dm_control.md).

>>> from cefc_mj import suite
>>> env = suite.load("cefc", "formation_c6", task_kwargs={"seed": 0})   # doctest: +SKIP
>>> time_step = env.reset()                                             # doctest: +SKIP
>>> suite.stack_observations(time_step.observation).shape               # doctest: +SKIP
(6, 63)

`load(domain_name, task_name, task_kwargs=None, environment_kwargs=None)` returns a
`dm_control.rl.control.Environment` (a `dm_env.Environment`) whose physics is the MuJoCo world of
`cefc_mj.make_env(backend="mujoco", ...)` and whose task is that env's CEFC task
(`cefc_mj.suite.swarm`: spaces, layout, stepping). `load` needs the `dm-control` extra
(`pip install -e '.[dm-control]'`); importing this package does not, and `import cefc_mj` does not
import it at all.
"""

from __future__ import annotations

from collections.abc import Mapping

from cefc_mj.errors import CefcError
from cefc_mj.suite.tasks import (
    ALL_TASKS,
    DOMAIN,
    ENVIRONMENT_KWARGS,
    FIXED_OPTIONS,
    TASKS,
    SuiteTask,
    stack_observations,
    task_options,
)

DM_CONTROL_HINT = "pip install 'cefc-mj[dm-control]' (from a checkout: pip install -e '.[dm-control]')"
"""How to install the extra `load` needs."""
_SWARM_NAMES = ("PhysicsStepRefused", "SwarmEnvironment", "SwarmPhysics", "SwarmTask", "frame_arena")


class MissingExtra(CefcError, ImportError):
    """dm-control (the `dm-control` extra) is not installed; the message says how to install it."""


def load(
    domain_name: str,
    task_name: str,
    task_kwargs: Mapping | None = None,
    environment_kwargs: Mapping | None = None,
):
    """The dm_control environment (a `SwarmEnvironment`) of a task of the `cefc` domain (TASKS).

    Args:
        domain_name: "cefc".
        task_name: a name in TASKS ("formation_c3" .. "formation_c8", "cefc_game").
        task_kwargs: `cefc_mj.make_env` options, passed through: seed (or `random`, the suite's name
            for it: an int or None; the first episode's seed, later episodes continue its streams),
            wind, wind_direction, deviation, airframe, evaluator_agent (the fused estimate and the
            separation guard, as cefc-eval flies), and any TaskConfig field (e.g. episode_steps).
        environment_kwargs: {"time_limit": seconds} (ENVIRONMENT_KWARGS).

    Raises:
        ConfigError (a ValueError) with one line naming the bad argument, before anything is built;
        MissingExtra (an ImportError) without dm-control.
    """
    options, seed = task_options(domain_name, task_name, task_kwargs, environment_kwargs)
    swarm = _swarm()
    import cefc_mj

    parallel_env = cefc_mj.make_env(backend="mujoco", seed=seed, **options)
    world = parallel_env.batched.world
    physics = swarm.SwarmPhysics.from_world(world, parallel_env.config)
    task = swarm.SwarmTask(parallel_env, seed=seed)
    return swarm.SwarmEnvironment(physics, task, n_sub_steps=world.n_substeps)


def _swarm():
    """The dm_control module of the suite; MissingExtra without dm-control, or beside a MuJoCo it fails with."""
    try:
        from cefc_mj.suite import swarm
    except ImportError as e:
        if (e.name or "").split(".")[0] not in ("dm_control", "dm_env"):
            raise
        raise MissingExtra(f"the dm_control suite needs dm-control: {DM_CONTROL_HINT}") from None
    from importlib.metadata import PackageNotFoundError, version

    import mujoco

    try:
        installed = version("dm-control")
    except PackageNotFoundError:  # a source tree on the path: nothing to check against
        return swarm
    if installed == "1.0.50" and int(mujoco.__version__.split(".")[0]) >= 4:
        raise MissingExtra(
            f"dm-control {installed} fails with mujoco {mujoco.__version__} (it needs mujoco 3.x): {DM_CONTROL_HINT}"
        )
    return swarm


def __getattr__(name: str):
    """The dm_control classes (SwarmPhysics, SwarmTask, SwarmEnvironment, ...), imported when first asked for."""
    if name in _SWARM_NAMES:
        return getattr(_swarm(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ALL_TASKS",
    "DM_CONTROL_HINT",
    "DOMAIN",
    "ENVIRONMENT_KWARGS",
    "FIXED_OPTIONS",
    "MissingExtra",
    "SuiteTask",
    "TASKS",
    "load",
    "stack_observations",
    "task_options",
    *_SWARM_NAMES,
]
