"""`cefc-train`: train the low-level policies (AT-M steps, AT-M-Safe/Robust/Quad, the distilled student,
the CL-M baseline).

    cefc-train lowlevel --formation 6 --step 1 --budget 15m
    cefc-train lowlevel --formation 6 --step 3 --safe --init-from atm_c6_step3 --budget 100it
    cefc-train distill --budget 20000it
    cefc-train lowlevel-all --budget 80m            # the whole pipeline
    cefc-train clm --formation 6 --budget 1404s     # the CL-M baseline (curriculum 0,0.01,0.02,0.03)
    cefc-train highlevel --variant consmac-a --budget 75it   # the high level (Algorithm 2) over atm_student
    cefc-train adversary                                     # the PPO adversary (imitation, critic warm-up)
    cefc-train adversary-ddpg --budget 150it                 # the DDPG adversary (Table VI)

Everything a run writes goes under --out (default runs/<command>, relative to the current folder):
run folders (config, CSV and TensorBoard logs, resumable state) and the exported policies with their
model cards in <out>/policies/ (or --policies-dir). The shipped policies/ folder is written only
with --install, after a successful run. --resume continues an interrupted run from its last
checkpoint. Invalid input prints one line and exits with status 2 before anything is written.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.fileio import can_write_in
from cefc_mj.task.config import RULE_TEAMS
from cefc_mj.train.config import (
    CLM_CURRICULUM,
    DISTILL_TEACHERS,
    FORMATIONS,
    Budget,
    DistillConfig,
    LowLevelConfig,
    PPOConfig,
)

EXIT_USAGE = 2

_FLAG_OF_FIELD = {
    "n_envs": "--envs",
    "epochs": "--epochs",
    "minibatches": "--minibatches",
    "lr": "--lr",
    "update_threads": "--threads",
    "seed": "--seed",
    "obstacle_density": "--density",
    "deviation": "--deviation",
    "deviation_sampling": "--deviation-sampling",
    "response_time": "--response-time",
    "velocity_noise": "--velocity-noise",
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
}
"""Config fields set from a flag: their validation errors name the flag the user typed."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (the usage is in --help)."""

    def error(self, message: str):
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


