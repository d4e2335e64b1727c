"""`cefc-train highlevel-benchmarl`: BenchMARL's MASAC (the stand-in for the paper's HASAC) or MAPPO on our
high-level game, exported as a high-level policy file that Table V flies (docs/research/baselines.md, "BenchMARL
baselines"). The flags default to None so that BenchMARLConfig (cefc_mj/train/benchmarl_config.py) owns
the defaults and the range checks. Needs the optional `benchmarl` extra; without it the subcommand
prints one line and exits 2."""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from cefc_mj import paths
from cefc_mj.cli.train_common import (
    EXIT_USAGE,
    HIGHLEVEL_DOCS,
    check_destinations,
    field_default,
    install,
    subcommand_help,
)
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.task.config import ADVERSARY_RULES
from cefc_mj.train.benchmarl_config import (
    ALGORITHMS,
    BENCHMARL_EXTRA,
    BenchMARLConfig,
    config_from_args,
    parse_episode_budget,
)

COMMANDS = ("highlevel-benchmarl",)
COMMAND = COMMANDS[0]


def parse_budget(text: str | None) -> int:
    """The --budget of this subcommand: episodes ('1500ep' or '1500'; None: BenchMARLConfig's default);
    cefc-train's `run` calls it."""
    return field_default(BenchMARLConfig, "budget_episodes") if text is None else parse_episode_budget(text)


def has_benchmarl() -> bool:
    """Whether the `benchmarl` extra (BenchMARL and torchrl) is installed."""
    try:
        return all(importlib.util.find_spec(name) is not None for name in ("benchmarl", "torchrl", "tensordict"))
    except (ImportError, ValueError):  # a broken or blocked installation counts as none
        return False


def add_output_args(p: argparse.ArgumentParser, command: str, benchmarl_folder: str, resume: str | None = None) -> None:
    """--out, --policies-dir, --install, --resume (where `resume`, its help, is given) and --no-progress
    of a BenchMARL subcommand; `benchmarl_folder`: what the --out help says of BenchMARL's folder."""
    p.add_argument(
        "--out",
        type=Path,
        default=Path("runs") / command,
        help=f"where the run writes: <out>/<name>/ (config, progress.csv, {benchmarl_folder}) and, in "
        f"<out>/policies/, the exported policy and its model card (default runs/{command})",
    )
    p.add_argument(
        "--policies-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="where the exported policy and model card go instead of <out>/policies/",
    )
    p.add_argument(
        "--install",
        action="store_true",
        help=f"after a successful run, copy the exported policy and card into the shipped {paths.POLICIES_DIR}",
    )
    if resume is not None:
        p.add_argument("--resume", action="store_true", help=resume)
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for log files)")


def add_threads_arg(p: argparse.ArgumentParser, default: int) -> None:
    """--threads, the torch threads of a BenchMARL run (None: the config's `default`)."""
    p.add_argument(
        "--threads", type=int, default=None, metavar="N", help=f"torch threads of the run (default {default})"
    )


