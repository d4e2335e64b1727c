"""Experiment: AT-M Step 1 with a LiDAR that sees obstacles only (docs/layouts.md, "Step 1 collisions").

The shipped Step 1 policies never collide in Table III (C 0.00 %), where the paper's collide in
11-19 % of agent-steps. Our LiDAR also sees the other UAVs (`TaskConfig.lidar_sees_agents`), so even
Step 1, which trains without obstacles, learns to steer clear of whatever its beams hit. This script
trains Step 1 for c = 6 with `lidar_sees_agents=False` (everything else as `cefc-train lowlevel
--formation 6 --step 1`) and evaluates it on Table III's protocol (density 0.05, 50 episodes x 100
steps, seed 0) with that LiDAR, then with the default one.

    python experiments/step1_obstacle_lidar.py runs/step1-obstacle-lidar 305     # 305 iterations, ~8 min

It writes only under the folder it is given. The LiDAR switch is not a training flag: a policy
trained with it must also be evaluated with it, which the evaluators do not know how to do yet.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cefc_mj.train.lowlevel as lowlevel
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.eval.table3 import TABLE3_DENSITY, TABLE3_EPISODES, TABLE3_STEPS, roll_out
from cefc_mj.nn.policy_io import load_policy
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.config import Budget, LowLevelConfig, PPOConfig

FORMATION = 6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="run folder (must not exist)")
    parser.add_argument("iterations", type=int, help="PPO iterations (the shipped c = 6 Step 1 had 305)")
    args = parser.parse_args()
    if args.out.exists():
        parser.error(f"{args.out} exists: choose a new folder")
    if args.iterations < 1:
        parser.error(f"iterations {args.iterations}: must be at least 1")

    stage_task = lowlevel.task_config_for
    lowlevel.task_config_for = lambda cfg, density=None: dataclasses.replace(stage_task(cfg, density),
                                                                             lidar_sees_agents=False)
    cfg = LowLevelConfig(formation=FORMATION, step=1, budget=Budget(iterations=args.iterations),
                         ppo=PPOConfig(update_threads=1))
    lowlevel.train_lowlevel(cfg, args.out, args.out / "policies", show_progress=False, evaluate=False)
    policy = load_policy(args.out / "policies" / f"{cfg.name}.pt")
    for sees_agents in (False, True):
        task = TaskConfig(n_agents=FORMATION, mode="formation", obstacle_density=TABLE3_DENSITY,
                          episode_steps=TABLE3_STEPS, lidar_sees_agents=sees_agents)
        env = BatchedCEFCEnv(task, n_envs=TABLE3_EPISODES, seed=0)
        result = roll_out(env, env.reset(seed=0), policy.act, TABLE3_STEPS)
        print(f"evaluated with lidar_sees_agents={sees_agents}: "
              + ", ".join(f"{k} {v.mean():.2f}" for k, v in result.items()), flush=True)


if __name__ == "__main__":
    main()