class _VersionAction(argparse.Action):
    """--version, computed only when asked (it imports mujoco, numba and torch)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from cefc_mj.provenance import version_line

        print(version_line("cefc-train"))
        parser.exit()


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


def _common(p: argparse.ArgumentParser, command: str, default_budget: str) -> None:
    p.add_argument("--seed", type=int, default=0, help="seed of networks, sampling and episodes (default 0)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("runs") / command,
        help=f"where the run writes: run folders (logs, TensorBoard, resumable state) and, in "
        f"<out>/policies/, the exported policies (default runs/{command})",
    )
    p.add_argument(
        "--policies-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="where exported policies and model cards go instead of <out>/policies/",
    )
    p.add_argument(
        "--install",
        action="store_true",
        help=f"after a successful run, copy the exported policies and cards into the shipped "
        f"{paths.POLICIES_DIR} (replacing files of the same name)",
    )
    p.add_argument("--resume", action="store_true", help="continue the run(s) found under --out")
    p.add_argument(
        "--budget",
        default=default_budget,
        help=f"iterations ('40', '40it') or wall-clock time ('90s', '15m', '1.5h') (default {default_budget})",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for log files)")


def _ppo_args(p: argparse.ArgumentParser) -> None:
    d = PPOConfig()
    p.add_argument("--envs", type=int, default=d.n_envs, help=f"parallel envs (default {d.n_envs})")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"PPO epochs per iteration (default {d.epochs})")
    p.add_argument(
        "--minibatches", type=int, default=d.minibatches, help=f"minibatches per epoch (default {d.minibatches})"
    )
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument(
        "--credit",
        choices=("agent", "team"),
        default=d.collision_credit,
        help=f"collision credit: per agent or the paper's team reward (default {d.collision_credit})",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=d.update_threads,
        help=f"torch threads of the PPO update; 1 when several trainings share the CPU (default {d.update_threads})",
    )


def _ppo_from(args) -> PPOConfig:
    ppo = PPOConfig(
        n_envs=args.envs,
        epochs=args.epochs,
        minibatches=args.minibatches,
        lr=args.lr,
        collision_credit=args.credit,
        update_threads=args.threads,
    )
    ppo.validate()
    return ppo


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="cefc-train",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--version", action=_VersionAction, help="print the version, code digest and libraries")
    sub = parser.add_subparsers(
        dest="command", required=True, metavar="{lowlevel,distill,lowlevel-all,clm,highlevel,adversary,adversary-ddpg}"
    )

    p = sub.add_parser(
        "lowlevel",
        help="one AT-M stage for one formation size",
        description="Train one AT-M stage (Algorithm 1): step 1 without obstacles, step 2 with "
        "obstacles (density 0.03), step 3 merging them and fine-tuning; --safe, "
        "--deviation, --response-time/--velocity-noise fine-tune the step-3 result. Step 3 "
        "and its fine-tunes read the earlier stages' state from --out, or start from a "
        "trained policy with --init-from (e.g. the shipped atm_c6_step3).",
    )
    p.add_argument(
        "--formation",
        type=int,
        required=True,
        choices=FORMATIONS,
        metavar="C",
        help=f"formation size c, one of {FORMATIONS}",
    )
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
        default=0.0,
        metavar="M",
        help="train under sensing deviation M (m); with --step 3 this is AT-M-Robust, fine-tuned from "
        "the Step 3 policy and written as atm_c<C>_robust (default 0)",
    )
    p.add_argument(
        "--deviation-sampling",
        choices=("fixed", "uniform"),
        default="fixed",
        help="fixed: every episode at --deviation; uniform: each env draws its episode's deviation from "
        "[0, --deviation] (default fixed)",
    )
    p.add_argument(
        "--response-time",
        type=float,
        default=0.0,
        metavar="S",
        help="velocity lag (s) of the particle world; about 0.1 matches the MuJoCo quadrotor (default 0, "
        "the paper's MPE). With --step 3 and no --deviation this is AT-M-Quad, fine-tuned from the "
        "Step 3 policy and written as atm_c<C>_quad",
    )
    p.add_argument(
        "--velocity-noise",
        type=float,
        default=0.0,
        metavar="MPS",
        help="std (m/s) of per-step velocity kicks in the particle world, a real vehicle's tracking "
        "error; about 0.1 matches the MuJoCo quadrotor (default 0)",
    )
    p.add_argument(
        "--collision-margin",
        type=float,
        default=0.0,
        metavar="M",
        help="add M metres to both distances of the collision reward (delta_s 0.2, delta_a,c 0.5), so "
        "the policy keeps more clearance than the paper's reward asks (default 0)",
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
        default=1,
        metavar="K",
        help="Step 3 fine-tunes: training episodes of K x 100 steps, the anchor redrawn every 100 steps "
        "(as Table VIII redraws it every 250), so the policy learns to leave a reached anchor for a "
        "far one (default 1, the paper's)",
    )
    p.add_argument(
        "--straggler-fraction",
        type=float,
        default=0.0,
        metavar="P",
        help="Step 3 fine-tunes: in this fraction of the training episodes one agent starts 3-7 m from "
        "the others, out of their sight, so the policy learns to rejoin the group around obstacles "
        "(default 0, the paper's starts)",
    )
    p.add_argument(
        "--lidar",
        choices=("obstacles+uavs", "obstacles"),
        default="obstacles+uavs",
        help="what the LiDAR beams hit while training (default obstacles+uavs). obstacles: the stage "
        "is named <stage>_obstacle_lidar; with --step 1 it is the paper's Step 1, whose LiDAR reads "
        "nothing as it trains without obstacles. The policy file records it and the evaluators fly "
        "the policy with that LiDAR",
    )
    p.add_argument(
        "--density", type=float, default=None, help="training obstacle density per m^2 (default: the step's)"
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
    _common(p, "lowlevel", "100it")
    _ppo_args(p)
    p.set_defaults(seed=None)  # to tell an explicit --seed from none next to --seeds (_seed_sweep makes it 0)

    p = sub.add_parser(
        "distill",
        help="distill one student from the Step 3 (or Nav) teachers",
        description="Collect (observation, action) replay from each atm_c{c}_step3 (or, with "
        "--teacher nav, atm_c{c}_nav) teacher in --teachers-dir and train one student "
        "(hidden 256, MSE, Adam 1e-4, batch 600).",
    )
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="teachers' sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="replay tuples per teacher (default 60000)")
    p.add_argument(
        "--teacher",
        choices=DISTILL_TEACHERS,
        default="step3",
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
    _common(p, "distill", "20000it")

    p = sub.add_parser(
        "lowlevel-all",
        help="the whole low-level pipeline",
        description="AT-M steps 1-3 and Safe for every formation, then distillation of the "
        "pipeline's own Step 3 policies; one --budget split over the stages (see "
        "cefc_mj.train.pipeline).",
    )
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="formation sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="distillation replay tuples per teacher (default 60000)")
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help=f"processes training formations side by side, one torch thread each, 1 to {len(FORMATIONS)} (default 1)",
    )
    _common(p, "lowlevel-all", "80m")
    _ppo_args(p)

    p = sub.add_parser(
        "clm",
        help="the CL-M baseline of Table III for one formation size",
        description="CL-M, the paper's curriculum-learning baseline: one MAPPO run of the AT-M "
        "network from random weights while the obstacle density rises through "
        "--curriculum, each density for an equal share of --budget; written as "
        "clm_c<C>. Not part of lowlevel-all.",
    )
    p.add_argument(
        "--formation",
        type=int,
        required=True,
        choices=FORMATIONS,
        metavar="C",
        help=f"formation size c, one of {FORMATIONS}",
    )
    p.add_argument(
        "--curriculum",
        type=_densities,
        default=CLM_CURRICULUM,
        metavar="D1,D2,...",
        help="obstacle densities per m^2, non-decreasing, trained in turn for equal shares of the "
        f"budget (default {','.join(f'{d:g}' for d in CLM_CURRICULUM)})",
    )
    _common(p, "clm", "100it")
    _ppo_args(p)
    _highlevel_parser(sub)
    _adversary_parser(sub)
    _adversary_ddpg_parser(sub)
    return parser


def _names(text: str) -> tuple[str, ...]:
    """A comma-separated list of names (argparse type)."""
    names = tuple(part.strip() for part in text.split(","))
    if not all(names):
        raise argparse.ArgumentTypeError(f"{text!r}: a comma-separated list of names, none empty")
    return names


def _population_game_args(p: argparse.ArgumentParser) -> None:
    """The flags both adversary trainers share: the population of teams, the game and the reward."""
    p.add_argument(
        "--teams",
        type=_names,
        default=None,
        metavar="NAME,...",
        help="the population: trained high levels (names or files) and rule teams ("
        + ", ".join(RULE_TEAMS)
        + "); default every shipped method over its training seeds and "
        "every rule team",
    )
    p.add_argument(
        "--teams-per-iteration",
        type=int,
        default=None,
        metavar="K",
        help="games per iteration, each with a team drawn from the population (default 4; must divide --envs)",
    )
    p.add_argument(
        "--low-level",
        default=None,
        metavar="NAME|PATH|per-group",
        help="the UAV team's low level (default atm_student)",
    )
    p.add_argument(
        "--action",
        choices=("velocity", "heading", "acceleration"),
        default=None,
        help="what the actor outputs: its heading at top speed, the velocity it wants, or the "
        "acceleration (default heading)",
    )
    p.add_argument(
        "--alert-weight",
        type=float,
        default=None,
        metavar="W",
        help="reward per step for the share of UAVs within the alert distance (default 1)",
    )
    p.add_argument(
        "--progress-weight",
        type=float,
        default=None,
        metavar="W",
        help="reward per metre the step approached the nearest group (default 10)",
    )
    p.add_argument(
        "--collision-weight",
        type=float,
        default=None,
        metavar="W",
        help="penalty per step inside an obstacle (default 30)",
    )
    p.add_argument(
        "--density",
        type=float,
        default=None,
        dest="obstacle_density",
        metavar="D",
        help="obstacle density per m^2 (default 0.03)",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        metavar="N",
        help="episodes evaluated for the model card (default 20; 0 skips)",
    )


def _adversary_parser(sub) -> None:
    """`cefc-train adversary`; flags left out keep AdversaryConfig's defaults (cefc_mj/train/adversary.py)."""
    p = sub.add_parser(
        "adversary",
        help="the PPO adversary (the paper's predator) against a population of UAV teams",
        description="Single-agent PPO with the low level's network shape: chase the nearest group "
        "of >= 3 UAVs, avoid obstacles, against a population of teams (trained high "
        "levels and rule-driven teams, one drawn per game) over a trained low level. "
        "Written as adversary_ppo[_seed<k>].",
    )
    _population_game_args(p)
    p.add_argument(
        "--imitation-episodes",
        type=int,
        default=None,
        metavar="N",
        help="before PPO, imitate the nearest-group rule on N episodes per round of the population's "
        "games (default 200; 0: PPO from random weights)",
    )
    p.add_argument(
        "--imitation-steps",
        type=int,
        default=None,
        metavar="N",
        help="Adam steps of that imitation, over all rounds (default 8000)",
    )
    p.add_argument(
        "--imitation-rounds",
        type=int,
        default=None,
        metavar="K",
        help="DAgger rounds: the first flies the rule, later ones the actor, labelled by the rule (default 8)",
    )
    p.add_argument(
        "--init-log-std",
        type=float,
        default=None,
        metavar="S",
        help="initial log-std of the actor's Gaussian, in its output units (default -0.5)",
    )
    p.add_argument(
        "--imitation-rule",
        default=None,
        metavar="RULE",
        help="the rule imitated before PPO: nearest_group_strike (default: the nearest group of >= 3, "
        "the nearest UAV within 3 m), nearest_group, r_nearest or r_largest",
    )
    p.add_argument(
        "--critic-warmup",
        type=int,
        default=None,
        metavar="N",
        help="first PPO iterations in which only the critic learns (default 20)",
    )
    p.add_argument("--envs", type=int, default=None, dest="n_envs", metavar="N", help="parallel envs (default 20)")
    p.add_argument("--epochs", type=int, default=None, metavar="N", help="PPO epochs per iteration (default 5)")
    p.add_argument("--lr", type=float, default=None, metavar="LR", help="Adam learning rate (default 3e-4)")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        dest="update_threads",
        metavar="N",
        help="torch threads of the update (default 1)",
    )
    _common(p, "adversary", "20it")


