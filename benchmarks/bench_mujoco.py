"""Real-time factor of the MuJoCo world as users run it: Table VIII episodes vs raw mj_step, measured in one run.

Full loop: `cefc_mj.eval.runner.run_episode` flies the shipped AT-M policy (atm_c<c>_step3) through the
Table VIII scene (c UAVs, obstacles at 0.03 per m^2, 1000 decision steps, anchor redraws), exactly the
code `cefc-eval` runs: task core, observations, the policy, MujocoWorld.step (the compiled PX4-like
cascade + mj_step, 50 physics steps per decision step), LiDAR, metrics. Its wall time is the episode's
own (`EpisodeResult.wall_s`: reset to the last step; world construction and policy loading excluded).

Physics only: `mujoco.mj_step(model, data, nstep)` on the very MjModel that episode flew (obstacles in
place; fresh MjData, drones level where the episode left them), drones held up by their rotor
actuators (ctrl = m g / 4) or, for the external path, by their weight in xfrc_applied: the floor the
full loop can approach.

Both are measured for MujocoWorldConfig.rotor_actuation = "actuators" (the default: the airframe's
site-mounted thrust motors live in the scene) and "external" (no actuators, the rotor wrench in
xfrc_applied), alternating, best of `--rounds`. The external episodes go through the same
run_episode, with the world factory swapped for one that sets rotor_actuation="external" (nothing
else differs); their F, N, C are printed beside the default's (equal up to the last bits of the
physics, so usually identical). `--scaling` adds physics-only RTFs of both paths for 8..64 drones
(the site transmissions cost O(actuators x dofs) per mj_step).

    .venv/bin/python benchmarks/bench_mujoco.py                     # c = 8, calm air, 3 rounds
    .venv/bin/python benchmarks/bench_mujoco.py --formation 5 --wind 8 --rounds 5
    .venv/bin/python benchmarks/bench_mujoco.py --steps 300 --scaling

RTF = simulated seconds / wall seconds. Absolute figures move with the load of a shared machine; the
ratios measured in one run are what to compare.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np
import torch

import cefc_mj.eval.runner as runner
from cefc_mj.eval.runner import EpisodeSpec, load_policy_for, run_episode
from cefc_mj.sim.mujoco_world import MujocoWorld, MujocoWorldConfig, build_scene, make_mujoco_world

MODES = ("actuators", "external")


class _Capture:
    """The world factory run_episode calls, with rotor_actuation set; keeps the world and times its parts."""

    def __init__(self, mode: str):
        self.mode = mode
        self.world: MujocoWorld | None = None
        self.seconds = {"world.step": 0.0, "world.lidar": 0.0}

    def __call__(self, backend, config, n_envs=1, wind=0.0, seed=None):
        assert backend == "mujoco"
        world = make_mujoco_world(config, n_envs=n_envs, wind=wind, seed=seed,
                                  config=MujocoWorldConfig(rotor_actuation=self.mode))
        for name in ("step", "lidar"):
            method, key = getattr(world, name), f"world.{name}"

            def timed(*args, _method=method, _key=key):
                start = time.perf_counter()
                out = _method(*args)
                self.seconds[_key] += time.perf_counter() - start
                return out

            setattr(world, name, timed)  # the instance attribute shadows the method for the env's calls
        self.world = world
        return world


def episode(spec: EpisodeSpec, policy, mode: str) -> tuple[float, dict, MujocoWorld, dict]:
    """(full-loop RTF, metrics, the world, ms per decision step of world.step / world.lidar / the rest)."""
    capture = _Capture(mode)
    original = runner.make_world
    runner.make_world = capture
    try:
        result = run_episode(spec, policy=policy)
    finally:
        runner.make_world = original
    if result.diverged:
        raise SystemExit(f"episode diverged: {result.diverged}")
    ms = {k: v / result.steps * 1e3 for k, v in capture.seconds.items()}
    ms["rest"] = result.wall_s / result.steps * 1e3 - ms["world.step"] - ms["world.lidar"]
    return result.steps * spec.task_config().dt / result.wall_s, {k: getattr(result, k) for k in "FNC"}, capture.world, ms


def physics_only_rtf(model: mujoco.MjModel, qpos: np.ndarray, weight: float, n_drones: int, live: bool,
                     seconds: float) -> float:
    """Raw mj_step (nstep in C, no Python per step) on `model`, the drones level at their positions in
    `qpos` and hovering open loop (a tilted drone would fly off under constant rotor thrusts)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    drones = data.qpos[:7 * n_drones].reshape(n_drones, 7)
    drones[:, 3:] = (1.0, 0.0, 0.0, 0.0)
    if live:
        data.ctrl[:] = weight / 4.0
    else:
        data.xfrc_applied[1:n_drones + 1, 2] = weight
    mujoco.mj_forward(model, data)
    n = int(round(seconds / model.opt.timestep))
    start = time.perf_counter()
    mujoco.mj_step(model, data, nstep=n)
    return seconds / (time.perf_counter() - start)


