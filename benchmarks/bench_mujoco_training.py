"""Speed of training in MuJoCo (`cefc-train lowlevel --backend mujoco`) against training in the
particle world, measured in one run, on the training loop itself.

Each case builds the MAPPO trainer exactly as `cefc_mj.train.lowlevel.train_lowlevel` does for its
stage (the same env factory, the same rollout workers) and times whole iterations, `MAPPO.iterate()`:
episodes collected (the cascade, mj_step, LiDAR, observations, rewards, the policy sampling actions)
and the PPO update. Cases, interleaved round by round, best of `--rounds`:

    particle        the paper's world (AT-M-Nav's fine-tune settings), one process
    mujoco W=1      the MuJoCo fine-tune (acceleration interface, wind 0-8 m/s, deviation 0-0.8 m), one process
    mujoco W=k      the same with k rollout worker processes (`--workers`, default 2)
    mujoco earlier  mujoco W=1 with the reset every env used to get after an iteration's last step
                    (thrown away: the next iteration resets from its seed), timed with the iteration

Printed per case: agent-steps per second, per core used (k worker processes + the learner, which waits
while they collect, count as k cores), and the ratios MuJoCo / particle, W=k / W=1 and W=1 / earlier
(what dropping the wasted reset gained). The ratios are
what to read: absolute figures move with the load of a shared machine.

    .venv/bin/python benchmarks/bench_mujoco_training.py                 # c = 6, 20 envs, 3 rounds
    .venv/bin/python benchmarks/bench_mujoco_training.py --workers 4 --rounds 5
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from cefc_mj.nn.atm import Critic
from cefc_mj.nn.policy_io import load_actor, resolve_policy_path
from cefc_mj.train.config import Budget, LowLevelConfig, MujocoTraining, PPOConfig
from cefc_mj.train.lowlevel import critic_input_size, mujoco_training_env, task_config_for
from cefc_mj.train.mappo import MAPPO, particle_env


def trainer_for(formation: int, n_envs: int, workers: int | None) -> MAPPO:
    """The trainer of a fine-tune of atm_c<formation>_nav: particle (workers None) or MuJoCo."""
    mujoco = None if workers is None else MujocoTraining(rollout_workers=workers, critic_warmup=0)
    cfg = LowLevelConfig(
        formation=formation,
        step=3,
        navigation_weight=10.0,
        deviation=0.8 if mujoco else 0.0,
        deviation_sampling="uniform",
        budget=Budget(iterations=1),
        ppo=PPOConfig(n_envs=n_envs, update_threads=1),
        mujoco=mujoco,
    )
    task = task_config_for(cfg)
    actor = load_actor(resolve_policy_path(f"atm_c{formation}_nav"))[0]
    make_env = particle_env if mujoco is None else functools.partial(mujoco_training_env, training=mujoco)
    critic = Critic(critic_input_size(cfg, task))
    return MAPPO(task, cfg.ppo, actor, critic, seed=0, make_env=make_env, rollout_workers=workers or 1)


def timed_iteration(trainer: MAPPO, earlier: bool) -> float:
    """Agent-steps per second of one iteration (collect + update), on the wall clock around it;
    `earlier`: plus the reset of every env after the last step that iterations used to do."""
    before = trainer.agent_steps
    t0 = time.perf_counter()
    trainer.iterate()
    if earlier:
        trainer.env.reset(mask=np.ones(trainer.env.n_envs, bool))
    return (trainer.agent_steps - before) / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--formation", type=int, default=6, help="c (default 6)")
    p.add_argument("--envs", type=int, default=20, help="envs per iteration (default 20, the trainers')")
    p.add_argument("--workers", type=int, default=2, help="rollout processes of the parallel case (default 2)")
    p.add_argument("--rounds", type=int, default=3, help="iterations timed per case, best kept (default 3)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes, one round (for the test suite)")
    args = p.parse_args(argv)
    if args.smoke:
        args.formation, args.envs, args.workers, args.rounds = 3, 2, 2, 1
    if args.envs % args.workers:
        p.error(f"--workers {args.workers}: must divide --envs {args.envs}")
    torch.set_num_threads(1)
    cases = {"particle": None, "mujoco W=1": 1, "mujoco earlier": 1, f"mujoco W={args.workers}": args.workers}
    trainers = {name: trainer_for(args.formation, args.envs, w) for name, w in cases.items()}
    best = dict.fromkeys(cases, 0.0)
    try:
        for name, trainer in trainers.items():  # warm-up: kernels, worker start, first allocations
            timed_iteration(trainer, name == "mujoco earlier")
        for _ in range(args.rounds):
            for name, trainer in trainers.items():
                best[name] = max(best[name], timed_iteration(trainer, name == "mujoco earlier"))
    finally:
        for trainer in trainers.values():
            trainer.close()
    print(f"c = {args.formation}, {args.envs} envs per iteration, best of {args.rounds} iteration(s)")
    print(f"{'case':<14} {'agent-steps/s':>14} {'per core':>10}")
    for name, w in cases.items():
        cores = 1 if w in (None, 1) else w
        print(f"{name:<14} {best[name]:>14,.0f} {best[name] / cores:>10,.0f}")
    many = f"mujoco W={args.workers}"
    print(
        f"mujoco / particle: {best['mujoco W=1'] / best['particle']:.3f}   "
        f"W={args.workers} / W=1: x{best[many] / best['mujoco W=1']:.2f} on {args.workers} cores   "
        f"W=1 / earlier: x{best['mujoco W=1'] / best['mujoco earlier']:.3f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