def _adversary_ddpg_parser(sub) -> None:
    """`cefc-train adversary-ddpg`; flags left out keep DDPGAdversaryConfig's defaults
    (cefc_mj/train/adversary_ddpg.py)."""
    p = sub.add_parser(
        "adversary-ddpg",
        help="the DDPG adversary (Table VI) against a population of UAV teams",
        description="DDPG (Lillicrap et al.) with the PPO adversary's actor network, game, population "
        "of teams and reward, learning from scratch (no imitation): Gaussian exploration "
        "noise, a replay of transitions, a Q critic and target networks. Written as "
        "adversary_ddpg[_seed<k>]; Table VI (cefc-eval --protocol table6) flies it once "
        "it is in the policies folder (--install).",
    )
    _population_game_args(p)
    p.add_argument(
        "--envs",
        type=int,
        default=None,
        dest="n_envs",
        metavar="N",
        help="parallel envs, one 400-step episode each per iteration (default 20)",
    )
    p.add_argument(
        "--replay",
        type=int,
        default=None,
        dest="replay_capacity",
        metavar="N",
        help="replay capacity in transitions, a ring (default 100000)",
    )
    p.add_argument(
        "--batch-size", type=int, default=None, metavar="N", help="transitions per gradient step (default 256)"
    )
    p.add_argument(
        "--learning-starts",
        type=int,
        default=None,
        metavar="N",
        help="transitions in the replay before the updates start; until then iterations fly uniform "
        "random actions (default 8000)",
    )
    p.add_argument(
        "--updates",
        type=int,
        default=None,
        dest="updates_per_iteration",
        metavar="N",
        help="gradient steps after each iteration (default 1000)",
    )
    p.add_argument("--actor-lr", type=float, default=None, metavar="LR", help="actor Adam learning rate (default 1e-4)")
    p.add_argument(
        "--critic-lr", type=float, default=None, metavar="LR", help="critic Adam learning rate (default 1e-3)"
    )
    p.add_argument(
        "--tau",
        type=float,
        default=None,
        metavar="T",
        help="Polyak rate of the target networks per gradient step (default 0.005)",
    )
    p.add_argument(
        "--gamma",
        type=float,
        default=None,
        metavar="G",
        help="discount per 0.1 s step (default 0.95, the PPO adversary's)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=None,
        dest="exploration_noise",
        metavar="STD",
        help="std of the Gaussian exploration noise on the actor's output (velocity: a share of top "
        "speed) (default 0.2)",
    )
    p.add_argument("--threads", type=int, default=None, metavar="N", help="torch threads of the updates (default 1)")
    _common(p, "adversary-ddpg", "150it")


