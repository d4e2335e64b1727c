"""Speed of the MuJoCo evaluation loop as users run it, against raw mj_step, measured in one run.

(i) Table VIII: `cefc_mj.eval.runner.run_episode` flies the evaluator's default policy
(`cefc_mj.eval.DEFAULT_POLICY` of c) through the Table VIII scene (c UAVs, obstacles at 0.03 per m^2,
anchor redraws), called exactly as `cefc-eval` calls it (the benchmark only keeps a reference to the world
`runner.make_world` returns): task core, observations, the policy, MujocoWorld.step (the compiled PX4-like
cascade + mj_step, 50 physics steps per decision step), LiDAR, metrics. Its wall time is the episode's own
(`EpisodeResult.wall_s`: reset to the last step; world construction and policy loading excluded). Against
it, raw `mujoco.mj_step(model, data, nstep)` (nstep in C, no Python per step) on the very MjModel that
episode flew, two ways: from each decision step's physics state of that same episode (recorded in a
separate, untimed run of the same seed; the 50 physics steps that follow, thrusts held: the physics work
the episode itself asked of MuJoCo), and with the drones hovering open loop at their start positions for
the same simulated time (MuJoCo steps a drone at rest about 20 % faster than one in flight, so this
baseline is the faster one). Episodes and raw runs alternate, best of `--rounds` each; the ratio loop
RTF / raw RTF over the episode's own states is what to read (1.0 would be a loop that costs nothing
beside the physics). A breakdown (world.step, LiDAR, policy, the rest: task core and observations) comes
from one more, instrumented, episode. `--before` adds, in the same run, the loop as it was before the
speed-ups: LiDAR by `mj_multiRay` drone by drone, the policy through torch's nn.Module forward with the
free-space pass recomputed (the compiled kernel agrees with it to float32 rounding, so the two episodes
part ways after a while and their F / N / C differ as two seeds' would).

(ii) `--sweep 8,16,...,256`: one world of N drones (formation mode, obstacles at the Table VIII density
in an arena grown with N), the same per-step loop as run_episode for `--sweep-steps` decision steps,
the default policy of c = 8 reading each drone's 7 nearest neighbour slots (the env's observation has
N - 1, nearest first). Per N: RTF (x real time), cost per drone (wall us per drone per simulated second),
that cost relative to the first N of the sweep (1.00 = flat), and raw mj_step RTF of the same model.
`--sweep-rotors` picks MujocoWorldConfig.rotor_actuation ("external" by default: MuJoCo's site-actuator
transmission costs O(actuators x dofs) per mj_step, i.e. quadratic in the drone count, so "actuators"
cannot be flat).

(iii) `--scaling [8,64,256]`: the swarm loop of (ii) for each N with both rotor paths, "actuators" and
"external", interleaved round by round in one process (best of `--rounds`), plus raw mj_step of each
model (drones hovering); prints loop RTF of each path, external / actuators, and what the default
rotor_actuation = "auto" resolves to at that N (docs/research/mujoco_world.md, Performance).

`--smoke`: every mode at tiny sizes, one round (a few seconds; tests/test_benchmarks.py runs it).

    .venv/bin/python benchmarks/bench_mujoco.py                          # (i): c = 8, calm, 1000 steps, 3 rounds
    .venv/bin/python benchmarks/bench_mujoco.py --before --rounds 5
    .venv/bin/python benchmarks/bench_mujoco.py --steps 0 --sweep 8,16,32,64,128,256
    .venv/bin/python benchmarks/bench_mujoco.py --steps 0 --scaling 8,64,256 --scaling-steps 50

RTF = simulated seconds / wall seconds. Absolute figures move with the load of a shared machine; the
ratios measured in one run are what to compare.
"""

from __future__ import annotations

import argparse
import math
import time
from types import SimpleNamespace

import mujoco
import numpy as np
import torch

