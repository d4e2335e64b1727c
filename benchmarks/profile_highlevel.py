"""Where one core's time goes in high-level training, before and after the hand-written ConsMAC
step, as markdown tables (docs/research/highlevel_speed.md holds a copy).

1. One ConsMAC supervised step of batch 2048 (`torch.profiler`, `--steps` steps each): the old step
   (tests/reference_impl.py, autograd) and the new (`cefc_mj.nn.consmac_grad`), their time split
   into matrix products (mm, addmm, bmm, linear), the other torch operators, and the rest (Python,
   autograd's engine, the numba kernels, which the profiler does not see).
2. One CI-HRL iteration (consmac-a, 20 envs, 200 ConsMAC steps, one thread; `cProfile`) with each
   step: rollout, PPO update and ConsMAC round, and the functions that take the most time.

    .venv/bin/python benchmarks/profile_highlevel.py
    .venv/bin/python benchmarks/profile_highlevel.py --steps 20 --top 12
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from torch.profiler import profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from bench_consmac import StepPair, random_replay  # noqa: E402
from reference_impl import consmac_supervised_loss_reference  # noqa: E402

from cefc_mj.hierarchy import NAVIGATION, load_low_level  # noqa: E402
from cefc_mj.nn.consmac import ConsMAC, ConsMACConfig  # noqa: E402
from cefc_mj.task.config import TaskConfig  # noqa: E402
from cefc_mj.train import highlevel_trainer  # noqa: E402
from cefc_mj.train.config import Budget  # noqa: E402
from cefc_mj.train.highlevel_config import HighLevelConfig  # noqa: E402
from cefc_mj.train.highlevel_trainer import HighLevelTrainer  # noqa: E402

GEMM = {"aten::mm", "aten::addmm", "aten::bmm", "aten::linear", "aten::matmul"}


def step_profile(steps: int) -> None:
    cfg = ConsMACConfig.from_task(TaskConfig(n_agents=8, mode="cefc"))
    pair = StepPair(ConsMAC(cfg, seed=0), random_replay(cfg, 8192), 2048)
    rows = {}
    for which in ("old", "new"):
        for _ in range(2):
            pair.step(which)
        with profile() as prof:
            start = time.perf_counter()
            for _ in range(steps):
                pair.step(which)
            wall = (time.perf_counter() - start) / steps * 1e3
        gemm = other = 0.0
        for event in prof.key_averages():
            if event.key.startswith("aten::"):
                ms = event.self_cpu_time_total / steps / 1e3
                if event.key in GEMM:
                    gemm += ms
                else:
                    other += ms
        rows[which] = (wall, gemm, other, wall - gemm - other)
    print(f"ConsMAC step, batch 2048, one thread, mean of {steps} under the profiler (ms per step)\n")
    print("| step | total | matrix products | other torch operators | rest (Python, autograd engine, numba) |")
    print("|---|---:|---:|---:|---:|")
    for which, (wall, gemm, other, rest) in rows.items():
        print(f"| {which} | {wall:.1f} | {gemm:.1f} | {other:.1f} | {rest:.1f} |")
    print()


def reference_grads(net, batch):
    net.zero_grad(set_to_none=True)
    loss = consmac_supervised_loss_reference(net, batch)
    loss.backward()
    return loss.detach()


def iteration_profile(top: int) -> None:
    cfg = HighLevelConfig(budget=Budget(iterations=1500), variant="consmac-a", eval_episodes=0)
    cfg = replace(cfg, ppo=replace(cfg.ppo, rollout_threads=1, update_threads=1))
    task = cfg.task()
    low_levels = (load_low_level(NAVIGATION, task), load_low_level(cfg.low_level, task))
    new_grads = highlevel_trainer.supervised_grads
    for which, grads in (("old", reference_grads), ("new", new_grads)):
        highlevel_trainer.supervised_grads = grads
        trainer = HighLevelTrainer(cfg, low_levels)
        trainer.iterate()  # warm-up: kernels, the first env
        profiler = cProfile.Profile()
        profiler.enable()
        row = trainer.iterate()
        profiler.disable()
        total = row["rollout_s"] + row["update_s"] + row["consmac_s"]
        print(f"CI-HRL iteration ({which} ConsMAC step), one thread, under cProfile\n")
        print("| part | s | share |")
        print("|---|---:|---:|")
        for part in ("rollout_s", "update_s", "consmac_s"):
            print(f"| {part[:-2]} | {row[part]:.2f} | {row[part] / total:.0%} |")
        print(f"| iteration | {total:.2f} | |\n")
        stats = pstats.Stats(profiler).sort_stats("tottime")
        print(f"| function (top {top} by own time) | calls | own s |")
        print("|---|---:|---:|")
        for (path, line, name), (_, calls, own, _, _) in sorted(stats.stats.items(), key=lambda item: -item[1][2])[
            :top
        ]:
            where = name if path == "~" else f"{Path(path).name}:{line}({name})"
            print(f"| `{where}` | {calls} | {own:.2f} |")
        print()
    highlevel_trainer.supervised_grads = new_grads


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="ConsMAC steps profiled per implementation")
    parser.add_argument("--top", type=int, default=10, help="functions listed per iteration profile")
    args = parser.parse_args()
    torch.set_num_threads(1)
    step_profile(args.steps)
    iteration_profile(args.top)


if __name__ == "__main__":
    main()