def _highlevel_parser(sub) -> None:
    """`cefc-train highlevel`; flags left out keep HighLevelConfig's defaults (cefc_mj/train/highlevel.py)."""
    p = sub.add_parser(
        "highlevel",
        help="the high level (ConsMAC + anchor selector) over a trained low level",
        description="Algorithm 2: MAPPO anchor selection every 10 low-level steps, ConsMAC trained "
        "alternately by supervised learning; pre-training with a navigation-only low "
        "level, then fine-tuning with --low-level. Written as cihrl_<variant>.",
    )
    p.add_argument(
        "--variant",
        choices=("consmac-a", "consmac-o", "mappo", "tarmac"),
        default=None,
        help="consmac-a (default), consmac-o, mappo (no communication), tarmac (messages trained end to end by RL)",
    )
    p.add_argument(
        "--ablation",
        choices=("none", "wo-com", "wo-mem", "wo-de", "wt-rl", "consmac-g"),
        default=None,
        help="one of the paper's Fig. 7 ablations of ConsMAC (consmac-a/-o only; default none): wo-com (no "
        "message received), wo-mem (no GRU memory), wo-de (no distance encoder), wt-rl (the RL loss also "
        "trains ConsMAC), consmac-g (the estimate g_hat is sent as the message). Written as "
        "cihrl_<variant>_<ablation>",
    )
    p.add_argument(
        "--low-level",
        default=None,
        metavar="NAME|PATH|per-group",
        help="fine-tuning low level: a policy name or file (default atm_student) or per-group "
        "(atm_c<C>_step3 by group size)",
    )
    p.add_argument(
        "--pretrain-share",
        type=float,
        default=None,
        metavar="F",
        help="share of the budget with the navigation-only low level (default 2/3, the paper's 1000 of "
        "1500 episodes; 0: direct training)",
    )
    p.add_argument(
        "--density",
        type=float,
        default=None,
        dest="obstacle_density",
        metavar="D",
        help="obstacle density per m^2 (default 0.03)",
    )
    p.add_argument(
        "--adversary",
        default=None,
        metavar="RULE|NAME|PATH",
        help="the game's adversary: a rule (nearest_group, r_nearest, r_largest, none) or a trained "
        "adversary's policy name or file (default adversary_ppo, the shipped PPO adversary)",
    )
    p.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        metavar="N",
        help="low-level steps per episode, a multiple of 10 (default 400)",
    )
    p.add_argument(
        "--consmac-every",
        type=int,
        default=None,
        metavar="IT",
        help="train ConsMAC after every IT iterations (default 1)",
    )
    p.add_argument(
        "--consmac-steps",
        type=int,
        default=None,
        metavar="N",
        help="Adam steps per ConsMAC round (default 200; the paper's 5000)",
    )
    p.add_argument("--consmac-batch", type=int, default=None, metavar="N", help="ConsMAC batch (default 2048)")
    p.add_argument(
        "--consmac-lr", type=float, default=None, metavar="LR", help="ConsMAC learning rate (default 1e-4, the paper's)"
    )
    p.add_argument(
        "--replay",
        type=int,
        default=None,
        metavar="N",
        dest="replay_capacity",
        help="ConsMAC replay capacity in agent-decisions (default 50000)",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        metavar="N",
        help="episodes evaluated for the model card (default 20; 0 skips)",
    )
    p.add_argument("--envs", type=int, default=None, dest="n_envs", metavar="N", help="parallel envs (default 20)")
    p.add_argument("--epochs", type=int, default=None, metavar="N", help="PPO epochs per iteration (default 15)")
    p.add_argument("--minibatches", type=int, default=None, metavar="N", help="minibatches per epoch (default 4)")
    p.add_argument(
        "--lr", type=float, default=None, metavar="LR", help="Adam learning rate of selector and critic (default 1e-4)"
    )
    p.add_argument(
        "--entropy", type=float, default=None, dest="entropy_coef", metavar="C", help="entropy bonus (default 0.01)"
    )
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        dest="update_threads",
        metavar="N",
        help="torch threads of the updates and ConsMAC (default 2)",
    )
    _common(p, "highlevel", "75it")