def scaling(drones: list[int], obstacles: int, seconds: float, rounds: int) -> None:
    """Physics-only RTF of both rotor paths for larger swarms (hovering on a grid, `obstacles` parked)."""
    print(f"\nphysics only (raw mj_step, {obstacles} obstacles), RTF best of {rounds}:")
    print(f"{'drones':>6} {'actuators':>10} {'external':>9} {'actuators/external':>19}")
    for n in drones:
        best = {}
        for _ in range(rounds):
            for mode in MODES:
                config = MujocoWorldConfig(rotor_actuation=mode)
                model = build_scene(config, n, obstacles, False, 0.25)
                data = mujoco.MjData(model)
                side = int(np.ceil(np.sqrt(n)))
                qpos = data.qpos.reshape(n, 7)
                qpos[:, 0] = 1.2 * (np.arange(n) % side)
                qpos[:, 1] = 1.2 * (np.arange(n) // side)
                qpos[:, 2] = config.flight_altitude
                qpos[:, 3] = 1.0
                weight = model.body_mass[1] * config.gravity
                rtf = physics_only_rtf(model, data.qpos.copy(), weight, n, mode == "actuators", seconds)
                best[mode] = max(best.get(mode, 0.0), rtf)
        print(f"{n:>6} {best['actuators']:>10.1f} {best['external']:>9.1f} {best['actuators'] / best['external']:>19.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--formation", type=int, default=8, help="c: UAVs in the group (5..8, shipped policies)")
    parser.add_argument("--wind", type=float, default=0.0, help="mean wind speed (m/s)")
    parser.add_argument("--steps", type=int, default=1000, help="decision steps per episode (Table VIII: 1000)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds (best kept)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (the same layout every round)")
    parser.add_argument("--scaling", action="store_true", help="also physics-only RTFs for 8, 16, 32, 64 drones")
    args = parser.parse_args()
    torch.set_num_threads(1)
    spec = EpisodeSpec(formation=args.formation, seed=args.seed, wind=args.wind, steps=args.steps)
    policy = load_policy_for(spec.policy, spec.formation)
    warm = EpisodeSpec(formation=args.formation, seed=args.seed, wind=args.wind, steps=5)
    for mode in MODES:  # compile / load the kernels, warm caches
        episode(warm, policy, mode)

    sim_seconds = spec.steps * spec.task_config().dt
    full = {m: 0.0 for m in MODES}
    physics = {m: 0.0 for m in MODES}
    parts: dict[str, dict] = {}
    metrics: dict[str, dict] = {}
    for _ in range(args.rounds):
        # alternate everything: load that hits one measurement but not the other would bias the ratios
        for mode in MODES:
            rtf, metrics[mode], world, ms = episode(spec, policy, mode)
            if rtf > full[mode]:
                full[mode], parts[mode] = rtf, ms
            weight = world.airframe.mass * world.config.gravity
            physics[mode] = max(physics[mode], physics_only_rtf(
                world.models[0], world.datas[0].qpos.copy(), weight, world.n_drones, mode == "actuators", sim_seconds))

    print(f"Table VIII episode: c = {spec.formation}, {spec.condition}, {spec.steps} decision steps, seed {spec.seed}, "
          f"policy {policy.name}; RTF best of {args.rounds}")
    print(f"{'rotors':>10} {'full-loop RTF':>14} {'physics-only RTF':>17} {'full/physics':>13}   "
          f"ms per decision step: world.step / lidar / rest (task, policy)   F / N / C")
    for mode in MODES:
        m, p = metrics[mode], parts[mode]
        print(f"{mode:>10} {full[mode]:>14.1f} {physics[mode]:>17.1f} {full[mode] / physics[mode]:>13.2f}   "
              f"{p['world.step']:.2f} / {p['world.lidar']:.2f} / {p['rest']:.2f}"
              f"{'':>34}{m['F']:.0f} / {m['N']:.0f} / {m['C']:.2f}")
    print(f"live-actuator cost (external RTF / actuators RTF): full loop x{full['external'] / full['actuators']:.3f}, "
          f"raw mj_step x{physics['external'] / physics['actuators']:.3f}")
    if args.scaling:
        scaling([8, 16, 32, 64], 30, 10.0, args.rounds)


if __name__ == "__main__":
    main()
