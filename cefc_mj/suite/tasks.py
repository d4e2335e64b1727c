"""The tasks of the `cefc` domain and the checks of a `load` call; no dm_control here (importing
`cefc_mj.suite` needs no extra, `load` does)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from cefc_mj.errors import ConfigError
from cefc_mj.task.config import TaskConfig

DOMAIN = "cefc"
"""The suite's one domain: the CEFC quadrotor swarm (MuJoCo backend)."""


@dataclass(frozen=True)
class SuiteTask:
    """One task of the `cefc` domain: the scene `cefc_mj.make_env` builds for it."""

    description: str
    """What is flown, in one line."""
    options: Mapping[str, object]
    """`make_env` keyword arguments that define the scene (swarm size, mode, obstacles, episode
    length, ...). `task_kwargs` may change any of them except FIXED_OPTIONS, and add the others."""
    policy: str | None
    """The shipped low-level policy that flies it (`cefc-view`'s default; `load_policy(name)`), or
    None where no single shipped policy reads its observation (the game's agents are hierarchical)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))  # read-only


# The scenes cefc-eval flies (tests/test_suite_dm_control.py holds them equal): Table VIII for formation,
# cefc_mj.eval.runner.EpisodeSpec(formation=c).task_config() (its agent options aside: they are task_kwargs
# here, e.g. evaluator_agent=True), and the game of Tables V and VI, cefc_mj.game_protocol.game_task().
_TABLE8 = {"mode": "formation", "obstacle_density": 0.03, "episode_steps": 1000, "anchor_redraw_steps": 250}
TASKS: dict[str, SuiteTask] = {
    **{
        f"formation_c{c}": SuiteTask(
            f"{c} quadrotors keep formation and navigate to anchors redrawn every 25 s among obstacles (Table VIII)",
            {"n_agents": c, **_TABLE8},
            f"atm_c{c}_nav",
        )
        for c in range(3, 9)
    },
    "cefc_game": SuiteTask(
        "the full game: 8 quadrotors cover two targets and evade the nearest-group adversary (Tables V, VI)",
        {
            "n_agents": 8,
            "mode": "cefc",
            "obstacle_density": 0.03,
            "adversary": "nearest_group",
            "adversary_avoids_obstacles": True,
            "episode_steps": 400,
            "position_estimator": "fused",
        },
        None,
    ),
}
"""Task name -> SuiteTask."""
ALL_TASKS = tuple((DOMAIN, name) for name in TASKS)
"""(domain, task) pairs, as dm_control.suite.ALL_TASKS."""
FIXED_OPTIONS = ("backend", "render_mode", "n_agents", "mode")
"""make_env arguments a task fixes: the backend is MuJoCo, frames come from `physics.render`, and the
swarm size and mode are in the task's name."""
ENVIRONMENT_KWARGS = ("time_limit",)
"""What `environment_kwargs` may hold: `time_limit` (s), a whole number of decision steps, which sets the
episode length (TaskConfig.episode_steps). Substeps are the world's (decision_dt / physics_dt); flat
observations do not apply to per-agent lists."""


def task_options(domain_name, task_name, task_kwargs, environment_kwargs) -> tuple[dict, int | None]:
    """(make_env options without seed, seed) of a load() call; ConfigError for bad input."""
    if domain_name != DOMAIN:
        raise ConfigError(f"domain_name={domain_name!r}: the only domain is {DOMAIN!r}")
    if task_name not in TASKS:
        raise ConfigError(f"task_name={task_name!r}: must be one of {', '.join(TASKS)}")
    for name, value in (("task_kwargs", task_kwargs), ("environment_kwargs", environment_kwargs)):
        if value is not None and not isinstance(value, Mapping):
            raise ConfigError(f"{name}: expected a dict, got {type(value).__name__}")
    task_kwargs, environment_kwargs = dict(task_kwargs or {}), dict(environment_kwargs or {})
    fixed = sorted(set(task_kwargs) & set(FIXED_OPTIONS))
    if fixed:
        raise ConfigError(f"task_kwargs: {', '.join(fixed)} fixed by the task {task_name!r}; pick another task instead")
    if "random" in task_kwargs and "seed" in task_kwargs:
        raise ConfigError("task_kwargs: give seed or random (the same seed), not both")
    seed = task_kwargs.pop("random", task_kwargs.pop("seed", None))
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise ConfigError(f"task_kwargs: seed={seed!r}: must be an integer or None")
    unknown = sorted(set(environment_kwargs) - set(ENVIRONMENT_KWARGS))
    if unknown:
        raise ConfigError(
            f"environment_kwargs: {', '.join(unknown)} not supported (only {', '.join(ENVIRONMENT_KWARGS)}: "
            "the substeps are the world's, and the observations are per-agent lists)"
        )
    options = {**TASKS[task_name].options, **task_kwargs}
    if "time_limit" in environment_kwargs:
        if "episode_steps" in task_kwargs:
            raise ConfigError("give time_limit (environment_kwargs) or episode_steps (task_kwargs), not both")
        options["episode_steps"] = _steps_of(environment_kwargs["time_limit"], float(options.get("dt", TaskConfig.dt)))
    return options, seed


def _steps_of(time_limit, dt: float) -> int:
    """Decision steps in `time_limit` seconds; ConfigError unless a whole number >= 1 of them."""
    steps = time_limit / dt if isinstance(time_limit, (int, float)) and not isinstance(time_limit, bool) else math.nan
    if not (math.isfinite(steps) and steps >= 1 - 1e-9 and abs(steps - round(steps)) < 1e-6):
        raise ConfigError(f"time_limit={time_limit!r}: must be a whole number (>= 1) of decision steps of {dt} s")
    return int(round(steps))


def stack_observations(observation: Sequence[Mapping[str, np.ndarray]]) -> np.ndarray:
    """[N, D] float32: each agent's observation parts joined in order, the rows the shipped policies read
    (`policy.act(stack_observations(time_step.observation))` -> the [N, 2] action)."""
    if not isinstance(observation, Sequence) or not all(isinstance(o, Mapping) for o in observation):
        raise ConfigError("observation: expected the environment's list of per-agent dicts")
    return np.stack([np.concatenate(list(o.values())) for o in observation]).astype(np.float32, copy=False)
