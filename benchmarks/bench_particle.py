"""Particle-world throughput: agent-steps/s of BatchedCEFCEnv.step (physics, exact LiDAR, groups,
rewards, observations) for B in {1, 64, 256}, N = 8, 24 beams, obstacles at density 0.05 in the
20 m x 20 m arena, beside a per-env Python loop over B single-env instances measured in the same run.

    python benchmarks/bench_particle.py [--steps 200] [--mode cefc|formation]
    python benchmarks/bench_particle.py --smoke     # B in {1, 4}, 3 steps: seconds (tests/test_benchmarks.py)
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from cefc_mj.env import BatchedCEFCEnv  # noqa: E402
from cefc_mj.task.config import TaskConfig  # noqa: E402


def time_steps(envs: list[BatchedCEFCEnv], steps: int, rng: np.random.Generator) -> float:
    """Seconds per decision step of all `envs` (each stepped once per decision step)."""
    actions = [rng.uniform(-2, 2, (steps, e.n_envs, e.n_agents, 2)) for e in envs]
    for e in envs:
        e.reset()
        e.step(actions[0][0] if e is envs[0] else np.zeros((e.n_envs, e.n_agents, 2)))  # warm-up / JIT
    done_at = envs[0].config.steps
    start = time.perf_counter()
    for t in range(steps):
        for e, a in zip(envs, actions):
            if e.t[0] >= done_at:
                e.reset()
            e.step(a[t])
    return (time.perf_counter() - start) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=200, help="decision steps timed per configuration")
    parser.add_argument("--mode", choices=["cefc", "formation"], default="cefc")
    parser.add_argument("--smoke", action="store_true", help="B in {1, 4}, 3 steps: the same code path in seconds")
    args = parser.parse_args()
    sizes = (1, 64, 256)
    if args.smoke:
        sizes, args.steps = (1, 4), 3
    cfg = TaskConfig(n_agents=8, mode=args.mode, obstacle_density=0.05, n_lidar_rays=24)
    rng = np.random.default_rng(0)
    print(f"mode={args.mode} N=8 M=24 obstacles={cfg.n_obstacles} (density 0.05), {args.steps} steps each, 1 thread")
    print(f"{'B':>5} {'batched agent-steps/s':>22} {'per-env loop agent-steps/s':>27} {'ratio':>7}")
    for b in sizes:
        batched = time_steps([BatchedCEFCEnv(cfg, n_envs=b, seed=0)], args.steps, rng)
        loop_steps = max(args.steps // max(b // 8, 1), 3 if args.smoke else 10)
        singles = [BatchedCEFCEnv(cfg, n_envs=1, seed=s) for s in range(b)]
        looped = time_steps(singles, loop_steps, rng)
        fast, slow = b * 8 / batched, b * 8 / looped
        print(f"{b:>5} {fast:>22,.0f} {slow:>27,.0f} {fast / slow:>6.1f}x")


if __name__ == "__main__":
    main()
