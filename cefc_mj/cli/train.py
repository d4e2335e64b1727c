"""`cefc-train`: train the low-level policies (AT-M steps, AT-M-Safe, the distilled student).

    cefc-train lowlevel --formation 6 --step 1 --budget 15m
    cefc-train lowlevel --formation 6 --step 3 --safe --budget 100it
    cefc-train distill --budget 20000it
    cefc-train lowlevel-all --budget 80m            # the whole pipeline, writes policies/

Run folders (logs, TensorBoard, resumable state) go under --out; exported policies and their
model cards under --policies-dir. --resume continues an interrupted run from its last checkpoint.
Invalid input prints one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.train.config import FORMATIONS, Budget, DistillConfig, LowLevelConfig, PPOConfig


def _formations(text: str) -> tuple[int, ...]:
    try:
        values = tuple(sorted({int(v) for v in text.split(",") if v.strip()}))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated formation sizes, e.g. 6,7,8") from None
    if not values or any(v not in FORMATIONS for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: formation sizes must be among {FORMATIONS}")
    return values


def _common(p: argparse.ArgumentParser, default_budget: str) -> None:
    p.add_argument("--seed", type=int, default=0, help="seed of networks, sampling and episodes (default 0)")
    p.add_argument("--out", type=Path, default=Path("runs/lowlevel"),
                   help="root of the run folders: logs, TensorBoard, resumable state (default runs/lowlevel)")
    p.add_argument("--policies-dir", type=Path, default=paths.POLICIES_DIR,
                   help=f"where exported policies and model cards go (default {paths.POLICIES_DIR})")
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
    parser = argparse.ArgumentParser(prog="cefc-train", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    sub = parser.add_subparsers(dest="command", required=True, metavar="{lowlevel,distill,lowlevel-all}")

    p = sub.add_parser("lowlevel", help="one AT-M stage for one formation size",
                       description="Train one AT-M stage (Algorithm 1): step 1 without obstacles, step 2 with "
                                   "obstacles (density 0.03), step 3 merging them and fine-tuning; --safe fine-tunes "
                                   "the step-3 result with the AT-M-Safe LiDAR transform. Step 3 and --safe read the "
                                   "earlier stages' state from --out.")
    p.add_argument("--formation", type=int, required=True, choices=FORMATIONS, metavar="C",
                   help=f"formation size c, one of {FORMATIONS}")
    p.add_argument("--step", type=int, required=True, choices=(1, 2, 3), help="AT-M step")
    p.add_argument("--safe", action="store_true", help="AT-M-Safe (with --step 3)")
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
    _common(p, "100it")
    _ppo_args(p)

    p = sub.add_parser("distill", help="distill one student from the Step 3 teachers",
                       description="Collect (observation, action) replay from each atm_c{c}_step3 teacher in "
                                   "--policies-dir and train one student (hidden 256, MSE, Adam 1e-4, batch 600).")
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="teachers' sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="replay tuples per teacher (default 60000)")
    _common(p, "20000it")

    p = sub.add_parser("lowlevel-all", help="the whole low-level pipeline",
                       description="AT-M steps 1-3 and Safe for every formation, then distillation; one --budget "
                                   "split over the stages (see cefc_mj.train.pipeline).")
    p.add_argument("--formations", type=_formations, default=FORMATIONS, help="formation sizes (default 3,4,5,6,7,8)")
    p.add_argument("--tuples", type=int, default=60_000, help="distillation replay tuples per teacher (default 60000)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes training formations side by side, one torch thread each (default 1)")
    _common(p, "80m")
    _ppo_args(p)
    return parser


def run(args) -> None:
    budget = Budget.parse(args.budget)
    if getattr(args, "workers", 1) < 1:
        raise ConfigError(f"--workers {args.workers}: must be >= 1")
    show = not args.no_progress
    if args.command == "lowlevel":
        from cefc_mj.train.lowlevel import train_lowlevel

        cfg = LowLevelConfig(formation=args.formation, step=args.step, safe=args.safe, deviation=args.deviation,
                             deviation_sampling=args.deviation_sampling, response_time=args.response_time,
                             velocity_noise=args.velocity_noise,
                             budget=budget, seed=args.seed,
                             obstacle_density=args.density, ppo=_ppo_from(args))
        card = train_lowlevel(cfg, args.out, args.policies_dir, resume=args.resume, show_progress=show)
        print(f"{card['name']}: {card['iterations']} iterations, {card['agent_steps']} agent-steps, "
              f"{card['train_wall_clock_s']} s -> {args.policies_dir / (card['name'] + '.pt')}")
        o = card["table3"]["ours"]
        print(f"Table III protocol (density 0.05): R_L {o['R_L']:.2f}/step  F {o['F']:.2f}  N {o['N']:.2f}  C {o['C']:.2f}%")
    elif args.command == "distill":
        from cefc_mj.train.distill import train_student

        cfg = DistillConfig(budget=budget, formations=args.formations, tuples_per_formation=args.tuples, seed=args.seed)
        card = train_student(cfg, args.policies_dir, args.out, resume=args.resume, show_progress=show)
        print(f"atm_student: {card['gradient_steps']} steps; held-out relative error "
              + ", ".join(f"c={k.split('c')[-1]}: {v:.3f}" for k, v in card["held_out_error"].items() if "rel" in k))
    else:
        from cefc_mj.train.pipeline import run_pipeline

        run_pipeline(budget, args.out, args.policies_dir, seed=args.seed, resume=args.resume,
                     formations=args.formations, ppo=_ppo_from(args), show_progress=show,
                     tuples_per_formation=args.tuples, workers=args.workers)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        run(args)
    except CefcError as e:
        print(f"cefc-train: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cefc-train: interrupted; continue with --resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