# ---------------------------------------------------------------------------- checks
def _check_folder(flag: str, folder: Path) -> None:
    """`folder` exists or can be made (its nearest existing ancestor is a writable folder)."""
    folder = folder.absolute()
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f"{flag} {folder}: {probe} is a file, not a folder")
    if not can_write_in(probe):
        raise ConfigError(f"{flag} {folder}: {probe} is not writable")


def _is_shipped(folder: Path) -> bool:
    return folder.resolve() == paths.POLICIES_DIR.resolve()


def check_destinations(args) -> Path:
    """Checks --out, --policies-dir and --install before anything is written; returns the folder
    the exported policies go to."""
    out = args.out
    policies_dir = args.policies_dir if args.policies_dir is not None else out / "policies"
    _check_folder("--out", out)
    shipped = paths.POLICIES_DIR.resolve()
    if out.resolve() == shipped or shipped in out.resolve().parents:
        raise ConfigError(
            f"--out {out}: inside the shipped policies folder {paths.POLICIES_DIR}; choose another folder"
        )
    if _is_shipped(policies_dir) and not args.install:
        raise ConfigError(f"--policies-dir {policies_dir}: the shipped policies folder is written only with --install")
    _check_folder("--policies-dir", policies_dir)
    if args.install:
        _check_folder("--install", paths.POLICIES_DIR)
    return policies_dir


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


