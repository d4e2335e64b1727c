"""`cefc-train`: train the policies the evaluators fly: the low level (AT-M steps, AT-M-Safe/Robust/Quad,
the distilled student, the CL-M baseline, BenchMARL's algorithms on the formation task), the high level
(CI-HRL's ConsMAC + anchor selector, its variants, BenchMARL's MASAC or MAPPO) and the game's
adversaries (PPO, DDPG).

Examples:
    cefc-train lowlevel --formation 6 --step 1 --budget 15m
    cefc-train lowlevel --formation 6 --step 3 --safe --init-from atm_c6_step3 --budget 100it
    cefc-train distill --budget 20000it
    cefc-train lowlevel-all --budget 80m            # the whole pipeline
    cefc-train clm --formation 6 --budget 1404s     # the CL-M baseline (curriculum 0,0.01,0.02,0.03)
    cefc-train highlevel --variant consmac-a --budget 75it   # the high level (Algorithm 2) over atm_student
    cefc-train adversary                                     # the PPO adversary (imitation, critic warm-up)
    cefc-train adversary-ddpg --budget 150it                 # the DDPG adversary (Table VI)
    cefc-train highlevel-benchmarl --algorithm masac --budget 1500ep   # BenchMARL's MASAC (benchmarl extra)
    cefc-train formation-benchmarl --algorithm maddpg --formation 6    # BenchMARL's MADDPG, Table III's baseline

Everything a run writes goes under --out (default runs/<command>, relative to the current folder):
run folders (config, CSV and TensorBoard logs, resumable state) and the exported policies with their
model cards in <out>/policies/ (or --policies-dir). The shipped policies/ folder is written only
with --install, after a successful run. --resume continues an interrupted run from its last
checkpoint. Invalid input prints one line and exits with status 2 before anything is written.
Each subcommand's --help lists its flags, with an example.

Docs: docs/train_lowlevel.md (lowlevel, distill, lowlevel-all, clm); docs/train_highlevel.md (highlevel,
adversary, adversary-ddpg, highlevel-benchmarl); docs/formation_benchmarl.md (formation-benchmarl).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from cefc_mj.cli import (
    train_adversary,
    train_benchmarl,
    train_benchmarl_formation,
    train_highlevel,
    train_lowlevel,
)
from cefc_mj.cli.train_common import EXIT_USAGE, PROG, check_destinations
from cefc_mj.errors import CefcError, ConfigError, ExamplesHelpFormatter, OneLineParser
from cefc_mj.train.config import Budget

__all__ = ["EXIT_USAGE", "build_parser", "check_destinations", "main", "run"]

FAMILIES = (train_lowlevel, train_highlevel, train_adversary, train_benchmarl, train_benchmarl_formation)
"""The trainer modules, in the order their subcommands are listed: each has COMMANDS, add_parser(sub)
adding their parsers, and run(args, budget, command) -> the model cards; a module with parse_budget(text)
reads its own --budget (highlevel-benchmarl: episodes; formation-benchmarl: frames), the others get a Budget."""

RUNNERS = {command: family for family in FAMILIES for command in family.COMMANDS}
"""The module that runs each subcommand."""


_Parser = OneLineParser


class _VersionAction(argparse.Action):
    """--version, computed only when asked (it imports mujoco, numba and torch)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from cefc_mj.provenance import version_line

        print(version_line(PROG))
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description=__doc__.split("\n\n")[0],
        formatter_class=ExamplesHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--version", action=_VersionAction, help="print the version, code digest and libraries")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{" + ",".join(RUNNERS) + "}")
    for family in FAMILIES:
        family.add_parser(sub)
    return parser


def _as_flag_error(e: ConfigError) -> ConfigError:
    """'n_envs=0: must be ...' from a config -> '--envs 0: must be ...', the flag the user typed (the
    adversary and high-level configs name their flags themselves, in config_from_args)."""
    from cefc_mj.train.config import flag_error

    return flag_error(e, train_lowlevel.FLAG_OF_FIELD)


def run(args, command: str | None = None) -> list[dict]:
    """Validate the arguments, train, export (and install); returns the model cards. Configs and
    folders are checked before the training modules (torch, numba) are imported."""
    family = RUNNERS[args.command]
    budget = getattr(family, "parse_budget", Budget.parse)(args.budget)
    return family.run(args, budget, command)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    started = time.time()
    try:
        run(args, command=shlex.join([PROG, *argv]))
    except CefcError as e:
        message = str(_as_flag_error(e) if isinstance(e, ConfigError) else e)
        print(f"{PROG}: error: {' '.join(message.split())}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None
    except OSError as e:  # a failing disk or folder during the run: one line, not a traceback
        print(f"{PROG}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; {_resume_hint(args, started)}", file=sys.stderr)
        return 130
    return 0


def _resume_hint(args, started: float) -> str:
    """What continues an interrupted run: --resume where a checkpoint exists (written by this command,
    or the one it resumed), else the same command again (a run interrupted before its first checkpoint,
    e.g. in the adversary's imitation phase, has nothing to resume)."""
    from cefc_mj.train.run_state import STATE_FILE

    out = getattr(args, "out", None)
    patterns = (f"**/{STATE_FILE}", "**/checkpoints/checkpoint_*.pt")  # ours; BenchMARL's (formation-benchmarl)
    found = out is not None and Path(out).is_dir()
    states = sorted(p for pattern in patterns for p in Path(out).glob(pattern)) if found else []
    if getattr(args, "resume", False) or any(p.stat().st_mtime >= started for p in states):
        return "the same command with --resume continues from the last checkpoint"
    return "no checkpoint was written yet: run the same command again (without --resume) to start over"


if __name__ == "__main__":
    sys.exit(main())
