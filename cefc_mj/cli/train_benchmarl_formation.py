"""`cefc-train formation-benchmarl`: BenchMARL's MADDPG (the paper's Table III baseline), IPPO, MAPPO or
MASAC on the formation task of AT-M's stages, exported as an AT-M policy file that Table III flies
(docs/formation_benchmarl.md). A sibling of `highlevel-benchmarl` (cefc_mj/cli/train_benchmarl.py): the
same extra, the same checks, another task and budget unit. The flags default to None so that
FormationBenchMARLConfig (cefc_mj/train/benchmarl_config.py) owns the defaults and the range checks.
Without the `benchmarl` extra the subcommand prints one line and exits 2."""

from __future__ import annotations

import argparse

from cefc_mj.cli.train_benchmarl import add_output_args, add_threads_arg, finish, has_benchmarl, require_extra
from cefc_mj.cli.train_common import check_destinations, field_default, subcommand_help
from cefc_mj.train.benchmarl_config import (
    FORMATION_ALGORITHMS,
    FORMATION_COMMAND,
    FORMATION_EXTRA,
    FormationBenchMARLConfig,
    formation_config_from_args,
    parse_frame_budget,
)

COMMANDS = (FORMATION_COMMAND,)
COMMAND = FORMATION_COMMAND


def parse_budget(text: str | None) -> int:
    """The --budget of this subcommand: frames (env-steps; None: FormationBenchMARLConfig's default)."""
    return field_default(FormationBenchMARLConfig, "budget_frames") if text is None else parse_frame_budget(text)


def add_parser(sub) -> None:
    """`cefc-train formation-benchmarl`; flags left out keep FormationBenchMARLConfig's defaults."""

    def default(name: str):
        return field_default(FormationBenchMARLConfig, name)

    p = sub.add_parser(
        COMMAND,
        help="BenchMARL's MADDPG (Table III's baseline), IPPO, MAPPO or MASAC on the formation task "
        "(needs the benchmarl extra)",
        description="Train BenchMARL 1.5.2's MADDPG, IPPO, MAPPO or MASAC on the formation task of AT-M's "
        "stages (one group of c UAVs flying to an anchor for 100 steps; Step 1's scenario without "
        "obstacles or Steps 2-3's at density 0.03), with AT-M's actor network, from random weights. The actor "
        "is exported as an AT-M policy file benchmarl_<algorithm>_c<c>[_step1][_seed<k>].pt that Table III "
        "flies (cefc-eval --backend particle --protocol table3 --policy FILE). Resumable (--resume). "
        "Needs the benchmarl extra: pip install -e '.[benchmarl]'.",
        **subcommand_help(
            ["cefc-train formation-benchmarl --algorithm maddpg --formation 6   # Table III's MADDPG baseline, c = 6"],
            "docs/formation_benchmarl.md",
        ),
    )
    p.add_argument(
        "--algorithm",
        choices=FORMATION_ALGORITHMS,
        default=None,
        help=f"BenchMARL's algorithm (default {default('algorithm')})",
    )
    p.add_argument(
        "--formation",
        type=int,
        default=None,
        metavar="C",
        help=f"agents in the group, 3..8 (default {default('formation')})",
    )
    p.add_argument(
        "--step",
        type=int,
        default=None,
        metavar="1|2",
        help="the AT-M stage whose scenario is trained: 1 (no obstacles) or 2 (density 0.03, the scenario "
        f"of Steps 2 and 3) (default {default('step')})",
    )
    p.add_argument(
        "--seed", type=int, default=None, help=f"BenchMARL's seed and the episodes' (default {default('seed')})"
    )
    p.add_argument(
        "--budget",
        default=None,
        metavar="FRAMES",
        help="training frames (env-steps; one frame is c agent-steps): '300000', '300kf' or '3mf', a "
        f"multiple of the frames of an iteration (default {default('budget_frames')})",
    )
    add_output_args(
        p,
        COMMAND,
        "BenchMARL's folder with its checkpoints",
        resume="continue the run in <out>/<name>/ from its newest checkpoint (a larger --budget trains further)",
    )
    p.add_argument(
        "--envs",
        type=int,
        default=None,
        dest="n_envs",
        metavar="N",
        help=f"envs stepped as one batch (default {default('n_envs')})",
    )
    p.add_argument(
        "--episodes-per-iteration",
        type=int,
        default=None,
        dest="episodes_per_iteration",
        metavar="N",
        help=f"episodes each env plays per iteration (default {default('episodes_per_iteration')})",
    )
    p.add_argument(
        "--reward-scale",
        type=float,
        default=None,
        metavar="K",
        help="factor on each agent's reward before BenchMARL sees it, for its unnormalised critics "
        f"(default {default('reward_scale')}; 1: unscaled)",
    )
    p.add_argument(
        "--gamma", type=float, default=None, metavar="G", help=f"discount per step (default {default('gamma')})"
    )
    p.add_argument("--lr", type=float, default=None, metavar="LR", help=f"Adam learning rate (default {default('lr')})")
    p.add_argument(
        "--updates",
        type=int,
        default=None,
        metavar="N",
        help=f"maddpg, masac: gradient steps per iteration (default {default('updates')})",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=None,
        dest="batch_size",
        metavar="N",
        help=f"maddpg, masac: frames per gradient step (default {default('batch_size')})",
    )
    p.add_argument(
        "--memory",
        type=int,
        default=None,
        dest="memory_frames",
        metavar="FRAMES",
        help=f"maddpg, masac: replay capacity in frames (default {default('memory_frames')})",
    )
    p.add_argument(
        "--anneal-frames",
        type=int,
        default=None,
        dest="exploration_anneal_frames",
        metavar="FRAMES",
        help="maddpg: frames over which the exploration noise falls from sigma 0.8 to 0.01 "
        f"(default {default('exploration_anneal_frames')})",
    )
    p.add_argument(
        "--epochs",
        type=int,
        default=None,
        metavar="N",
        help=f"ippo, mappo: passes over each iteration's frames (default {default('epochs')})",
    )
    p.add_argument(
        "--minibatch-size",
        type=int,
        default=None,
        dest="minibatch_size",
        metavar="N",
        help=f"ippo, mappo: frames per minibatch (default {default('minibatch_size')})",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=None,
        dest="checkpoint_every",
        metavar="N",
        help=f"iterations between checkpoints (default {default('checkpoint_every')})",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        metavar="N",
        help="validation episodes of Table III's protocol flown for the model card "
        f"(default {default('eval_episodes')}; 0 skips)",
    )
    add_threads_arg(p, default("threads"))


def run(args: argparse.Namespace, budget_frames: int, command: str | None = None) -> list[dict]:
    """Check the flags, the extra and the folders, train (or resume), export and, with --install,
    install; returns the model card."""
    cfg = formation_config_from_args(args, budget_frames)
    require_extra(has_benchmarl(), FORMATION_EXTRA)
    policies_dir = check_destinations(args)
    from cefc_mj.train.benchmarl_formation import summary_lines, train_formation

    card = train_formation(
        cfg, args.out, policies_dir, resume=args.resume, show_progress=not args.no_progress, command=command
    )
    return finish(card, policies_dir, summary_lines, args.install)
