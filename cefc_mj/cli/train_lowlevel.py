"""`cefc-train lowlevel`, `distill`, `lowlevel-all` and `clm`: the low-level trainers' flags (the
defaults are LowLevelConfig's, DistillConfig's and PPOConfig's, cefc_mj/train/config.py), the
--seeds sweep, and the runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from cefc_mj import paths
from cefc_mj.cli.train_common import (
    LOWLEVEL_DOCS,
    add_common_args,
    add_ppo_args,
    check_destinations,
    field_default,
    install,
    ppo_from,
    subcommand_help,
)
from cefc_mj.errors import ConfigError
from cefc_mj.train.config import (
    CLM_CURRICULUM,
    DISTILL_TEACHERS,
    FORMATIONS,
    Budget,
    DistillConfig,
    LowLevelConfig,
    MujocoTraining,
)

COMMANDS = ("lowlevel", "distill", "lowlevel-all", "clm")

FLAG_OF_FIELD = {
    "n_envs": "--envs",
    "epochs": "--epochs",
    "minibatches": "--minibatches",
    "lr": "--lr",
    "gamma": "--gamma",
    "collision_credit": "--credit",
    "update_threads": "--threads",
    "seed": "--seed",
    "obstacle_density": "--density",
    "deviation": "--deviation",
    "deviation_sampling": "--deviation-sampling",
    "response_time": "--response-time",
    "velocity_noise": "--velocity-noise",
    "accel_max": "--accel-max",
    "push_observer_s": "--push-observer",
    "collision_margin": "--collision-margin",
    "navigation_weight": "--navigation-weight",
    "anchor_periods": "--anchor-periods",
    "straggler_fraction": "--straggler-fraction",
    "safe": "--safe",
    "lidar_sees_uavs": "--lidar",
    "tuples_per_formation": "--tuples",
    "formations": "--formations",
    "response_time/velocity_noise": "--response-time/--velocity-noise",
    "curriculum": "--curriculum",
    "mujoco": "--backend mujoco",
    "mujoco.offboard": "--offboard",
    "mujoco.wind_max": "--wind-max",
    "mujoco.gust_speed": "--gust-speed",
    "mujoco.gust_duration": "--gust-duration",
    "mujoco.rollout_workers": "--rollout-workers",
    "mujoco.critic_warmup": "--critic-warmup",
}
"""Config fields (LowLevelConfig, DistillConfig, PPOConfig) set from a flag: their validation errors
name the flag the user typed."""

_LIDAR = {True: "obstacles+uavs", False: "obstacles"}
"""--lidar's choices by LowLevelConfig.lidar_sees_uavs."""


def _low(name: str):
    return field_default(LowLevelConfig, name)


def _distill(name: str):
    return field_default(DistillConfig, name)


def _sizes(values) -> str:
    return ",".join(map(str, values))


def _formations(text: str) -> tuple[int, ...]:
    try:
        values = tuple(sorted({int(v) for v in text.split(",") if v.strip()}))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated formation sizes, e.g. 6,7,8") from None
    if not values or any(v not in FORMATIONS for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: formation sizes must be among {FORMATIONS}")
    return values


def _densities(text: str) -> tuple[float, ...]:
    """'0,0.01,0.02,0.03' -> the CL-M curriculum, in the order given (LowLevelConfig checks it)."""
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected comma-separated densities, e.g. 0,0.01,0.02,0.03"
        ) from None


# ---------------------------------------------------------------------------- parsers
def add_parser(sub) -> None:
    """The subcommands lowlevel, distill, lowlevel-all and clm, in that order."""
    _lowlevel_parser(sub)
    _distill_parser(sub)
    _pipeline_parser(sub)
    _clm_parser(sub)


def _formation_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--formation",
        type=int,
        required=True,
        choices=FORMATIONS,
        metavar="C",
        help=f"formation size c, one of {FORMATIONS}",
    )


