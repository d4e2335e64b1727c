"""`cefc-train highlevel`: the high level's flags, which default to None so that HighLevelConfig
(cefc_mj/train/highlevel_config.py) owns the defaults and the range checks, and its run."""

from __future__ import annotations

from cefc_mj.cli.train_common import HIGHLEVEL_DOCS, add_common_args, check_destinations, install, subcommand_help
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.task.config import ADVERSARY_RULES
from cefc_mj.train.config import Budget

COMMANDS = ("highlevel",)


def add_parser(sub) -> None:
    """`cefc-train highlevel`; flags left out keep HighLevelConfig's defaults (cefc_mj/train/highlevel_config.py)."""
    p = sub.add_parser(
        "highlevel",
        help="the high level (ConsMAC + anchor selector) over a trained low level",
        description="Algorithm 2: MAPPO anchor selection every 10 low-level steps, ConsMAC trained "
        "alternately by supervised learning; pre-training with a navigation-only low "
        "level, then fine-tuning with --low-level. Written as cihrl_<variant>.",
        **subcommand_help(
            [
                "cefc-train highlevel --variant consmac-a --budget 75it   # CI-HRL's high level over atm_student",
                "cefc-train highlevel --variant mappo --budget 75it       # the MAPPO baseline (no messages)",
            ],
            HIGHLEVEL_DOCS,
        ),
    )
    p.add_argument(
        "--variant",
        choices=("consmac-a", "consmac-o", "mappo", "tarmac", "masia", "nvif"),  # nn.highlevel_policy.VARIANTS
        default=None,
        help="consmac-a (default), consmac-o, mappo (no communication), tarmac (messages trained end to end by "
        "RL), masia (sends its 38-number local observation; attention aggregate trained to reconstruct the "
        "global state), nvif (sends a 64-number variational latent + the local observation, 102; trained as "
        "a VAE of local observations)",
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
        metavar="NAME|PATH|per-group|clm-per-group",
        help="fine-tuning low level: a policy name or file (default atm_student), per-group "
        "(atm_c<C>_step3 by group size) or clm-per-group (clm_c<C> by group size: CI-HRL-w-CL-M, "
        "written as cihrl_<variant>_clm)",
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
        help=f"the game's adversary: a rule ({', '.join(ADVERSARY_RULES)}) or a trained "
        f"adversary's policy name or file (default {GAME_ADVERSARY}, the game's PPO adversary)",
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
    p.add_argument(
        "--schedule",
        choices=("short", "paper", "paper-scaled"),  # train.highlevel_config.SCHEDULES
        default=None,
        help="the reading of the paper's training budget: short (default, the shipped runs': 75 iterations "
        "of 20 envs, ConsMAC 200 steps after each; flags may change its numbers), paper (1500 iterations of "
        "20 envs, 1000 of them pre-training, ConsMAC 5000 steps of batch 2048 after every 20; those numbers are "
        "fixed, so --budget, --envs, --pretrain-share and the --consmac-* flags must be left out or match) or "
        "paper-scaled (paper's numbers shrunk to --budget Nit, required: N a multiple of 3 below 1500, the "
        "first 2N/3 pre-training; a --resume keeps N)",
    )
    add_common_args(p, "highlevel", "75it")
    p.set_defaults(budget=None)  # the schedule's iterations (parse_budget)


def parse_budget(text: str | None) -> Budget | None:
    """--budget as a Budget; None when left out (the schedule's iterations: 75, or 1500 under paper)."""
    return None if text is None else Budget.parse(text)


def run(args, budget: Budget | None, command: str | None = None) -> list[dict]:
    """Check the config and folders, train, export and, with --install, install the policy and its
    pre-trained (wo-FT) weights; returns the model card."""
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.train.highlevel import summary_lines, train_highlevel
    from cefc_mj.train.highlevel_config import config_from_args

    cfg = config_from_args(args, budget)
    policies_dir = check_destinations(args)
    card = train_highlevel(
        cfg, args.out, policies_dir, resume=args.resume, show_progress=not args.no_progress, command=command
    )
    print("\n".join(summary_lines(card, policies_dir)))
    if args.install:
        install(filter(None, (card["name"], card.get("wo_ft"))), policies_dir, load=load_highlevel_policy)
    return [card]