import cefc_mj.eval.runner as runner
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.eval.runner import TABLE8_DENSITY, EpisodeSpec, load_policy_for, run_episode
from cefc_mj.nn.policy_io import Policy
from cefc_mj.sim.mujoco_world import (
    AUTO_ACTUATORS_MAX_DRONES,
    MujocoWorld,
    MujocoWorldConfig,
    make_mujoco_world,
    resolve_rotor_actuation,
)
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.observation import low_level_layout


class _KeepWorld:
    """Wraps `runner.make_world`: calls it unchanged and keeps the world it returns; `before` switches the
    world to the per-drone mj_multiRay LiDAR; `timers` times world.step / world.lidar."""

    def __init__(self, before: bool = False, timers: dict | None = None):
        self.original = runner.make_world
        self.before, self.timers = before, timers
        self.world: MujocoWorld | None = None

    def __call__(self, *args, **kwargs):
        world = self.original(*args, **kwargs)
        if self.before:
            world._lidar_compiled = False
        if self.timers is not None:
            for name in ("step", "lidar"):
                setattr(world, name, _timed(getattr(world, name), self.timers, f"world.{name}"))
        self.world = world
        return world

    def __enter__(self):
        runner.make_world = self
        return self

    def __exit__(self, *exc):
        runner.make_world = self.original


def _timed(fn, timers: dict, key: str):
    timers.setdefault(key, 0.0)

    def wrapper(*args):
        start = time.perf_counter()
        out = fn(*args)
        timers[key] += time.perf_counter() - start
        return out

    return wrapper


def before_actions(policy: Policy):
    """The policy path before the speed-ups: nn.Module calls with F_a(d_free) recomputed every forward, as
    `Policy.act` computed it (same arithmetic, same bits)."""
    a = policy.actor

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            obs_t = torch.as_tensor(obs, dtype=torch.float32)
            f = a.formation(obs_t.index_select(-1, a.formation_index))
            mean = a.output(f + (a.obstacle(a.lidar_input(obs_t)) - a.obstacle(a.free_lidar)))
            return a.to_acceleration(mean, obs_t).numpy().astype(np.float64)

    return act


class _PolicyLike:
    """What run_episode reads of a Policy, with another action path for its actor."""

    def __init__(self, policy: Policy, actions):
        self.actor = SimpleNamespace(deterministic_actions=actions)
        self.act, self.name, self.obs_dim = actions, policy.name, policy.obs_dim
        self.task_for = policy.task_for  # the policy's own LiDAR (run_episode asks)


def raw_rtf(model: mujoco.MjModel, qpos: np.ndarray, n_drones: int, seconds: float) -> float:
    """Raw mj_step RTF on `model`: the drones level at their positions in `qpos`, hovering open loop (rotor
    actuators at m g / 4 each, or their weight in xfrc_applied without actuators)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    drones = data.qpos[: 7 * n_drones].reshape(n_drones, 7)
    drones[:, 3:] = (1.0, 0.0, 0.0, 0.0)
    weight = model.body_mass[1] * -model.opt.gravity[2]
    if model.nu:
        data.ctrl[:] = weight / 4.0
    else:
        data.xfrc_applied[1 : n_drones + 1, 2] = weight
    mujoco.mj_forward(model, data)
    n = int(round(seconds / model.opt.timestep))
    start = time.perf_counter()
    mujoco.mj_step(model, data, nstep=n)
    return seconds / (time.perf_counter() - start)


def replay_rtf(model: mujoco.MjModel, states: list[np.ndarray], n_substeps: int, dt: float) -> float:
    """Raw mj_step RTF over the states an episode flew through: from each decision step's physics state
    (mjSTATE_INTEGRATION: positions, velocities, rotor thrusts, applied forces, warm start), the
    n_substeps physics steps that follow, in C, with the thrusts held; setting the states is not timed."""
    data = mujoco.MjData(model)
    total = 0.0
    for state in states:
        mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
        start = time.perf_counter()
        mujoco.mj_step(model, data, nstep=n_substeps)
        total += time.perf_counter() - start
    return len(states) * dt / total


class _RecordStates(_KeepWorld):
    """A _KeepWorld that keeps env 0's physics state before every decision step."""

    def __init__(self):
        super().__init__()
        self.states: list[np.ndarray] = []

    def __call__(self, *args, **kwargs):
        world = super().__call__(*args, **kwargs)
        model, data, step = world.models[0], world.datas[0], world.step
        size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)

        def recording_step(*step_args):
            self.states.append(np.empty(size))
            mujoco.mj_getState(model, data, self.states[-1], mujoco.mjtState.mjSTATE_INTEGRATION)
            return step(*step_args)

        world.step = recording_step
        return world