def _lowlevel_parser(sub) -> None:
    p = sub.add_parser(
        "lowlevel",
        help="one AT-M stage for one formation size",
        description="Train one AT-M stage (Algorithm 1): step 1 without obstacles, step 2 with "
        "obstacles (density 0.03), step 3 merging them and fine-tuning; --safe, "
        "--deviation, --response-time/--velocity-noise fine-tune the step-3 result. Step 3 "
        "and its fine-tunes read the earlier stages' state from --out, or start from a "
        "trained policy with --init-from (e.g. the shipped atm_c6_step3).",
        **subcommand_help(
            [
                "cefc-train lowlevel --formation 6 --step 1 --budget 15m       # Step 1 for c = 6, 15 minutes",
                "cefc-train lowlevel --formation 6 --step 3 --safe --init-from atm_c6_step3 --budget 100it",
                "cefc-train lowlevel --formation 6 --step 3 --backend mujoco --budget 20it   # on quadrotors",
            ],
            LOWLEVEL_DOCS,
        ),
    )
    _formation_arg(p)
    p.add_argument("--step", type=int, required=True, choices=(1, 2, 3), help="AT-M step")
    p.add_argument("--safe", action="store_true", help="AT-M-Safe (with --step 3)")
    p.add_argument(
        "--init-from",
        metavar="PATH|NAME",
        default=None,
        help="Step 3 stages: start the actor from this policy file (a path, or a name in the shipped "
        "policies/, e.g. atm_c6_step3) instead of the earlier stages' runs under --out; the critic "
        "starts fresh, as a policy file holds only the actor",
    )
    p.add_argument(
        "--deviation",
        type=float,
        default=_low("deviation"),
        metavar="M",
        help="train under sensing deviation M (m); with --step 3 this is AT-M-Robust, fine-tuned from "
        f"the Step 3 policy and written as atm_c<C>_robust (default {_low('deviation'):g})",
    )
    p.add_argument(
        "--deviation-sampling",
        choices=("fixed", "uniform"),
        default=_low("deviation_sampling"),
        help="fixed: every episode at --deviation; uniform: each env draws its episode's deviation from "
        f"[0, --deviation] (default {_low('deviation_sampling')})",
    )
    p.add_argument(
        "--response-time",
        type=float,
        default=_low("response_time"),
        metavar="S",
        help="velocity lag (s) of the particle world; about 0.1 matches the MuJoCo quadrotor (default "
        f"{_low('response_time'):g}, the paper's MPE). With --step 3 and no --deviation this is AT-M-Quad, "
        "fine-tuned from the Step 3 policy and written as atm_c<C>_quad",
    )
    p.add_argument(
        "--velocity-noise",
        type=float,
        default=_low("velocity_noise"),
        metavar="MPS",
        help="std (m/s) of per-step velocity kicks in the particle world, a real vehicle's tracking "
        f"error; about 0.1 matches the MuJoCo quadrotor (default {_low('velocity_noise'):g})",
    )
    p.add_argument(
        "--accel-max",
        type=float,
        default=_low("accel_max"),
        metavar="MPS2",
        help="the action bound (m/s^2 per axis) the stage trains at, recorded in its model card; our "
        f"choice, the paper states none (default {_low('accel_max'):g}; docs/px4_interface.md). "
        "--init-from may start from a policy trained at another bound",
    )
    p.add_argument(
        "--push-observer",
        type=float,
        default=_low("push_observer_s"),
        metavar="S",
        help="time constant (s) of the agent's push observer, which cancels the acceleration it feels "
        "beyond its own setpoint (the wind's push) within the action bound; recorded in the policy "
        f"file, and every evaluator flies the policy with it (default {_low('push_observer_s'):g}; 0 is none, "
        "the paper's memoryless agent; docs/px4_interface.md)",
    )
    p.add_argument(
        "--collision-margin",
        type=float,
        default=_low("collision_margin"),
        metavar="M",
        help="add M metres to both distances of the collision reward (delta_s 0.2, delta_a,c 0.5), so "
        f"the policy keeps more clearance than the paper's reward asks (default {_low('collision_margin'):g})",
    )
    p.add_argument(
        "--navigation-weight",
        type=float,
        default=None,
        metavar="W",
        help="omega_n of the low-level reward (the paper's 4). With --step 3 and no other fine-tune "
        "flag this is AT-M-Nav, fine-tuned from the Step 3 policy and written as atm_c<C>_nav, "
        "which keeps more of N on quadrotors (default: the paper's)",
    )
    p.add_argument(
        "--anchor-periods",
        type=int,
        default=_low("anchor_periods"),
        metavar="K",
        help="Step 3 fine-tunes: training episodes of K x 100 steps, the anchor redrawn every 100 steps "
        "(as Table VIII redraws it every 250), so the policy learns to leave a reached anchor for a "
        f"far one (default {_low('anchor_periods')}, the paper's)",
    )
    p.add_argument(
        "--straggler-fraction",
        type=float,
        default=_low("straggler_fraction"),
        metavar="P",
        help="Step 3 fine-tunes: in this fraction of the training episodes one agent starts 3-7 m from "
        "the others, out of their sight, so the policy learns to rejoin the group around obstacles "
        f"(default {_low('straggler_fraction'):g}, the paper's starts)",
    )
    p.add_argument(
        "--lidar",
        choices=tuple(_LIDAR.values()),
        default=_LIDAR[_low("lidar_sees_uavs")],
        help=f"what the LiDAR beams hit while training (default {_LIDAR[_low('lidar_sees_uavs')]}). obstacles: "
        "the stage is named <stage>_obstacle_lidar; with --step 1 it is the paper's Step 1, whose LiDAR "
        "reads nothing as it trains without obstacles. The policy file records it and the evaluators fly "
        "the policy with that LiDAR",
    )
    p.add_argument(
        "--density", type=float, default=None, help="training obstacle density per m^2 (default: the step's)"
    )
    m = MujocoTraining()
    p.add_argument(
        "--backend",
        choices=("particle", "mujoco"),
        default="particle",
        help="where the stage learns: particle (the paper's MPE-like world; default) or mujoco (AT-M-MuJoCo: "
        "a Step 3 fine-tune on MuJoCo quadrotors in wind, from --init-from, by default the shipped "
        "atm_c<C>_nav, written as atm_c<C>_mujoco; docs/train_lowlevel.md)",
    )
    p.add_argument(
        "--offboard",
        choices=("acceleration", "acceleration-assisted", "velocity"),
        default=None,
        help=f"--backend mujoco: the offboard interface flown while training (default {m.offboard}, the paper's)",
    )
    p.add_argument(
        "--wind-max",
        type=float,
        default=None,
        metavar="MPS",
        help="--backend mujoco: each episode's mean wind drawn from [0, MPS] m/s, direction uniform "
        f"(default {m.wind_max:g})",
    )
    p.add_argument(
        "--gust-speed",
        type=float,
        default=None,
        metavar="MPS",
        help="--backend mujoco: mean speed of each episode's gust, at a random time "
        f"(default {m.gust_speed:g}; 0: none)",
    )
    p.add_argument(
        "--gust-duration",
        type=float,
        default=None,
        metavar="S",
        help=f"--backend mujoco: seconds each gust lasts (default {m.gust_duration:g})",
    )
    p.add_argument(
        "--critic-warmup",
        type=int,
        default=None,
        metavar="K",
        help=f"--backend mujoco: the first K iterations train only the fresh critic (default {m.critic_warmup})",
    )
    p.add_argument(
        "--rollout-workers",
        type=int,
        default=None,
        metavar="W",
        help="--backend mujoco: processes collecting each iteration's episodes, each stepping --envs / W "
        "MuJoCo worlds with one thread (default 1: in the training process)",
    )
    p.add_argument(
        "--seeds",
        default=None,
        metavar="S1,S2,...",
        help="a sweep: train the stage once per seed, each in <out>/seed<k>/, its policy named "
        "<stage>_s<k> (e.g. atm_c6_step3_s1); instead of --seed, not with --install",
    )
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default=None,
        help="with --seeds: local trains the seeds one after another here (default); ray trains each as "
        "a Ray task, on the cluster at --address or on a Ray instance started here (docs/scaling.md)",
    )
    p.add_argument(
        "--address",
        default=None,
        metavar="HOST:PORT",
        help="with --executor ray: the head of a running Ray cluster (`ray start --head`)",
    )
    add_common_args(p, "lowlevel", "100it")
    add_ppo_args(p)
    p.set_defaults(seed=None)  # to tell an explicit --seed from none next to --seeds (_seed_sweep makes it 0)


