"""`run_sitl_episode`: one evaluation episode with every UAV's policy in its own OS process (SITL-M).

The MuJoCo world and the task core (`BatchedCEFCEnv`, here `DropoutCEFCEnv`) run in the calling
process; each agent (`cefc_mj.deploy.agent`) runs in its own process with its own copy of the
policy, local or on another machine, and talks to the simulator over ZeroMQ (`SitlServer`). Per
decision step (0.1 s) the simulator sends every flying agent its sensor packet, then flies the step
in control ticks (0.01 s on MuJoCo), applying at each tick the newest setpoint that has taken effect
(zero-order hold; timing model in `cefc_mj.deploy.sim_server` and docs/research/sitl_m.md).

>>> from cefc_mj.eval.runner import EpisodeSpec
>>> result = run_sitl_episode(EpisodeSpec(formation=5, seed=0, steps=50), SitlConfig())  # doctest: +SKIP
>>> result.F, result.N, result.C, result.sitl.summary()["round_trip_ms"]["all"]["p50"]  # doctest: +SKIP
"""

from __future__ import annotations

import math
import signal
import sys
import time
from dataclasses import dataclass

import numpy as np

from cefc_mj.deploy.dropout import DropoutCEFCEnv, check_drop, choose_dropouts, dropout_report
from cefc_mj.deploy.results import SitlEpisodeResult, SitlStats
from cefc_mj.deploy.sim_server import (  # noqa: F401
    OFFBOARD_LOSS_TIMEOUT_S,
    AgentError,
    AgentFleet,
    SitlServer,
    block_sigint,
    restore_sigint,
)
from cefc_mj.deploy.tick_world import make_ticked_world
from cefc_mj.errors import ConfigError, SimulationDiverged
from cefc_mj.eval.runner import EpisodeSpec, wind_direction_flown
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.guard import guarded

FAULT_ACTIONS = ("kill", "stop")


@dataclass(frozen=True)
class AgentFault:
    """A fault injected into one local agent process; its vehicle stays in the world."""

    uav: int
    """The UAV whose agent is hit."""
    step: int
    """Before which decision step."""
    action: str = "kill"
    """"kill" (SIGKILL: the process dies) or "stop" (SIGSTOP: the process hangs)."""


