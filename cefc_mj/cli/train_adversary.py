"""`cefc-train adversary` and `adversary-ddpg`: the adversary trainers' flags, which default to None
so that AdversaryConfig (cefc_mj/train/adversary.py) and DDPGAdversaryConfig
(cefc_mj/train/adversary_ddpg.py) own the defaults and the range checks, and their runs."""

from __future__ import annotations

import argparse

from cefc_mj.cli.train_common import HIGHLEVEL_DOCS, add_common_args, check_destinations, install, subcommand_help
from cefc_mj.task.config import RULE_TEAMS
from cefc_mj.train.config import Budget

COMMANDS = ("adversary", "adversary-ddpg")


def _names(text: str) -> tuple[str, ...]:
    """A comma-separated list of names (argparse type); for --teams, `every-row` is every shipped Table V
    row over its training seeds and the rule teams (`EVERY_ROW_POPULATION`)."""
    if text.strip() == "every-row":
        from cefc_mj.train.adversary import EVERY_ROW_POPULATION

        return EVERY_ROW_POPULATION
    names = tuple(part.strip() for part in text.split(","))
    if not all(names):
        raise argparse.ArgumentTypeError(f"{text!r}: a comma-separated list of names, none empty")
    if "every-row" in names:
        raise argparse.ArgumentTypeError(f"{text!r}: every-row names the whole population; give it alone")
    return names


def add_parser(sub) -> None:
    """The subcommands adversary and adversary-ddpg, in that order."""
    _adversary_parser(sub)
    _adversary_ddpg_parser(sub)


def _population_game_args(p: argparse.ArgumentParser) -> None:
    """The flags both adversary trainers share: the population of teams, the game and the reward."""
    p.add_argument(
        "--teams",
        type=_names,
        default=None,
        metavar="NAME,...",
        help="the population: trained high levels (names or files) and rule teams ("
        + ", ".join(RULE_TEAMS)
        + "); default the first Table V rows over their training seeds and every rule team; "
        "every-row: every shipped Table V row over its training seeds, each over its own low level, and "
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
        **subcommand_help(
            ["cefc-train adversary   # imitation of a chase rule, critic warm-up, then PPO (default budget)"],
            HIGHLEVEL_DOCS,
        ),
    )
    _population_game_args(p)
    p.add_argument(
        "--imitation-episodes",
        type=int,
        default=None,
        metavar="N",
        help="before PPO, imitate --imitation-rule on N episodes per round of the population's "
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
        "the nearest UAV within 3 m), nearest_group_intercept (the game adversary's: aims ahead of the "
        "nearest group, and of its member within 3 m), nearest_group_member, nearest_group, r_nearest or "
        "r_largest",
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
    add_common_args(p, "adversary", "20it")


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
        **subcommand_help(["cefc-train adversary-ddpg --budget 150it"], HIGHLEVEL_DOCS),
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
    add_common_args(p, "adversary-ddpg", "150it")


def run(args, budget: Budget, command: str | None = None) -> list[dict]:
    """Check the config and folders, train, export and, with --install, install; returns the model card."""
    from cefc_mj.nn.adversary_policy import load_adversary_policy

    if args.command == "adversary":
        from cefc_mj.train.adversary import config_from_args, summary_lines, train_adversary as train
    else:
        from cefc_mj.train.adversary_ddpg import config_from_args, summary_lines, train_ddpg_adversary as train
    cfg = config_from_args(args, budget)
    policies_dir = check_destinations(args)
    card = train(cfg, args.out, policies_dir, resume=args.resume, show_progress=not args.no_progress, command=command)
    print("\n".join(summary_lines(card, policies_dir)))
    if args.install:
        install([card["name"]], policies_dir, load=load_adversary_policy)
    return [card]