def _distill_parser(sub) -> None:
    p = sub.add_parser(
        "distill",
        help="distill one student from the Step 3 (or Nav) teachers",
        description="Collect (observation, action) replay from each atm_c{c}_step3 (or, with "
        "--teacher nav, atm_c{c}_nav) teacher in --teachers-dir and train one student "
        "(hidden 256, MSE, Adam 1e-4, batch 600).",
        **subcommand_help(
            [
                "cefc-train distill --budget 20000it                 # the student of the shipped Step 3 teachers",
                "cefc-train distill --teacher nav --budget 20000it   # ... of the AT-M-Nav teachers",
            ],
            LOWLEVEL_DOCS,
        ),
    )
    p.add_argument(
        "--formations",
        type=_formations,
        default=_distill("formations"),
        help=f"teachers' sizes (default {_sizes(_distill('formations'))})",
    )
    p.add_argument(
        "--tuples",
        type=int,
        default=_distill("tuples_per_formation"),
        help=f"replay tuples per teacher (default {_distill('tuples_per_formation')})",
    )
    p.add_argument(
        "--teacher",
        choices=DISTILL_TEACHERS,
        default=_distill("teacher"),
        help="the teacher of each c: step3 (atm_c<C>_step3, the paper's AT-M; default) or nav "
        "(atm_c<C>_nav, AT-M-Nav, the evaluators' default low level)",
    )
    p.add_argument(
        "--teachers-dir",
        type=Path,
        default=paths.POLICIES_DIR,
        metavar="DIR",
        help=f"folder of the atm_c<C>_step3 teachers (default the shipped {paths.POLICIES_DIR})",
    )
    add_common_args(p, "distill", "20000it")