@dataclass(frozen=True)
class SitlConfig:
    """How a SITL-M episode is deployed. Defaults: every agent a local process on 127.0.0.1, no
    extra link delay, as fast as the agents allow."""

    bind: str = "tcp://127.0.0.1:*"
    """ZeroMQ endpoint the simulator binds; "*" as the port picks a free one. Bind
    "tcp://0.0.0.0:5555" to let agents on other machines connect to tcp://<this host>:5555."""
    remote_agents: tuple[int, ...] = ()
    """UAV indices whose agents are started elsewhere (`cefc-agent --connect ... --uav I`); the
    simulator waits `startup_timeout_s` for them. All others are spawned locally."""
    agent_command: tuple[str, ...] | None = None
    """Command that starts a local agent (the flags --connect/--uav/--policy/--parent-pid are
    appended); None: this Python with `-m cefc_mj.deploy.agent`."""
    control_tick_s: float | None = None
    """Control tick (s) at which setpoints take effect; None: 0.01 on MuJoCo (one PX4 position-loop
    period), the decision step on the particle world (it has no finer step)."""
    link_delay_ms: float = 0.0
    """One-way network delay added in simulated time to each packet and each reply (ms)."""
    jitter_ms: float = 0.0
    """Each direction adds a further uniform draw from [0, jitter_ms] (seeded by the episode seed)."""
    offboard_loss_timeout_s: float = OFFBOARD_LOSS_TIMEOUT_S
    """PX4's COM_OF_LOSS_T: simulated seconds without a new setpoint before a vehicle holds."""
    realtime: bool = False
    """Pace the simulation to the wall clock (1 simulated second per second)."""
    lockstep: bool = False
    """Verification mode: wait for every flying agent's reply to packet k and fly it for the whole
    of step k (the lock-step runner's semantics over the wire)."""
    drop: tuple[int, int] | None = None
    """(k, step): k UAVs (seeded choice) leave the swarm before decision step `step`: their agents
    are killed (see drop_action), their vehicles parked out of the arena, and the task's group and
    metrics become c - k (docs/sitl_m.md). Fly policy "student" for the paper's Fig. 4b."""
    drop_action: str = "kill"
    """How the dropped local agents go: "kill" (SIGKILL) or "stop" (SIGSTOP); remote ones are told to stop."""
    faults: tuple[AgentFault, ...] = ()
    """Faults injected into local agent processes (their vehicles stay and fail safe)."""
    startup_timeout_s: float = 120.0
    """Wall seconds for every agent to connect, load its policy and report ready."""
    heartbeat_timeout_s: float = 5.0
    """Agents exit after this many wall seconds without a message from the simulator."""
    lockstep_timeout_s: float = 10.0
    """Lock-step mode: wall seconds to wait for a reply before the vehicle holds."""
    lockstep_delay_s: float = 0.0
    """Lock-step mode only: each command takes effect this long (simulated s, rounded up to the
    control tick) after its packet, the world then advancing by control ticks; 0: for the whole step,
    the one-process game's semantics. One tick (0.01 s on MuJoCo) is the delay an asynchronous run
    has when every decision comes back within the tick, without the scheduler's variation."""
    verbose_agents: bool = False
    """Let the agents log to their (captured) stderr."""

    def validate(self) -> None:
        """ConfigError naming the first bad field."""
        for name in ("link_delay_ms", "jitter_ms"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ConfigError(f"{name}={value!r}: must be a finite number >= 0")
        for name in ("offboard_loss_timeout_s", "startup_timeout_s", "heartbeat_timeout_s", "lockstep_timeout_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(f"{name}={value!r}: must be a finite number > 0")
        if self.control_tick_s is not None and not (
            isinstance(self.control_tick_s, (int, float))
            and math.isfinite(self.control_tick_s)
            and self.control_tick_s > 0
        ):
            raise ConfigError(f"control_tick_s={self.control_tick_s!r}: must be a finite number > 0 or None")
        if "://" not in str(self.bind):
            raise ConfigError(f"bind={self.bind!r}: not a ZeroMQ endpoint (e.g. tcp://127.0.0.1:5555)")
        delay = self.lockstep_delay_s
        if not isinstance(delay, (int, float)) or not math.isfinite(delay) or delay < 0:
            raise ConfigError(f"lockstep_delay_s={delay!r}: must be a finite number >= 0")
        if delay and not self.lockstep:
            raise ConfigError("lockstep_delay_s: only for lockstep=True (an asynchronous run has its measured delays)")
        if self.drop_action not in FAULT_ACTIONS:
            raise ConfigError(f"drop_action={self.drop_action!r}: must be one of {', '.join(FAULT_ACTIONS)}")
        for fault in self.faults:
            if not isinstance(fault, AgentFault) or fault.action not in FAULT_ACTIONS:
                raise ConfigError(f"faults: {fault!r} is not an AgentFault with action kill or stop")


def server_options(sitl: SitlConfig) -> dict:
    """The `SitlServer` keyword arguments a SitlConfig sets (timing, link, failsafe, lock-step)."""
    return {
        "link_delay_ms": sitl.link_delay_ms,
        "jitter_ms": sitl.jitter_ms,
        "offboard_loss_timeout_s": sitl.offboard_loss_timeout_s,
        "realtime": sitl.realtime,
        "lockstep": sitl.lockstep,
        "lockstep_timeout_s": sitl.lockstep_timeout_s,
        "lockstep_delay_s": sitl.lockstep_delay_s,
    }


def control_tick(sitl: SitlConfig, backend: str, dt: float) -> float:
    """The tick (s) at which setpoints take effect: the whole step in plain lock-step mode, else
    `control_tick_s` (default 0.01 s on MuJoCo, one PX4 position-loop period; the step on the particle
    world, which has no finer step)."""
    if sitl.lockstep and not sitl.lockstep_delay_s:
        return dt
    return sitl.control_tick_s if sitl.control_tick_s is not None else (0.01 if backend == "mujoco" else dt)


def check_faults(sitl: SitlConfig, n_uavs: int, steps: int, what: str) -> None:
    """ConfigError unless every injected fault names a local UAV and a step of the `what` (episode, game)."""
    for fault in sitl.faults:
        if not 0 <= fault.uav < n_uavs or not 0 <= fault.step < steps:
            raise ConfigError(f"faults: {fault} is outside the {what} (uav 0..{n_uavs - 1}, step 0..{steps - 1})")
        if fault.uav in sitl.remote_agents:
            raise ConfigError(f"faults: uav {fault.uav}'s agent is remote; only local processes can be signalled")


def _check(spec: EpisodeSpec, sitl: SitlConfig) -> tuple[float, tuple[int, int] | None, TaskConfig]:
    """Everything checked before a process starts; returns (control tick, drop, the game with the
    policy's LiDAR)."""
    from cefc_mj.eval.runner import load_policy_for

    sitl.validate()
    config = spec.task_config()  # validates the game
    if spec.backend not in ("mujoco", "particle"):
        raise ConfigError(f"backend={spec.backend!r}: must be mujoco or particle")
    tick = control_tick(sitl, spec.backend, config.dt)
    drop = check_drop(sitl.drop, spec.formation, spec.steps)
    for uav in sitl.remote_agents:
        if not isinstance(uav, int) or not 0 <= uav < spec.formation:
            raise ConfigError(f"remote_agents: {uav!r} is not a UAV index 0..{spec.formation - 1}")
    check_faults(sitl, spec.formation, spec.steps, "episode")
    policy = load_policy_for(spec.policy, spec.formation)  # an unknown policy fails here, not in N processes
    return tick, drop, policy.task_for(config), policy


def ticked_episode_env(spec: EpisodeSpec, config: TaskConfig, tick: float):
    """(world, env) of one SITL-M episode: the spec's world stepped at the control tick `tick`, and the
    task core over it."""
    world = make_ticked_world(
        spec.backend,
        config,
        tick,
        wind=spec.wind,
        seed=spec.seed,
        airframe=spec.mujoco_airframe,
        wind_direction=spec.wind_direction,
        rotor_actuation=spec.rotor_actuation,
    )
    return world, DropoutCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)


def warm_up_kernels(spec: EpisodeSpec, config: TaskConfig, tick: float, policy) -> None:
    """Compile (a cold numba cache) or load every kernel the episode runs, here, before any agent starts.

    The simulator's first steps would otherwise compile for tens of seconds while the agents, already
    flying, hear nothing and leave at their heartbeat timeout; and c agents compiling the same kernels
    at once would share the CPUs c ways. A throwaway world of the same game flies two steps (and its
    metrics), and the agents' decision code runs on a probe, so the agents load from a warm cache."""
    from cefc_mj.deploy.agent import low_level_act, warm_up_low_level

    fly_throwaway(*ticked_episode_env(spec, config, tick), spec.formation)
    warm_up_low_level(low_level_act(policy, config), config)


def fly_throwaway(world, env, n_agents: int, steps: int = 2) -> None:
    """Fly a throwaway ticked world and its env `steps` decision steps with zero setpoints, and take its
    metrics: every kernel of the episode's loop runs once (the warm-ups before the agents start)."""
    world.controller = lambda j: np.zeros((1, n_agents, 2))
    env.reset()
    for _ in range(steps):
        env.step(np.zeros((1, n_agents, 2)))
    env.episode_metrics()


def run_sitl_episode(spec: EpisodeSpec, sitl: SitlConfig = SitlConfig(), record: bool = False) -> SitlEpisodeResult:
    """Fly one episode with every UAV's policy in its own process (module docstring; docs/sitl_m.md).

    Returns the lock-step runner's result type (F, N, C over the episode, steps, wall_s, diverged,
    record) with `sitl` (SitlStats: per-agent latency, round trip and command age samples, events)
    and, with `sitl.drop`, `dropout` (F/N/C before and after). Raises ConfigError for a bad spec or
    config and AgentError when the agents cannot start; every agent process is gone when it returns
    or raises (Ctrl-C included).
    """
    tick, drop, config, policy = _check(spec, sitl)
    warm_up_kernels(spec, config, tick, policy)
    world, env = ticked_episode_env(spec, config, tick)
    welcome = {"formation": spec.formation, "task": config.to_dict(), "heartbeat_timeout_s": sitl.heartbeat_timeout_s}
    server = SitlServer(sitl.bind, spec.formation, welcome, world.tick_s, seed=spec.seed, **server_options(sitl))
    fleet = None
    try:
        local = [i for i in range(spec.formation) if i not in sitl.remote_agents]
        command = list(sitl.agent_command) if sitl.agent_command else [sys.executable, "-m", "cefc_mj.deploy.agent"]
        if local:
            fleet = AgentFleet(command, server.local_endpoint, spec.policy, local, sitl.verbose_agents)
            fleet.spawn()
        if sitl.remote_agents:
            print(
                f"SITL-M: waiting for agents {list(sitl.remote_agents)} at {server.endpoint}",
                file=sys.stderr,
                flush=True,
            )
        startup_s = server.wait_until_ready(sitl.startup_timeout_s, fleet)
        if fleet is not None:
            for uav in local:
                if not fleet.adopt(uav, server.vehicles[uav].info.get("pid", -1)):
                    server.event(
                        uav, "not_adopted", "the agent's pid is not a local agent process: faults cannot reach it"
                    )
        return _fly(spec, sitl, env, world, server, fleet, drop, startup_s, record)
    finally:  # Ctrl-C waits until every agent process is gone
        previous = block_sigint()
        try:
            server.stop_all("episode over")
            if fleet is not None:
                fleet.shutdown()
            server.close()
        finally:
            restore_sigint(previous)


TIMING_SCALARS = {
    "sitl_decision_latency_ms": "latency_ms",
    "sitl_round_trip_ms": "round_trip_ms",
    "sitl_command_age_ms": "age_ms",
}
"""Per-step SITL-M timing recorded for Rerun (name -> the per-vehicle sample list it reads)."""


def note_exits_and_faults(server: SitlServer, fleet: AgentFleet | None, faults) -> None:
    """Before a step: tell the server which agent processes exited, and inject this step's faults
    (SIGKILL or SIGSTOP to the UAV's local process), each logged as an event."""
    if fleet is not None:
        for uav in fleet.poll_exits():
            server.agent_exited(uav)
    for fault in faults:
        sig = signal.SIGKILL if fault.action == "kill" else signal.SIGSTOP
        delivered = fleet is not None and fleet.signal(fault.uav, sig)
        server.event(fault.uav, f"fault_{fault.action}", "injected" if delivered else "no local process to signal")


def _fly(spec, sitl, env, world, server: SitlServer, fleet: AgentFleet | None, drop, startup_s, record):
    from cefc_mj.eval.runner import _Recorder

    config = env.config
    n_ticks = world.n_ticks
    recorder = _Recorder(env, spec) if record else None
    dropped = choose_dropouts(spec.formation, drop[0], spec.seed) if drop else []
    faults = {}
    for fault in sitl.faults:
        faults.setdefault(fault.step, []).append(fault)
    step_index = 0
    timing: dict[str, list[float]] = {name: [] for name in TIMING_SCALARS}

    def controller(j: int) -> np.ndarray:
        accel, hold = server.control(step_index * n_ticks + j)
        if hold.any():
            accel[hold] = world.brake_accel(config.accel_max)[0, hold]
        return accel[None]

    world.controller = controller
    env.reset()
    start = time.perf_counter()
    diverged = None
    for k in range(spec.steps):
        step_index = k
        t = k * config.dt
        server.step, server.t_now = k, t
        note_exits_and_faults(server, fleet, faults.get(k, []))
        if drop and k == drop[1]:
            for uav in dropped:
                if fleet is not None:
                    fleet.signal(uav, signal.SIGKILL if sitl.drop_action == "kill" else signal.SIGSTOP)
                server.remove(uav, f"dropout ({sitl.drop_action})")
            env.remove_agents(0, dropped)
        server.send_sensors(
            k,
            t,
            env.perceived_pos[0],
            world.agent_vel[0],
            env.lidar[0],
            env.anchor[0],
            world.agent_pos[0],
            config.observation_distance,
        )
        server.await_replies()
        try:
            _, _, done, _ = env.step(np.zeros((1, spec.formation, 2)))  # the controller supplies the setpoints
        except SimulationDiverged as e:
            diverged = str(e)
            break
        if recorder is not None:
            recorder.capture()
            for name, attr in TIMING_SCALARS.items():  # the newest sample of each vehicle, worst over vehicles
                latest = [getattr(v, attr)[-1] for v in server.vehicles if len(getattr(v, attr))]
                timing[name].append(max(latest) if latest else 0.0)
        if done[0]:
            break
    loop_wall = time.perf_counter() - start
    metrics = env.episode_metrics()
    vehicles = server.vehicles
    local = set(fleet.uavs) if fleet is not None else set()
    stats = SitlStats(
        decision_latency_ms=[np.asarray(v.latency_ms) for v in vehicles],
        round_trip_ms=[np.asarray(v.round_trip_ms) for v in vehicles],
        command_age_ms=[np.asarray(v.age_ms) for v in vehicles],
        late_commands=np.array([v.late for v in vehicles]),
        skipped_packets=np.array([v.skipped + len(v.outstanding) for v in vehicles]),
        ignored_replies=np.array([v.ignored for v in vehicles]),
        malformed=server.malformed,
        malformed_reasons=dict(server.malformed_reasons),
        events=list(server.events),
        control_tick_s=world.tick_s,
        startup_s=startup_s,
        loop_wall_s=loop_wall,
        sim_s=int(env.t[0]) * config.dt,
        agents=[{**v.info, "local": v.index in local} for v in vehicles],
    )
    record = recorder.finish() if recorder is not None and int(env.t[0]) > 0 else None
    if record is not None:  # Rerun draws these under metrics/ beside F, N, C
        record.scalars.update({name: np.asarray(series, dtype=np.float64) for name, series in timing.items()})
    return SitlEpisodeResult(
        spec=spec,
        F=float(metrics["F"][0]),
        N=float(metrics["N"][0]),
        C=float(metrics["C"][0]),
        steps=int(env.t[0]),
        wall_s=loop_wall,
        diverged=diverged,
        wind_direction_flown=wind_direction_flown(world),
        record=record,
        sitl=stats,
        dropout=dropout_report(env, dropped, drop[1]) if drop else None,
        mode="SITL-M",
    )


def run_latency_model_episode(
    spec: EpisodeSpec, latency_ticks: int = 1, control_tick_s: float | None = None, policy=None
) -> SitlEpisodeResult:
    """The deterministic, one-process model of a SITL-M episode: the lock-step episode on the
    ticked world where each decision takes effect `latency_ticks` control ticks after its packet
    (held until the next one does), and each agent's policy runs on its own observation (batch of 1,
    as in its process). A SITL-M episode whose commands all took effect at their modelled tick
    (no late commands, every command age latency_ticks x tick) is this episode bit for bit; so the
    model separates what the modelled latency costs from what a loaded machine's late replies add.
    Returns mode "lock-step" and no SITL stats."""
    import torch

    from cefc_mj.eval.runner import episode_fields, fly, load_policy_for

    torch.set_num_threads(1)
    config = spec.task_config()
    tick = control_tick_s if control_tick_s is not None else (0.01 if spec.backend == "mujoco" else config.dt)
    if not isinstance(latency_ticks, int) or latency_ticks < 0:
        raise ConfigError(f"latency_ticks={latency_ticks!r}: must be an integer >= 0")
    policy = policy if policy is not None else load_policy_for(spec.policy, spec.formation)
    config = policy.task_for(config)
    world, env = ticked_episode_env(spec, config, tick)
    n_ticks = world.n_ticks
    commands: dict[int, np.ndarray] = {}  # decision step -> its setpoints [1, N, 2]
    held = [np.zeros((1, spec.formation, 2))]
    step_index = 0

    def controller(j: int) -> np.ndarray:
        tick_index = step_index * n_ticks + j
        due = [k for k in commands if k * n_ticks + latency_ticks <= tick_index]
        if due:
            newest = max(due)
            held[0] = commands[newest]
            for k in due:
                del commands[k]
        return held[0]

    world.controller = controller

    policy_act = guarded(policy.act, config)

    def decide(obs):  # each agent's policy on its own observation (the kernel gives a row the same bits in any batch)
        commands[step_index] = policy_act(obs)
        return commands[step_index]

    def advance(k: int) -> None:
        nonlocal step_index
        step_index = k

    diverged, wall_s = fly(env, spec.steps, decide, before_step=advance)
    return SitlEpisodeResult(**episode_fields(env, spec, diverged, wall_s), mode="lock-step")