def table8(args, policy: Policy) -> None:
    spec = EpisodeSpec(formation=args.formation, seed=args.seed, wind=args.wind, steps=args.steps)
    sim_seconds = spec.steps * spec.task_config().dt
    variants = {"now": policy}
    if args.before:
        variants["before"] = _PolicyLike(policy, before_actions(policy))
    for variant, pol in variants.items():  # compile / load the kernels, warm caches
        with _KeepWorld(before=variant == "before"):
            run_episode(EpisodeSpec(formation=args.formation, seed=args.seed, wind=args.wind, steps=5), policy=pol)
    with _RecordStates() as recorded:  # the states the timed episodes fly through (same seed, same bits)
        run_episode(spec, policy=policy)
    states, replay_world = recorded.states, recorded.world
    loop = {v: 0.0 for v in variants}
    raw = replay = 0.0
    metrics: dict[str, tuple] = {}
    for _ in range(args.rounds):  # alternate: load that hits one measurement but not the other would bias the ratios
        for variant, pol in variants.items():
            with _KeepWorld(before=variant == "before") as keep:
                result = run_episode(spec, policy=pol)
            if result.diverged:
                raise SystemExit(f"episode diverged: {result.diverged}")
            loop[variant] = max(loop[variant], result.steps * spec.task_config().dt / result.wall_s)
            metrics[variant] = (result.F, result.N, result.C)
            if variant == "now":
                world = keep.world
                raw = max(raw, raw_rtf(world.models[0], world.datas[0].qpos, world.n_drones, sim_seconds))
                replay = max(
                    replay, replay_rtf(replay_world.models[0], states, replay_world.n_substeps, spec.task_config().dt)
                )
    # breakdown: one instrumented episode (timers add a little overhead of their own)
    timers: dict[str, float] = {}
    timed_actor = _PolicyLike(policy, _timed(policy.actor.deterministic_actions, timers, "policy"))
    with _KeepWorld(timers=timers):
        result = run_episode(spec, policy=timed_actor)
    ms = {k: v / result.steps * 1e3 for k, v in timers.items()}
    rest = result.wall_s / result.steps * 1e3 - sum(ms.values())

    print(
        f"Table VIII episode: c = {spec.formation}, {spec.condition}, {spec.steps} decision steps, seed {spec.seed}, "
        f"policy {policy.name}, rotor_actuation {replay_world.config.rotor_actuation!r} -> "
        f"{replay_world.rotor_actuation_used!r}; best of {args.rounds}"
    )
    print(f"  raw mj_step, same model, the episode's own states:  RTF {replay:7.1f}")
    print(f"  raw mj_step, same model, drones hovering at start:   RTF {raw:7.1f}")
    for variant in variants:
        f, n, c = metrics[variant]
        print(
            f"  eval loop ({variant:>6}):     RTF {loop[variant]:7.1f}   "
            f"loop / raw mj_step = {loop[variant] / replay:.3f} (hovering: {loop[variant] / raw:.3f})   "
            f"F / N / C = {f:.0f} / {n:.0f} / {c:.2f}"
        )
    if args.before:
        print(f"  speed-up now / before: x{loop['now'] / loop['before']:.2f}")
    print(
        f"  ms per decision step (instrumented episode): world.step {ms['world.step']:.3f}, "
        f"LiDAR {ms['world.lidar']:.3f}, "
        f"policy {ms['policy']:.3f}, task core + observations {rest:.3f}"
    )