def _pipeline_parser(sub) -> None:
    p = sub.add_parser(
        "lowlevel-all",
        help="the whole low-level pipeline",
        description="AT-M steps 1-3 and Safe for every formation, then distillation of the "
        "pipeline's own Step 3 policies; one --budget split over the stages (see "
        "cefc_mj.train.pipeline).",
        **subcommand_help(
            ["cefc-train lowlevel-all --budget 80m --workers 2   # every c, two formations side by side"],
            LOWLEVEL_DOCS,
        ),
    )
    p.add_argument(
        "--formations", type=_formations, default=FORMATIONS, help=f"formation sizes (default {_sizes(FORMATIONS)})"
    )
    p.add_argument(
        "--tuples",
        type=int,
        default=_distill("tuples_per_formation"),
        help=f"distillation replay tuples per teacher (default {_distill('tuples_per_formation')})",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help=f"processes training formations side by side, one torch thread each, 1 to {len(FORMATIONS)} (default 1)",
    )
    add_common_args(p, "lowlevel-all", "80m")
    add_ppo_args(p)


def _clm_parser(sub) -> None:
    p = sub.add_parser(
        "clm",
        help="the CL-M baseline of Table III for one formation size",
        description="CL-M, the paper's curriculum-learning baseline: one MAPPO run of the AT-M "
        "network from random weights while the obstacle density rises through "
        "--curriculum, each density for an equal share of --budget; written as "
        "clm_c<C>. Not part of lowlevel-all.",
        **subcommand_help(
            ["cefc-train clm --formation 6 --budget 1404s   # densities 0, 0.01, 0.02, 0.03 in turn"],
            LOWLEVEL_DOCS,
        ),
    )
    _formation_arg(p)
    p.add_argument(
        "--curriculum",
        type=_densities,
        default=CLM_CURRICULUM,
        metavar="D1,D2,...",
        help="obstacle densities per m^2, non-decreasing, trained in turn for equal shares of the "
        f"budget (default {','.join(f'{d:g}' for d in CLM_CURRICULUM)})",
    )
    add_common_args(p, "clm", "100it")
    add_ppo_args(p)


# ---------------------------------------------------------------------------- checks
def _check_workers(args) -> None:
    if not 1 <= args.workers <= len(FORMATIONS):
        raise ConfigError(f"--workers {args.workers}: must be an integer in [1, {len(FORMATIONS)}]")


