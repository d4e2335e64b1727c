"""`cefc-train`: train the low-level policies (AT-M steps, AT-M-Safe/Robust/Quad, the distilled student).

    cefc-train lowlevel --formation 6 --step 1 --budget 15m
    cefc-train lowlevel --formation 6 --step 3 --safe --init-from atm_c6_step3 --budget 100it
    cefc-train distill --budget 20000it
    cefc-train lowlevel-all --budget 80m            # the whole pipeline

Everything a run writes goes under --out (default runs/<command>, relative to the current folder):
run folders (config, CSV and TensorBoard logs, resumable state) and the exported policies with their
model cards in <out>/policies/ (or --policies-dir). The shipped policies/ folder is written only
with --install, after a successful run. --resume continues an interrupted run from its last
checkpoint. Invalid input prints one line and exits with status 2 before anything is written.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.train.config import FORMATIONS, Budget, DistillConfig, LowLevelConfig, PPOConfig

EXIT_USAGE = 2

_FLAG_OF_FIELD = {
    "n_envs": "--envs", "epochs": "--epochs", "minibatches": "--minibatches", "lr": "--lr",
    "update_threads": "--threads", "seed": "--seed", "obstacle_density": "--density", "deviation": "--deviation",
    "deviation_sampling": "--deviation-sampling", "response_time": "--response-time",
    "velocity_noise": "--velocity-noise", "safe": "--safe", "tuples_per_formation": "--tuples",
    "formations": "--formations", "response_time/velocity_noise": "--response-time/--velocity-noise",
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


def _common(p: argparse.ArgumentParser, command: str, default_budget: str) -> None:
    p.add_argument("--seed", type=int, default=0, help="seed of networks, sampling and episodes (default 0)")
    p.add_argument("--out", type=Path, default=Path("runs") / command,
                   help=f"where the run writes: run folders (logs, TensorBoard, resumable state) and, in "
                        f"<out>/policies/, the exported policies (default runs/{command})")
    p.add_argument("--policies-dir", type=Path, default=None, metavar="DIR",
                   help="where exported policies and model cards go instead of <out>/policies/")
    p.add_argument("--install", action="store_true",
                   help=f"after a successful run, copy the exported policies and cards into the shipped "
                        f"{paths.POLICIES_DIR} (replacing files of the same name)")
    p.add_argument("--resume", action="store_true", help="continue the run(s) found under --out")
    p.add_argument("--budget", default=default_budget,
                   help=f"iterations ('40', '40it') or wall-clock time ('90s', '15m', '1.5h') (default {default_budget})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for log files)")


def _ppo_args(p: argparse.ArgumentParser) -> None:
    d = PPOConfig()
    p.add_argument("--envs", type=int, default=d.n_envs, help=f"parallel envs (default {d.n_envs})")
    p.add_argument("--epochs", type=int, default=d.epochs, help=f"PPO epochs per iteration (default {d.epochs})")
    p.add_argument("--minibatches", type=int, default=d.minibatches, help=f"minibatches per epoch (default {d.minibatches})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--credit", choices=("agent", "team"), default=d.collision_credit,
                   help=f"collision credit: per agent or the paper's team reward (default {d.collision_credit})")
    p.add_argument("--threads", type=int, default=d.update_threads,
                   help=f"torch threads of the PPO update; 1 when several trainings share the CPU (default "
                        f"{d.update_threads})")


def _ppo_from(args) -> PPOConfig:
    ppo = PPOConfig(n_envs=args.envs, epochs=args.epochs, minibatches=args.minibatches, lr=args.lr,
                    collision_credit=args.credit, update_threads=args.threads)
    ppo.validate()
    return ppo


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cefc-train", description=__doc__.split("\n\n")[0],
                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--version", action=_VersionAction, help="print the version, code digest and libraries")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{lowlevel,distill,lowlevel-all}")

    p = sub.add_parser("lowlevel", help="one AT-M stage for one formation size",
                       description="Train one AT-M stage (Algorithm 1): step 1 without obstacles, step 2 with "
                                   "obstacles (density 0.03), step 3 merging them and fine-tuning; --safe, "
                                   "--deviation, --response-time/--velocity-noise fine-tune the step-3 result. Step 3 "
                                   "and its fine-tunes read the earlier stages' state from --out, or start from a "
                                   "trained policy with --init-from (e.g. the shipped atm_c6_step3).")
    p.add_argument("--formation", type=int, required=True, choices=FORMATIONS, metavar="C",
                   help=f"formation size c, one of {FORMATIONS}")
    p.add_argument("--step", type=int, required=True, choices=(1, 2, 3), help="AT-M step")
    p.add_argument("--safe", action="store_true", help="AT-M-Safe (with --step 3)")
    p.add_argument("--init-from", metavar="PATH|NAME", default=None,
                   help="Step 3 stages: start the actor from this policy file (a path, or a name in the shipped "
                        "policies/, e.g. atm_c6_step3) instead of the earlier stages' runs under --out; the critic "
                        "starts fresh, as a policy file holds only the actor")
    p.add_argument("--deviation", type=float, default=0.0, metavar="M",
                   help="train under sensing deviation M (m); with --step 3 this is AT-M-Robust, fine-tuned from "
                        "the Step 3 policy and written as atm_c<C>_robust (default 0)")
    p.add_argument("--deviation-sampling", choices=("fixed", "uniform"), default="fixed",
                   help="fixed: every episode at --deviation; uniform: each env draws its episode's deviation from "
                        "[0, --deviation] (default fixed)")
    p.add_argument("--response-time", type=float, default=0.0, metavar="S",
                   help="velocity lag (s) of the particle world; about 0.1 matches the MuJoCo quadrotor (default 0, "
                        "the paper's MPE). With --step 3 and no --deviation this is AT-M-Quad, fine-tuned from the "
                        "Step 3 policy and written as atm_c<C>_quad")
    p.add_argument("--velocity-noise", type=float, default=0.0, metavar="MPS",
                   help="std (m/s) of per-step velocity kicks in the particle world, a real vehicle's tracking "
                        "error; about 0.1 matches the MuJoCo quadrotor (default 0)")
    p.add_argument("--density", type=float, default=None, help="training obstacle density per m^2 (default: the step's)")
    _common(p, "lowlevel", "100it")
    _ppo_args(p)

    p = sub.add_parser("distill", help="distill one student from the Step 3 teachers",
                       description="Collect (observation, action) replay from each atm_c{c}_step3 teacher in "
                                   "--teachers-dir and train one student (hidden 256, MSE, Adam 1e-4, batch 600).")
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="teachers' sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="replay tuples per teacher (default 60000)")
    p.add_argument("--teachers-dir", type=Path, default=paths.POLICIES_DIR, metavar="DIR",
                   help=f"folder of the atm_c<C>_step3 teachers (default the shipped {paths.POLICIES_DIR})")
    _common(p, "distill", "20000it")

    p = sub.add_parser("lowlevel-all", help="the whole low-level pipeline",
                       description="AT-M steps 1-3 and Safe for every formation, then distillation of the "
                                   "pipeline's own Step 3 policies; one --budget split over the stages (see "
                                   "cefc_mj.train.pipeline).")
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="formation sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="distillation replay tuples per teacher (default 60000)")
    p.add_argument("--workers", type=int, default=1,
                   help=f"processes training formations side by side, one torch thread each, 1 to {len(FORMATIONS)} "
                        "(default 1)")
    _common(p, "lowlevel-all", "80m")
    _ppo_args(p)
    return parser


# ---------------------------------------------------------------------------- checks
def _check_folder(flag: str, folder: Path) -> None:
    """`folder` exists or can be made (its nearest existing ancestor is a writable folder)."""
    folder = folder.absolute()
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f"{flag} {folder}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
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
        raise ConfigError(f"--out {out}: inside the shipped policies folder {paths.POLICIES_DIR}; "
                          "choose another folder")
    if _is_shipped(policies_dir) and not args.install:
        raise ConfigError(f"--policies-dir {policies_dir}: the shipped policies folder is written only with --install")
    _check_folder("--policies-dir", policies_dir)
    if args.install:
        _check_folder("--install", paths.POLICIES_DIR)
    return policies_dir


def _check_workers(args) -> None:
    if not 1 <= args.workers <= len(FORMATIONS):
        raise ConfigError(f"--workers {args.workers}: must be an integer in [1, {len(FORMATIONS)}]")


def _as_flag_error(e: ConfigError) -> ConfigError:
    """'n_envs=0: must be ...' from a config -> '--envs 0: must be ...', the flag the user typed."""
    field, sep, rest = str(e).partition("=")
    if sep and field in _FLAG_OF_FIELD:
        value, _, why = rest.partition(": ")
        return ConfigError(f"{_FLAG_OF_FIELD[field]} {value}: {why}")
    return e


# ---------------------------------------------------------------------------- commands
def run(args, command: str | None = None) -> list[dict]:
    """Validate the arguments, train, export (and install); returns the model cards."""
    budget = Budget.parse(args.budget)
    show = not args.no_progress
    # Configs and folders are checked before the training modules (torch, numba) are imported.
    if args.command == "lowlevel":
        cfg = LowLevelConfig(formation=args.formation, step=args.step, safe=args.safe, deviation=args.deviation,
                             deviation_sampling=args.deviation_sampling, response_time=args.response_time,
                             velocity_noise=args.velocity_noise,
                             budget=budget, seed=args.seed,
                             obstacle_density=args.density, ppo=_ppo_from(args))
        policies_dir = check_destinations(args)
        from cefc_mj.train.lowlevel import train_lowlevel

        card = train_lowlevel(cfg, args.out, policies_dir, resume=args.resume, show_progress=show,
                              init_from=args.init_from, command=command)
        print(f"{card['name']}: {card['iterations']} iterations, {card['agent_steps']} agent-steps, "
              f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})")
        o = card["table3"]["ours"]
        print(f"Table III protocol (density 0.05): R_L {o['R_L']:.2f}/step  F {o['F']:.2f}  N {o['N']:.2f}  C {o['C']:.2f}%")
        cards = [card]
    elif args.command == "distill":
        cfg = DistillConfig(budget=budget, formations=args.formations, tuples_per_formation=args.tuples, seed=args.seed)
        policies_dir = check_destinations(args)
        from cefc_mj.train.distill import train_student

        card = train_student(cfg, policies_dir, args.out, resume=args.resume, show_progress=show,
                             teachers_dir=args.teachers_dir, command=command)
        print(f"atm_student: {card['gradient_steps']} steps -> {policies_dir / 'atm_student.pt'}; held-out relative "
              "error " + ", ".join(f"c={k.split('c')[-1]}: {v:.3f}" for k, v in card["held_out_error"].items()
                                   if "rel" in k))
        cards = [card]
    else:
        from cefc_mj.train.pipeline import plan, run_pipeline

        _check_workers(args)
        ppo = _ppo_from(args)
        plan(budget, args.formations, args.seed, ppo, args.tuples, args.workers)  # validates every stage's config
        policies_dir = check_destinations(args)
        cards = run_pipeline(budget, args.out, policies_dir, seed=args.seed, resume=args.resume,
                             formations=args.formations, ppo=ppo, show_progress=show,
                             tuples_per_formation=args.tuples, workers=args.workers, command=command)
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
        print("cefc-train: interrupted; the same command with --resume continues from the last checkpoint",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