def sweep_config(n: int) -> TaskConfig:
    """Formation task for n drones: start square and arena grown with n (the start density of c = 8 in the
    4 m x 4 m square at most), Table VIII obstacle density."""
    start = max(2.0, math.sqrt(n / 8.0) * 2.0)
    return TaskConfig(
        n_agents=n,
        mode="formation",
        obstacle_density=TABLE8_DENSITY,
        start_half_size=start,
        arena_half_size=start + 8.0,
        anchor_half_size=start + 4.0,
        episode_steps=10_000,
    )


def nearest_slots(config: TaskConfig, slots: int = 7) -> np.ndarray:
    """Observation columns that make the K = `slots` observation out of the env's K = N - 1 one (neighbours
    come nearest first): what a c = 8 policy reads."""
    layout = low_level_layout(config)
    cols = np.arange(layout.size)
    return np.concatenate(
        [
            cols[layout["anchor"]],
            cols[layout["own_velocity"]],
            cols[layout["neighbours"]][: 4 * slots],
            cols[layout["neighbour_mask"]][:slots],
            cols[layout["lidar"]],
        ]
    )


def swarm_loop(n: int, mode: str, policy: Policy, steps: int, seed: int) -> tuple[float, dict, MujocoWorld]:
    """One world of n drones (sweep_config) flown for `steps` decision steps by `policy` on the 7 nearest
    neighbour slots, rotor_actuation = mode: (loop RTF, parts in us per drone per decision step, the world).
    World construction and the first (warm-up) step are not timed."""
    config = policy.task_for(sweep_config(n))
    cols = nearest_slots(config)
    world = make_mujoco_world(config, seed=seed, config=MujocoWorldConfig(rotor_actuation=mode))
    env = BatchedCEFCEnv(config, n_envs=1, seed=seed, world=world)
    timers: dict[str, float] = {}
    world.step = _timed(world.step, timers, "world.step")
    world.lidar = _timed(world.lidar, timers, "lidar")
    act = _timed(lambda obs: policy.actor.deterministic_actions(obs[..., cols]), timers, "policy")
    obs = env.reset()
    env.step(act(obs))  # warm
    timers.update({k: 0.0 for k in timers})
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, _, _ = env.step(act(obs))
    wall = time.perf_counter() - start
    parts = {k: v / steps / n * 1e6 for k, v in timers.items()}
    parts["task"] = wall / steps / n * 1e6 - sum(parts.values())
    return steps * config.dt / wall, parts, world


def sweep(args, policy: Policy) -> None:
    drones = [int(x) for x in args.sweep.split(",")]
    print(
        f"\nDrones sweep: one world, formation mode, policy {policy.name} on the 7 nearest neighbour slots, "
        f"{args.sweep_steps} decision steps, best of {args.rounds}; cost = wall us per drone per simulated second, "
        f"parts in us per drone per decision step"
    )
    for mode in args.sweep_rotors.split(","):
        print(f"rotor_actuation = {mode!r}")
        print(
            f"{'drones':>7} {'loop RTF':>9} {'raw RTF':>8} {'loop/raw':>9} {'cost/drone':>11} {f'vs {drones[0]}':>7}"
            f"   {'world.step':>10} {'LiDAR':>6} {'policy':>7} {'task':>6}"
        )
        reference = None
        for n in drones:
            best, best_raw, parts = 0.0, 0.0, {}
            for _ in range(args.rounds):
                rtf, round_parts, world = swarm_loop(n, mode, policy, args.sweep_steps, args.seed)
                if rtf > best:
                    best, parts = rtf, round_parts
                best_raw = max(
                    best_raw, raw_rtf(world.models[0], world.datas[0].qpos, world.n_drones, args.sweep_steps * world.dt)
                )
            cost = 1e6 / (best * n)
            reference = reference or cost
            print(
                f"{n:>7} {best:>9.1f} {best_raw:>8.1f} {best / best_raw:>9.3f} {cost:>11.1f} {cost / reference:>7.2f}"
                f"   {parts['world.step']:>10.1f} {parts['lidar']:>6.1f} {parts['policy']:>7.1f} {parts['task']:>6.1f}"
            )


ROTOR_PATHS = ("actuators", "external")