def _seed_sweep(args):
    """lowlevel's --seeds, --executor, --address: (seeds, ExecutorConfig) for a sweep, None for a
    single run (then --executor/--address are errors). Sets args.seed (None when not given) to 0."""
    from cefc_mj.executors import ExecutorConfig

    seed_given, args.seed = args.seed is not None, 0 if args.seed is None else args.seed
    if args.seeds is None:
        for flag, value in (("--executor", args.executor), ("--address", args.address)):
            if value is not None:
                raise ConfigError(f"{flag} {value}: runs the seeds of a sweep; add --seeds, e.g. --seeds 0,1,2")
        return None
    if seed_given:
        raise ConfigError(f"--seed {args.seed}: give either --seed (one run) or --seeds {args.seeds} (a sweep)")
    if args.install:
        raise ConfigError(
            "--install: a --seeds sweep exports one policy per seed (<stage>_s<k>); install the one "
            "you choose with a single run, or copy it"
        )
    from cefc_mj.train.sweep import parse_seeds

    seeds = parse_seeds(args.seeds)
    executor = ExecutorConfig(kind=args.executor or "local", address=args.address)
    executor.validate()
    return seeds, executor


# ---------------------------------------------------------------------------- runs
def _print_lowlevel_card(card: dict, policies_dir: Path) -> None:
    print(
        f"{card['name']}: {card['iterations']} iterations, {card['agent_steps']} agent-steps, "
        f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    )
    o = card["table3"]["ours"]
    print(
        f"Table III protocol (density 0.05): R_L {o['R_L']:.2f}/step  F {o['F']:.2f}  N {o['N']:.2f}  C {o['C']:.2f}%"
    )


def _train_sweep(args, cfg: LowLevelConfig, sweep, policies_dir: Path, command: str) -> list[dict]:
    """`lowlevel --seeds`: the stage once per seed, each in <out>/seed<k>/; returns the cards in seed order."""
    from cefc_mj.train.sweep import plan_seeds, sweep_executor, train_seeds

    seeds, executor = sweep
    runs = plan_seeds(
        cfg,
        seeds,
        args.out,
        policies_dir,
        resume=args.resume,
        init_from=args.init_from,
        command=command,
        show_progress=not args.no_progress,
    )
    executor, _ = sweep_executor(runs, executor)
    where = "one after another in this process" if executor.kind == "local" else executor.describe()
    print(
        f"{cfg.name}: seeds {','.join(map(str, seeds))} {where}; run folders {args.out}/seed<k>/{cfg.name}, "
        f"policies {policies_dir}/{cfg.name}_s<k>.pt",
        flush=True,
    )
    return train_seeds(runs, executor, on_done=lambda card: _print_lowlevel_card(card, policies_dir))


_MUJOCO_FLAGS = {
    "offboard": "--offboard",
    "wind_max": "--wind-max",
    "gust_speed": "--gust-speed",
    "gust_duration": "--gust-duration",
    "rollout_workers": "--rollout-workers",
    "critic_warmup": "--critic-warmup",
}
"""MujocoTraining's fields and the lowlevel flags that set them (only with --backend mujoco)."""


def _mujoco_training(args) -> MujocoTraining | None:
    """--backend mujoco and its flags as a MujocoTraining (None for the particle world); its flags
    without --backend mujoco are an error, not silently ignored. Sets the default --init-from."""
    given = {field: getattr(args, field) for field in _MUJOCO_FLAGS if getattr(args, field) is not None}
    if args.backend != "mujoco":
        if given:
            flag = _MUJOCO_FLAGS[next(iter(given))]
            raise ConfigError(f"{flag}: a setting of training in MuJoCo; add --backend mujoco")
        return None
    if args.init_from is None:
        args.init_from = f"atm_c{args.formation}_nav"
    return MujocoTraining(**given)


