"""Cost of high-level training on one core, and of whole runs at the two schedules, old step against
new step, measured in the same run.

For each variant (CI-HRL's consmac-a and MAPPO+AT-M's mappo, the default config otherwise, 20 envs,
one torch thread), a `HighLevelTrainer` collects and updates on `--iterations` iterations in each
phase (pre-training flies the navigation-only low level, fine-tuning the student): the rollout and
the PPO update are the same code for old and new, timed once. For consmac-a, the ConsMAC step of
batch 2048 is then timed on the replay those iterations filled, the old step (tests/reference_impl.py)
and the new one alternating (benchmarks/bench_consmac.py's `StepPair`). From the medians:

    iteration   = rollout + PPO update + (ConsMAC steps per round / rounds' spacing) x step
    whole run   = iterations x (rollout + update) + rounds x steps per round x step

at the short schedule (75 iterations, 200 steps after each), the paper's (1,500 iterations,
5,000 steps after every 20; `cefc-train highlevel --schedule`) and the paper's shrunk to 75 and 300
iterations (paper-scaled, the budget ladder's shorter rungs), in core-hours.

    .venv/bin/python benchmarks/bench_highlevel_training.py
    .venv/bin/python benchmarks/bench_highlevel_training.py --iterations 3 --rounds 7
    .venv/bin/python benchmarks/bench_highlevel_training.py --smoke   # 2 envs, 1 iteration, 2 steps
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_consmac import StepPair  # noqa: E402

from cefc_mj.hierarchy import NAVIGATION, HierarchicalCEFCEnv, load_low_level  # noqa: E402
from cefc_mj.train.config import Budget  # noqa: E402
from cefc_mj.train.highlevel_config import SCHEDULES, HighLevelConfig  # noqa: E402
from cefc_mj.train.highlevel_trainer import HighLevelTrainer  # noqa: E402


def time_iterations(trainer: HighLevelTrainer, iterations: int) -> dict[str, list[float]]:
    """Seconds of rollout and PPO update per iteration, `iterations` in each phase."""
    cfg = trainer.cfg
    times: dict[str, list[float]] = {"rollout_pretrain": [], "rollout_finetune": [], "update": []}
    for phase, name in enumerate(("rollout_pretrain", "rollout_finetune")):
        env = HierarchicalCEFCEnv(
            trainer.task,
            trainer.low_levels[phase],
            n_envs=cfg.ppo.n_envs,
            seed=cfg.seed,
            decision_interval=cfg.decision_interval,
            adversary_policy=trainer.adversary_policy,
        )
        for _ in range(iterations):
            start = time.perf_counter()
            rollout = trainer.collect(env)
            middle = time.perf_counter()
            trainer.update(rollout)
            times[name].append(middle - start)
            times["update"].append(time.perf_counter() - middle)
            trainer.iteration += 1
    return times


def run_cost(schedule: dict, pretrain_s: float, finetune_s: float, step_s: float) -> float:
    """Seconds of a whole run: its iterations in each phase plus its ConsMAC steps."""
    iterations = schedule["iterations"]
    pretrain = round(schedule["pretrain_share"] * iterations)
    rounds = iterations // schedule["consmac_every"]
    return pretrain * pretrain_s + (iterations - pretrain) * finetune_s + rounds * schedule["consmac_steps"] * step_s


PAPER_SCALED_SHOWN = (75, 300)
"""Iterations at which the paper's schedule shrunk in its proportions ("paper-scaled", N from --budget)
is costed: the budget ladder's shorter rungs (docs/research/budget_ladder.md)."""


def schedule_costs() -> list[tuple[str, dict]]:
    """(name, numbers) of every schedule to cost; "paper-scaled" once per PAPER_SCALED_SHOWN."""
    out = []
    for name, schedule in SCHEDULES.items():
        if schedule["iterations"] is None:
            out += [(f"{name} {n}", {**schedule, "iterations": n}) for n in PAPER_SCALED_SHOWN]
        else:
            out.append((name, schedule))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=2, help="timed iterations per phase (default 2)")
    parser.add_argument("--steps", type=int, default=10, help="ConsMAC steps per timing round (default 10)")
    parser.add_argument("--rounds", type=int, default=5, help="timing rounds, old and new alternating (default 5)")
    parser.add_argument("--smoke", action="store_true", help="2 envs, 1 iteration per phase, 1 round of 2 steps")
    args = parser.parse_args()
    envs, batch = 20, 2048
    if args.smoke:
        args.iterations, args.steps, args.rounds, envs, batch = 1, 2, 1, 2, 64
    torch.set_num_threads(1)
    print(f"high-level training on one core: {envs} envs, ConsMAC batch {batch}; medians")
    results = {}
    for variant in ("consmac-a", "mappo"):
        cfg = HighLevelConfig(budget=Budget(iterations=1500), variant=variant, eval_episodes=0)
        cfg = replace(cfg, ppo=replace(cfg.ppo, n_envs=envs, rollout_threads=1, update_threads=1))
        task = cfg.task()
        trainer = HighLevelTrainer(cfg, (load_low_level(NAVIGATION, task), load_low_level(cfg.low_level, task)))
        times = time_iterations(trainer, args.iterations)
        med = {k: statistics.median(v) for k, v in times.items()}
        steps = {"old": 0.0, "new": 0.0}
        if trainer.replay is not None:
            pair = StepPair(trainer.policy.comm, trainer.replay, batch)
            step_times = pair.time(args.steps, args.rounds)
            steps = {k: statistics.median(v) / 1e3 for k, v in step_times.items()}
        results[variant] = (med, steps)
        print(
            f"{variant}: rollout {med['rollout_pretrain']:.2f} s (pre-training) / {med['rollout_finetune']:.2f} s "
            f"(fine-tuning), PPO update {med['update']:.2f} s"
            + (
                f"; ConsMAC step old {steps['old'] * 1e3:.1f} ms, new {steps['new'] * 1e3:.1f} ms "
                f"({steps['old'] / steps['new']:.2f}x)"
                if trainer.replay is not None
                else ""
            )
        )
        for name, schedule in schedule_costs():
            pre, fine = med["rollout_pretrain"] + med["update"], med["rollout_finetune"] + med["update"]
            per_it = {
                k: (pre + fine) / 2 + schedule["consmac_steps"] / schedule["consmac_every"] * s
                for k, s in steps.items()
            }
            cost = {k: run_cost(schedule, pre, fine, s) / 3600 for k, s in steps.items()}
            line = f"  {name} schedule: iteration {per_it['new']:.2f} s"
            if trainer.replay is not None:
                line += f" (old {per_it['old']:.2f} s, {per_it['old'] / per_it['new']:.2f}x)"
            line += f"; whole run {cost['new']:.2f} core-hours"
            if trainer.replay is not None:
                line += f" (old {cost['old']:.2f}, {cost['old'] / cost['new']:.2f}x)"
            print(line)


if __name__ == "__main__":
    main()
