"""What cefc-train's trainer modules share: the program's name and exit code, the flags every
subcommand takes (--seed, --out, --budget, ...) and the PPO ones, the checks of --out,
--policies-dir and --install before anything is written, and the final --install copy."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import ConfigError, ExamplesHelpFormatter, help_epilog
from cefc_mj.fileio import can_write_in
from cefc_mj.train.config import PPOConfig

PROG = "cefc-train"
EXIT_USAGE = 2
LOWLEVEL_DOCS = "docs/train_lowlevel.md"
"""The page on training the low level (lowlevel, distill, lowlevel-all, clm)."""
HIGHLEVEL_DOCS = "docs/train_highlevel.md"
"""The page on training the high level and the adversaries (highlevel, adversary, adversary-ddpg,
highlevel-benchmarl)."""


def subcommand_help(examples: list[str], docs: str) -> dict:
    """The `add_parser` keywords that end a subcommand's --help with its examples and its docs page."""
    return {"formatter_class": ExamplesHelpFormatter, "epilog": help_epilog(examples, docs)}


def field_default(config, name: str):
    """The default of field `name` of the config dataclass `config`, which owns it: a flag takes its
    default (and the "(default X)" of its help) from here instead of repeating the value."""
    field = {f.name: f for f in dataclasses.fields(config)}[name]
    return field.default_factory() if field.default is dataclasses.MISSING else field.default


def add_common_args(p: argparse.ArgumentParser, command: str, default_budget: str) -> None:
    """--seed, --out, --policies-dir, --install, --resume, --budget, --no-progress."""
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


def add_ppo_args(p: argparse.ArgumentParser) -> None:
    """The PPOConfig flags of the low-level trainers (lowlevel, lowlevel-all, clm), defaulted by PPOConfig."""
    d = PPOConfig()
    p.add_argument("--envs", type=int, default=d.n_envs, help=f"parallel envs (default {d.n_envs})")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"PPO epochs per iteration (default {d.epochs})")
    p.add_argument(
        "--minibatches", type=int, default=d.minibatches, help=f"minibatches per epoch (default {d.minibatches})"
    )
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument(
        "--gamma",
        type=float,
        default=d.gamma,
        help=f"discount factor (default {d.gamma}, the paper's; a horizon of about 1 / (1 - gamma) decision steps)",
    )
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


def ppo_from(args) -> PPOConfig:
    """The PPOConfig of add_ppo_args' flags, validated."""
    ppo = PPOConfig(
        n_envs=args.envs,
        epochs=args.epochs,
        minibatches=args.minibatches,
        lr=args.lr,
        gamma=args.gamma,
        collision_credit=args.credit,
        update_threads=args.threads,
    )
    ppo.validate()
    return ppo


# ---------------------------------------------------------------------------- destinations
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


def install(names, policies_dir: Path, load=None) -> None:
    """--install: copy the exported policies `names` (and their cards) from `policies_dir` into the
    shipped policies folder, each loaded first with `load` (default: as a low-level policy)."""
    from cefc_mj.train.model_card import install_policy

    for name in names:
        if load is None:
            target = install_policy(policies_dir / f"{name}.pt", paths.POLICIES_DIR)
        else:
            target = install_policy(policies_dir / f"{name}.pt", paths.POLICIES_DIR, load=load)
        print(f"installed {name} -> {target}")