def _run_lowlevel(args, budget: Budget, command: str | None) -> tuple[list[dict], Path]:
    sweep = _seed_sweep(args)  # --seeds/--executor/--address checked; None: a single run
    mujoco = _mujoco_training(args)
    cfg = LowLevelConfig(
        formation=args.formation,
        step=args.step,
        safe=args.safe,
        deviation=args.deviation,
        deviation_sampling=args.deviation_sampling,
        response_time=args.response_time,
        velocity_noise=args.velocity_noise,
        accel_max=args.accel_max,
        push_observer_s=args.push_observer,
        collision_margin=args.collision_margin,
        navigation_weight=args.navigation_weight,
        anchor_periods=args.anchor_periods,
        straggler_fraction=args.straggler_fraction,
        lidar_sees_uavs=args.lidar == _LIDAR[True],
        budget=budget,
        seed=args.seed,
        obstacle_density=args.density,
        mujoco=mujoco,
        ppo=ppo_from(args),
    )
    policies_dir = check_destinations(args)
    if sweep is not None:  # one run per seed, on an executor (cefc_mj/train/sweep.py); --install was refused
        return _train_sweep(args, cfg, sweep, policies_dir, command), policies_dir
    from cefc_mj.train.lowlevel import train_lowlevel

    card = train_lowlevel(
        cfg,
        args.out,
        policies_dir,
        resume=args.resume,
        show_progress=not args.no_progress,
        init_from=args.init_from,
        command=command,
    )
    _print_lowlevel_card(card, policies_dir)
    return [card], policies_dir


def _run_clm(args, budget: Budget, command: str | None) -> tuple[list[dict], Path]:
    cfg = LowLevelConfig(
        formation=args.formation,
        step=1,
        curriculum=args.curriculum,
        budget=budget,
        seed=args.seed,
        ppo=ppo_from(args),
    )
    policies_dir = check_destinations(args)
    from cefc_mj.train.lowlevel import train_lowlevel

    card = train_lowlevel(
        cfg, args.out, policies_dir, resume=args.resume, show_progress=not args.no_progress, command=command
    )
    phases = ", ".join(f"{p['density']:g}: {p['iterations']} it" for p in card["curriculum"]["phases"])
    print(
        f"{card['name']}: {card['iterations']} iterations ({phases}), {card['agent_steps']} agent-steps, "
        f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    )
    o = card["table3"]["ours"]
    print(
        f"Table III protocol (density 0.05): R_L {o['R_L']:.2f}/step  F {o['F']:.2f}  N {o['N']:.2f}  C {o['C']:.2f}%"
    )
    return [card], policies_dir


def _run_distill(args, budget: Budget, command: str | None) -> tuple[list[dict], Path]:
    cfg = DistillConfig(
        budget=budget,
        formations=args.formations,
        tuples_per_formation=args.tuples,
        seed=args.seed,
        teacher=args.teacher,
    )
    policies_dir = check_destinations(args)
    from cefc_mj.train.distill import train_student

    card = train_student(
        cfg,
        policies_dir,
        args.out,
        resume=args.resume,
        show_progress=not args.no_progress,
        teachers_dir=args.teachers_dir,
        command=command,
    )
    print(
        f"atm_student: {card['gradient_steps']} steps -> {policies_dir / 'atm_student.pt'}; held-out relative "
        "error " + ", ".join(f"c={k.split('c')[-1]}: {v:.3f}" for k, v in card["held_out_error"].items() if "rel" in k)
    )
    return [card], policies_dir


def _run_pipeline(args, budget: Budget, command: str | None) -> tuple[list[dict], Path]:
    from cefc_mj.train.pipeline import plan, run_pipeline

    _check_workers(args)
    ppo = ppo_from(args)
    plan(budget, args.formations, args.seed, ppo, args.tuples, args.workers)  # validates every stage's config
    policies_dir = check_destinations(args)
    cards = run_pipeline(
        budget,
        args.out,
        policies_dir,
        seed=args.seed,
        resume=args.resume,
        formations=args.formations,
        ppo=ppo,
        show_progress=not args.no_progress,
        tuples_per_formation=args.tuples,
        workers=args.workers,
        command=command,
    )
    return cards, policies_dir


def run(args, budget: Budget, command: str | None = None) -> list[dict]:
    """Check the configs and folders (before torch and numba are imported), train, export and, with
    --install, install; returns the model cards."""
    runner = {"lowlevel": _run_lowlevel, "clm": _run_clm, "distill": _run_distill, "lowlevel-all": _run_pipeline}
    cards, policies_dir = runner[args.command](args, budget, command)
    if args.install:  # never with --seeds (_seed_sweep refuses it)
        install([card["name"] for card in cards], policies_dir)
    return cards