def _as_flag_error(e: ConfigError) -> ConfigError:
    """'n_envs=0: must be ...' from a config -> '--envs 0: must be ...', the flag the user typed."""
    from cefc_mj.train.config import flag_error

    return flag_error(e, _FLAG_OF_FIELD)


# ---------------------------------------------------------------------------- commands
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


def run(args, command: str | None = None) -> list[dict]:
    """Validate the arguments, train, export (and install); returns the model cards."""
    budget = Budget.parse(args.budget)
    show = not args.no_progress
    # Configs and folders are checked before the training modules (torch, numba) are imported.
    if args.command == "lowlevel":
        sweep = _seed_sweep(args)  # --seeds/--executor/--address checked; None: a single run
        cfg = LowLevelConfig(
            formation=args.formation,
            step=args.step,
            safe=args.safe,
            deviation=args.deviation,
            deviation_sampling=args.deviation_sampling,
            response_time=args.response_time,
            velocity_noise=args.velocity_noise,
            collision_margin=args.collision_margin,
            navigation_weight=args.navigation_weight,
            anchor_periods=args.anchor_periods,
            straggler_fraction=args.straggler_fraction,
            lidar_sees_uavs=args.lidar == "obstacles+uavs",
            budget=budget,
            seed=args.seed,
            obstacle_density=args.density,
            ppo=_ppo_from(args),
        )
        policies_dir = check_destinations(args)
        if sweep is not None:  # one run per seed, on an executor (cefc_mj/train/sweep.py); --install was refused
            return _train_sweep(args, cfg, sweep, policies_dir, command)
        from cefc_mj.train.lowlevel import train_lowlevel

        card = train_lowlevel(
            cfg,
            args.out,
            policies_dir,
            resume=args.resume,
            show_progress=show,
            init_from=args.init_from,
            command=command,
        )
        _print_lowlevel_card(card, policies_dir)
        cards = [card]
    elif args.command == "clm":
        cfg = LowLevelConfig(
            formation=args.formation,
            step=1,
            curriculum=args.curriculum,
            budget=budget,
            seed=args.seed,
            ppo=_ppo_from(args),
        )
        policies_dir = check_destinations(args)
        from cefc_mj.train.lowlevel import train_lowlevel

        card = train_lowlevel(cfg, args.out, policies_dir, resume=args.resume, show_progress=show, command=command)
        phases = ", ".join(f"{p['density']:g}: {p['iterations']} it" for p in card["curriculum"]["phases"])
        print(
            f"{card['name']}: {card['iterations']} iterations ({phases}), {card['agent_steps']} agent-steps, "
            f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
        )
        o = card["table3"]["ours"]
        print(
            f"Table III protocol (density 0.05): R_L {o['R_L']:.2f}/step  F {o['F']:.2f}  "
            f"N {o['N']:.2f}  C {o['C']:.2f}%"
        )
        cards = [card]
    elif args.command in ("highlevel", "adversary", "adversary-ddpg"):  # own policy formats, so own --install
        from cefc_mj.train.model_card import install_policy

        if args.command == "highlevel":
            from cefc_mj.nn.highlevel_policy import load_highlevel_policy as load
            from cefc_mj.train.highlevel import config_from_args, summary_lines, train_highlevel as train
        elif args.command == "adversary":
            from cefc_mj.nn.adversary_policy import load_adversary_policy as load
            from cefc_mj.train.adversary import config_from_args, summary_lines, train_adversary as train
        else:
            from cefc_mj.nn.adversary_policy import load_adversary_policy as load
            from cefc_mj.train.adversary_ddpg import config_from_args, summary_lines, train_ddpg_adversary as train
        cfg = config_from_args(args, budget)
        policies_dir = check_destinations(args)
        card = train(cfg, args.out, policies_dir, resume=args.resume, show_progress=show, command=command)
        print("\n".join(summary_lines(card, policies_dir)))
        if args.install:
            for name in filter(None, (card["name"], card.get("wo_ft"))):  # wo_ft: the high level's pre-training
                target = install_policy(policies_dir / f"{name}.pt", paths.POLICIES_DIR, load=load)
                print(f"installed {name} -> {target}")
        return [card]
    elif args.command == "distill":
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
            show_progress=show,
            teachers_dir=args.teachers_dir,
            command=command,
        )
        print(
            f"atm_student: {card['gradient_steps']} steps -> {policies_dir / 'atm_student.pt'}; held-out relative "
            "error "
            + ", ".join(f"c={k.split('c')[-1]}: {v:.3f}" for k, v in card["held_out_error"].items() if "rel" in k)
        )
        cards = [card]
    else:
        from cefc_mj.train.pipeline import plan, run_pipeline

        _check_workers(args)
        ppo = _ppo_from(args)
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
            show_progress=show,
            tuples_per_formation=args.tuples,
            workers=args.workers,
            command=command,
        )
    if args.install:
        from cefc_mj.train.model_card import install_policy

        for card in cards:
            target = install_policy(policies_dir / f"{card['name']}.pt", paths.POLICIES_DIR)
            print(f"installed {card['name']} -> {target}")
    return cards


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        run(args, command=shlex.join(["cefc-train", *argv]))
    except CefcError as e:
        message = str(_as_flag_error(e) if isinstance(e, ConfigError) else e)
        print(f"cefc-train: error: {' '.join(message.split())}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None
    except OSError as e:  # a failing disk or folder during the run: one line, not a traceback
        print(f"cefc-train: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            "cefc-train: interrupted; the same command with --resume continues from the last checkpoint",
            file=sys.stderr,
        )
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
