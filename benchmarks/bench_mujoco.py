"""Real-time factor of the MuJoCo world: full loop vs physics only, measured in the same run.

Full loop per decision step (0.1 s): observation assembly + one 3x128 MLP forward for all agents
(batch N, torch.set_num_threads(1)) -> MujocoWorld.step (50 physics steps at 500 Hz, each running
the compiled PX4-like cascade for every drone) -> LiDAR (mj_multiRay, 10 Hz). Physics only: the
same compiled scene stepped with `mj_step` alone (one Python call per step), each drone held up by
its weight in xfrc_applied (the world applies the rotor thrusts there).

    .venv/bin/python benchmarks/bench_mujoco.py            # 8, 16, 32, 64 drones, 30 obstacles
    .venv/bin/python benchmarks/bench_mujoco.py --drones 8 --seconds 20
    .venv/bin/python benchmarks/bench_mujoco.py --episode  # + wall time of Table VIII episodes

--episode also times whole Table VIII episodes (BatchedCEFCEnv: task core, observations, metrics,
LiDAR, the MLP policy; 1000 decision steps, density 0.05, anchor redraws) for 5 and 8 drones in
Wind-8, the conditions of the evaluation grid's slowest cells.

RTF = simulated seconds / wall seconds, best of `--rounds` alternating rounds of each.
Target: full loop >= 0.5 x physics-only, i.e. about 100x real time for 8 drones on one quiet
core. Since the rotor thrusts moved to xfrc_applied, physics-only runs twice as fast as before and the
ratio understates the full loop's gain; compare full-loop RTFs (docs/mujoco_world.md, Performance).
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np
import torch

from cefc_mj.sim.mujoco_world import MujocoWorld, MujocoWorldConfig

OBS_DIM = 63  # the low-level observation for K = 7 neighbours, M = 24 beams (docs/architecture.md)


def layout(n_agents: int, n_obstacles: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Agents on a 1.2 m grid around the origin, obstacles uniform in the 20 m arena clear of them."""
    side = int(np.ceil(np.sqrt(n_agents)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n_agents] * 1.2
    agents = grid - grid.mean(0)
    obstacles = []
    while len(obstacles) < n_obstacles:
        c = rng.uniform(-10, 10, 2)
        if np.min(np.abs(c[None] - agents).max(-1)) > 2.0 and all(np.linalg.norm(c - o) > 1.3 for o in obstacles):
            obstacles.append(c)
    return agents, np.array(obstacles).reshape(n_obstacles, 2)


def physics_only_rtf(world: MujocoWorld, seconds: float) -> float:
    """mj_step alone on the world's compiled model, drones hovering open loop."""
    model = world.models[0]
    data = mujoco.MjData(model)
    data.qpos[:] = world.datas[0].qpos
    data.xfrc_applied[world.drone_body_ids, 2] = world.airframe.mass * world.config.gravity
    mujoco.mj_forward(model, data)
    n = int(round(seconds / model.opt.timestep))
    start = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(model, data)
    return seconds / (time.perf_counter() - start)


def full_loop_rtf(world: MujocoWorld, policy: torch.nn.Module, seconds: float) -> tuple[float, dict[str, float]]:
    """Policy + world.step + LiDAR at 10 Hz; returns (RTF, wall seconds per component)."""
    n = world.n_agents
    ranges = world.lidar(world.agent_pos)
    parts = {"policy": 0.0, "step": 0.0, "lidar": 0.0}
    steps = int(round(seconds / world.dt))
    start = time.perf_counter()
    for _ in range(steps):
        t0 = time.perf_counter()
        pos, vel = world.agent_pos[0], world.agent_vel[0]
        obs = np.zeros((n, OBS_DIM), dtype=np.float32)
        obs[:, 0:2] = -pos  # anchor at the origin
        obs[:, 2:4] = vel
        obs[:, OBS_DIM - ranges.shape[-1]:] = ranges[0]
        with torch.no_grad():
            action = 2.0 * policy(torch.from_numpy(obs)).numpy().astype(np.float64)  # tanh -> +-2 m/s^2
        t1 = time.perf_counter()
        world.step(action[None], np.zeros((1, 2)))
        t2 = time.perf_counter()
        ranges = world.lidar(world.agent_pos)
        t3 = time.perf_counter()
        parts["policy"] += t1 - t0
        parts["step"] += t2 - t1
        parts["lidar"] += t3 - t2
    return seconds / (time.perf_counter() - start), {k: v / steps * 1e3 for k, v in parts.items()}


def episode_wall_time(formation: int, wind: float, steps: int, seed: int = 0) -> tuple[float, float]:
    """(wall seconds, C) of one Table VIII episode flown by an untrained 3x128 MLP (tanh, 2 m/s^2)."""
    from cefc_mj import make_world
    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.eval.runner import EpisodeSpec

    spec = EpisodeSpec(formation=formation, seed=seed, backend="mujoco", wind=wind, steps=steps)
    config = spec.task_config()
    env = BatchedCEFCEnv(config, n_envs=1, seed=seed, world=make_world("mujoco", config, n_envs=1, wind=wind, seed=seed))
    torch.manual_seed(seed)
    obs = env.reset()
    policy = torch.nn.Sequential(
        torch.nn.Linear(obs.shape[-1], 128), torch.nn.Tanh(), torch.nn.Linear(128, 128), torch.nn.Tanh(),
        torch.nn.Linear(128, 128), torch.nn.Tanh(), torch.nn.Linear(128, 2), torch.nn.Tanh(),
    )
    with torch.no_grad():
        policy[-2].weight.mul_(0.5)
    start = time.perf_counter()
    info: dict = {}
    for _ in range(steps):
        with torch.no_grad():
            action = 2.0 * policy(torch.as_tensor(obs, dtype=torch.float32)).numpy().astype(np.float64)
        obs, _, done, info = env.step(action)
        if done[0]:
            break
    return time.perf_counter() - start, float(env.episode_metrics()["C"][0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drones", type=int, nargs="+", default=[8, 16, 32, 64], help="UAV counts to measure")
    parser.add_argument("--obstacles", type=int, default=30, help="cylinder obstacles in the arena")
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per measurement")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per measurement (best kept)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episode", action="store_true", help="also time Table VIII episodes (5 and 8 drones, Wind-8)")
    parser.add_argument("--episode-steps", type=int, default=1000, help="decision steps per timed episode")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    policy = torch.nn.Sequential(
        torch.nn.Linear(OBS_DIM, 128), torch.nn.Tanh(), torch.nn.Linear(128, 128), torch.nn.Tanh(),
        torch.nn.Linear(128, 128), torch.nn.Tanh(), torch.nn.Linear(128, 2), torch.nn.Tanh(),
    )
    # gentle output weights: the swarm wanders without piling up
    with torch.no_grad():
        policy[-2].weight.mul_(0.5)
    print(f"{'drones':>6} {'physics-only RTF':>17} {'full-loop RTF':>14} {'ratio':>6}   ms per decision step: step / lidar / policy")
    rng = np.random.default_rng(args.seed)
    for n in args.drones:
        agents, obstacles = layout(n, args.obstacles, rng)
        world = MujocoWorld(MujocoWorldConfig(), n_envs=1, n_agents=n, n_obstacles=args.obstacles, seed=args.seed)
        world.reset(np.ones(1, bool), agents[None], np.array([[0.0, -9.5]]), obstacles[None])
        world.step(np.zeros((1, n, 2)), np.zeros((1, 2)))  # compile / warm up
        # alternate the two measurements and keep each one's best round: the machine is shared,
        # and load that hits one measurement but not the other would bias the ratio
        physics, full, parts = 0.0, 0.0, {}
        for _ in range(args.rounds):
            physics = max(physics, physics_only_rtf(world, args.seconds / args.rounds))
            rtf, round_parts = full_loop_rtf(world, policy, args.seconds / args.rounds)
            if rtf > full:
                full, parts = rtf, round_parts
        print(f"{n:>6} {physics:>17.1f} {full:>14.1f} {full / physics:>6.2f}   "
              f"{parts['step']:.2f} / {parts['lidar']:.2f} / {parts['policy']:.2f}")
    if args.episode:
        print(f"\nTable VIII episode, {args.episode_steps} decision steps, Wind-8 (wall seconds, best of {args.rounds}):")
        for formation in (5, 8):
            episode_wall_time(formation, 8.0, 5, seed=args.seed)  # warm up
            wall = min(episode_wall_time(formation, 8.0, args.episode_steps, seed=args.seed + r)[0] for r in range(args.rounds))
            print(f"  {formation} drones: {wall:.2f} s ({args.episode_steps * 0.1 / wall:.0f}x real time)")


if __name__ == "__main__":
    main()
