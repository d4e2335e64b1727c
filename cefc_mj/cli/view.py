"""cefc-view: watch a shipped policy fly a task of the dm_control suite in `dm_control.viewer`.

Examples:
  cefc-view                                   # formation_c6, flown by atm_c6_nav
  cefc-view formation_c8 --wind 8 --seed 3    # 8 quadrotors in 8 m/s wind
  cefc-view cefc_game                         # the game, the swarm hovering (--policy none) under attack

The viewer is a window: it needs a display (DISPLAY or WAYLAND_DISPLAY). Without one, and for bad
input, it prints one line on stderr and exits with status 2 before anything is built. Headless (a
server, CI), render frames offscreen instead: set MUJOCO_GL=egl (or MUJOCO_GL=osmesa) before dm_control
is imported and call the task's env.physics.render(). The viewer opens paused: Space runs and pauses,
Backspace starts a new episode, F1 lists the viewer's keys.

Docs: docs/dm_control.md (the suite, the viewer, offscreen frames).
"""

from __future__ import annotations

import argparse
import sys

from cefc_mj.errors import CefcError, ConfigError, ExamplesHelpFormatter, OneLineParser
from cefc_mj.suite.tasks import DOMAIN, TASKS, task_options
from cefc_mj.viz.recorder import has_display

PROG = "cefc-view"
EXIT_USAGE = 2
DEFAULT_TASK = "formation_c6"
NO_POLICY = "none"


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=PROG,
        description="Open dm_control's viewer on a task of the cefc suite (cefc_mj.suite), a shipped policy flying.",
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=ExamplesHelpFormatter,
    )
    tasks = ", ".join(f"{name} ({task.policy or NO_POLICY})" for name, task in TASKS.items())
    parser.add_argument(
        "task",
        nargs="?",
        default=DEFAULT_TASK,
        help=f"the task, with its default policy in brackets: {tasks} (default: {DEFAULT_TASK})",
    )
    parser.add_argument(
        "--policy",
        help=f"a low-level policy in policies/ or a .pt path, whose observation is the task's; "
        f"'{NO_POLICY}' sends zero setpoints (the swarm hovers). Default: the task's",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    parser.add_argument("--wind", type=float, default=0.0, help="mean wind speed, m/s (default 0)")
    parser.add_argument(
        "--wind-direction", type=float, help="degrees the wind blows towards (ENU, 0 = +x); default: drawn per episode"
    )
    parser.add_argument("--deviation", type=float, default=0.0, help="sensing deviation d, m (default 0)")
    parser.add_argument(
        "--paper-agent",
        action="store_true",
        help="fly the paper's agent (raw fixes, actions as they are) instead of cefc-eval's (fused estimate, guard)",
    )
    return parser


def usage_error(message: str) -> None:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    raise SystemExit(EXIT_USAGE)


def prepare(args: argparse.Namespace):
    """(task_kwargs, the policy or None) of the arguments, checked without building the world: a
    CefcError (ConfigError, CheckpointError, MissingExtra) naming the bad one."""
    import math

    if args.task not in TASKS:
        raise ConfigError(f"task {args.task!r}: must be one of {', '.join(TASKS)}")
    if not (math.isfinite(args.wind) and args.wind >= 0):
        raise ConfigError(f"--wind {args.wind}: must be a number >= 0 (m/s)")
    task_kwargs = {"seed": args.seed, "wind": args.wind, "deviation": args.deviation}
    if args.wind_direction is not None:
        if not args.wind:
            raise ConfigError("--wind-direction: there is no wind to point (give --wind > 0)")
        if not math.isfinite(args.wind_direction):
            raise ConfigError(f"--wind-direction {args.wind_direction}: must be a finite angle (degrees)")
        task_kwargs["wind_direction"] = args.wind_direction
    if not args.paper_agent:
        task_kwargs["evaluator_agent"] = True
    options, _ = task_options(DOMAIN, args.task, task_kwargs, None)
    import cefc_mj
    from cefc_mj.task.observation import layout_for

    env_only = ("wind", "wind_direction", "airframe", "evaluator_agent")  # make_env's own, not TaskConfig fields
    config = cefc_mj.make_task_config(**{k: v for k, v in options.items() if k not in env_only})
    try:
        import dm_control  # noqa: F401 (the package only: its GL backend is picked later, by the suite)
    except ImportError:
        from cefc_mj.suite import DM_CONTROL_HINT, MissingExtra

        raise MissingExtra(f"the viewer needs dm-control: {DM_CONTROL_HINT}") from None
    name = policy_name(args)
    if name == NO_POLICY:
        return task_kwargs, None
    from cefc_mj.nn.policy_io import load_policy

    policy = load_policy(name)
    size = layout_for(config).size
    if policy.obs_dim != size:
        raise ConfigError(f"--policy {name}: reads {policy.obs_dim} numbers, the observation of {args.task} has {size}")
    if policy.task_for(config) != config:  # the LiDAR it was trained with, as every evaluator flies it
        task_kwargs["lidar_sees_agents"] = policy.task_for(config).lidar_sees_agents
    return task_kwargs, policy


def policy_name(args: argparse.Namespace) -> str:
    """The policy flown: --policy, else the task's shipped one, else 'none'."""
    return args.policy or TASKS[args.task].policy or NO_POLICY


def viewer_policy(policy):
    """The callable dm_control's viewer calls with each TimeStep: the policy's [N, 2] action, or zeros."""
    from cefc_mj.suite import stack_observations

    if policy is None:
        return None  # the viewer then sends its default action: the middle of the bounds, zero setpoints

    def act(time_step):
        return policy.act(stack_observations(time_step.observation))

    return act


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        task_kwargs, policy = prepare(args)
    except CefcError as e:
        usage_error(str(e))
    if not has_display():
        usage_error(
            "no display to open the viewer on (DISPLAY / WAYLAND_DISPLAY unset); headless, render frames "
            "with env.physics.render (docs/dm_control.md)"
        )
    from cefc_mj import suite

    try:
        env = suite.load(DOMAIN, args.task, task_kwargs=task_kwargs)
        from dm_control import viewer
    except CefcError as e:
        usage_error(str(e))
    viewer.launch(env, policy=viewer_policy(policy), title=f"{PROG}: {args.task} ({policy_name(args)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