def scaling(args, policy: Policy) -> None:
    """(iii): both rotor paths per N, interleaved round by round, best of args.rounds."""
    drones = [int(x) for x in args.scaling.split(",")]
    print(
        f"\nRotor paths by swarm size: one world, formation mode, policy {policy.name} on the 7 nearest "
        f"neighbour slots, {args.scaling_steps} decision steps, both paths interleaved, best of {args.rounds}; "
        f"RTF = x real time (full loop; raw: mj_step alone, drones hovering)"
    )
    for n in drones:
        loop = {m: 0.0 for m in ROTOR_PATHS}
        raw = {m: 0.0 for m in ROTOR_PATHS}
        for _ in range(args.rounds):
            for mode in ROTOR_PATHS:
                rtf, _, world = swarm_loop(n, mode, policy, args.scaling_steps, args.seed)
                assert world.rotor_actuation_used == mode
                loop[mode] = max(loop[mode], rtf)
                raw[mode] = max(
                    raw[mode],
                    raw_rtf(world.models[0], world.datas[0].qpos, world.n_drones, args.scaling_steps * world.dt),
                )
        print(
            f"{n:>5} drones   actuators: loop RTF {loop['actuators']:7.2f} (raw {raw['actuators']:7.2f})   "
            f"external: loop RTF {loop['external']:7.2f} (raw {raw['external']:7.2f})   "
            f"external / actuators x{loop['external'] / loop['actuators']:.2f} "
            f"(raw x{raw['external'] / raw['actuators']:.2f})   auto -> {resolve_rotor_actuation('auto', n)}",
            flush=True,
        )


SMOKE = dict(steps=10, rounds=1, sweep_steps=3, scaling_steps=3)
"""--smoke: tiny sizes, one round; the sweep and scaling sizes become 8 and AUTO_ACTUATORS_MAX_DRONES + 1
drones (either side of the "auto" cross-over) where they were asked for."""
SMOKE_DRONES = f"8,{AUTO_ACTUATORS_MAX_DRONES + 1}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--formation", type=int, default=8, help="c: UAVs in the group (5..8, shipped policies)")
    parser.add_argument("--wind", type=float, default=0.0, help="mean wind speed (m/s)")
    parser.add_argument(
        "--steps", type=int, default=1000, help="decision steps per episode (Table VIII: 1000; 0 skips (i))"
    )
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds (best kept)")
    parser.add_argument("--seed", type=int, default=0, help="episode seed (the same layout every round)")
    parser.add_argument("--before", action="store_true", help="also the loop before the speed-ups (same numbers)")
    parser.add_argument("--sweep", default="", help="comma-separated drone counts for the scaling sweep (ii)")
    parser.add_argument("--sweep-steps", type=int, default=100, help="decision steps per sweep run")
    parser.add_argument(
        "--sweep-rotors", default="external", help="rotor_actuation modes for the sweep, comma-separated"
    )
    parser.add_argument(
        "--scaling",
        nargs="?",
        const="8,64,256",
        default="",
        help="(iii): comma-separated drone counts flown with both rotor paths (default 8,64,256)",
    )
    parser.add_argument("--scaling-steps", type=int, default=50, help="decision steps per scaling run")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="tiny sizes, one round: every asked-for mode runs in seconds (tests/test_benchmarks.py)",
    )
    args = parser.parse_args()
    if args.smoke:
        for name, value in SMOKE.items():
            if name != "steps" or args.steps > 0:
                setattr(args, name, value)
        args.sweep = SMOKE_DRONES if args.sweep else ""
        args.scaling = SMOKE_DRONES if args.scaling else ""
    torch.set_num_threads(1)
    policy = load_policy_for(DEFAULT_POLICY, args.formation)
    if args.steps > 0:
        table8(args, policy)
    if args.sweep or args.scaling:
        swarm_policy = load_policy_for(DEFAULT_POLICY, 8)
        if args.sweep:
            sweep(args, swarm_policy)
        if args.scaling:
            scaling(args, swarm_policy)


if __name__ == "__main__":
    main()