def require_extra(installed: bool, line: str) -> None:
    """Without the `benchmarl` extra (`installed` False): print `line` (one line) and exit 2."""
    if not installed:
        print(line, file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def finish(card: dict, policies_dir: Path, summary_lines, install_policy: bool, load=None) -> list[dict]:
    """Print the run's summary (`summary_lines(card, policies_dir)`) and, with --install, install the
    exported policy (read back with `load`); returns [card]."""
    print("\n".join(summary_lines(card, policies_dir)))
    if install_policy:
        install([card["name"]], policies_dir, load=load)
    return [card]


def add_parser(sub) -> None:
    """`cefc-train highlevel-benchmarl`; flags left out keep BenchMARLConfig's defaults."""

    def default(name: str):
        return field_default(BenchMARLConfig, name)

    p = sub.add_parser(
        COMMAND,
        help="BenchMARL's MASAC (the HASAC stand-in) or MAPPO on the high-level game (needs the benchmarl extra)",
        description="Train BenchMARL 1.5.2's MASAC (maximum-entropy MARL, the stand-in for the paper's HASAC) "
        "or MAPPO (a cross-check of `cefc-train highlevel --variant mappo`) on our high-level game: the same "
        "TaskConfig, PPO adversary and fine-tuning low level (atm_student), no navigation-only pre-training, "
        "BenchMARL's default hyperparameters, the episode budget of our trainer (1500 episodes of 40 "
        "decisions). The actor is exported as a high-level policy file benchmarl_<algorithm>[_seed<k>].pt "
        "that Table V flies (cefc-eval --protocol table5 --policy FILE). Needs the benchmarl extra: "
        "pip install -e '.[benchmarl]'.",
        **subcommand_help(
            ["cefc-train highlevel-benchmarl --algorithm masac --budget 1500ep   # the HASAC stand-in of Table V"],
            HIGHLEVEL_DOCS,
        ),
    )
    p.add_argument("--algorithm", choices=ALGORITHMS, required=True, help="masac or mappo")
    p.add_argument(
        "--seed", type=int, default=None, help=f"BenchMARL's seed and the games' (default {default('seed')})"
    )
    p.add_argument(
        "--budget",
        default=None,
        metavar="EPISODES",
        help=f"training episodes ('1500ep' or '1500'), a multiple of --envs (default {default('budget_episodes')} "
        "episodes, the paper's 1000 + 500)",
    )
    add_output_args(p, COMMAND, "BenchMARL's folder")
    p.add_argument(
        "--envs",
        type=int,
        default=None,
        dest="n_envs",
        metavar="N",
        help=f"envs, one episode each per iteration (default {default('n_envs')})",
    )
    p.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        metavar="N",
        help=f"low-level steps per episode, a multiple of 10 (default {default('episode_steps')})",
    )
    p.add_argument(
        "--density",
        type=float,
        default=None,
        dest="obstacle_density",
        metavar="D",
        help=f"obstacle density per m^2 (default {default('obstacle_density')})",
    )
    p.add_argument(
        "--adversary",
        default=None,
        metavar="RULE|NAME|PATH",
        help=f"the game's adversary: a rule ({', '.join(ADVERSARY_RULES)}) or a trained "
        f"adversary's policy name or file (default {GAME_ADVERSARY}, the game's PPO adversary)",
    )
    p.add_argument(
        "--low-level",
        default=None,
        metavar="NAME|PATH|per-group",
        help="the low level: a policy name or file (default atm_student) or per-group",
    )
    p.add_argument(
        "--reward-scale",
        type=float,
        default=None,
        metavar="K",
        help="factor on R_H before BenchMARL sees it, for its unnormalised critics "
        f"(default {default('reward_scale')}; 1: unscaled)",
    )
    p.add_argument(
        "--gamma", type=float, default=None, metavar="G", help=f"discount per decision (default {default('gamma')})"
    )
    p.add_argument(
        "--lr",
        type=float,
        default=None,
        metavar="LR",
        help=f"Adam learning rate, BenchMARL's (default {default('lr')})",
    )
    p.add_argument(
        "--updates",
        type=int,
        default=None,
        dest="masac_updates",
        metavar="N",
        help=f"masac: gradient steps per iteration (default {default('masac_updates')})",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=None,
        dest="masac_batch",
        metavar="N",
        help=f"masac: frames per gradient step (default {default('masac_batch')})",
    )
    p.add_argument(
        "--epochs",
        type=int,
        default=None,
        dest="mappo_epochs",
        metavar="N",
        help=f"mappo: passes over each iteration's frames (default {default('mappo_epochs')})",
    )
    p.add_argument(
        "--minibatch-size",
        type=int,
        default=None,
        dest="mappo_minibatch",
        metavar="N",
        help=f"mappo: frames per minibatch (default {default('mappo_minibatch')})",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        metavar="N",
        help=f"validation episodes evaluated for the model card (default {default('eval_episodes')}; 0 skips)",
    )
    add_threads_arg(p, default("threads"))


def run(args: argparse.Namespace, budget_episodes: int, command: str | None = None) -> list[dict]:
    """Check the flags, the extra and the folders, train, export and, with --install, install; returns
    the model card."""
    cfg = config_from_args(args, budget_episodes)
    require_extra(has_benchmarl(), BENCHMARL_EXTRA)
    policies_dir = check_destinations(args)
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.train.benchmarl_game import summary_lines, train_benchmarl

    card = train_benchmarl(cfg, args.out, policies_dir, show_progress=not args.no_progress, command=command)
    return finish(card, policies_dir, summary_lines, args.install, load=load_highlevel_policy)
