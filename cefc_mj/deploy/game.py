"""`run_sitl_game`: the CI-HRL game (Table V) with every UAV's whole hierarchy in its own process.

The world, the task core (targets, adversary, rewards, metrics) and the radio run here; each UAV's
agent (`cefc-agent --game`, `cefc_mj.deploy.agent.GameAgent`) runs ConsMAC and the anchor selector at
every high-level decision (every 10 low-level steps) and the low level at every step, from its own
sensor packet and the neighbours' messages it received. Per low-level step the simulator sends each
flying agent its game sensor packet and flies the step in control ticks exactly as the low-level
SITL-M does (`SitlServer`: zero-order hold, latency carried into simulated time, offboard-loss
failsafe). At each decision it first delivers the messages the agents sent at the previous
decision, by the in-process game's own channel (`MessageChannel`: within 3 m by true distance, one
decision late), one inbox frame per agent; a message that has not arrived by then (the simulator
waits for it only as long as the wall clock has advanced less than simulated time) is late, and its
sender is an absent neighbour, as in the in-process game. docs/sitl_m.md, "The game over SITL-M".

>>> from cefc_mj.eval.highlevel_sitl import GameSpec
>>> result = run_sitl_game(GameSpec(seed=0, steps=60, n_agents=4), SitlConfig())  # doctest: +SKIP
>>> result.figures["R_t"], result.sitl["high_latency_ms"]["p50"]  # doctest: +SKIP
"""

from __future__ import annotations

import collections
import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from cefc_mj.deploy import wire
from cefc_mj.deploy.episode import (
    SitlConfig,
    check_faults,
    control_tick,
    fly_throwaway,
    note_exits_and_faults,
    server_options,
)
from cefc_mj.deploy.results import _percentiles, unrequested_faults
from cefc_mj.deploy.sim_server import AgentFleet, SitlServer, block_sigint, restore_sigint
from cefc_mj.deploy.tick_world import make_ticked_world
from cefc_mj.errors import ConfigError, SimulationDiverged
from cefc_mj.eval.highlevel_sitl import GameSpec, game_figures
from cefc_mj.eval.runner import diverged_faults
from cefc_mj.hierarchy import DECISION_INTERVAL
from cefc_mj.nn.highlevel_policy import highlevel_policy_path
from cefc_mj.nn.registry import HIERARCHY_LOWLEVEL
from cefc_mj.nn.selector import ANCHOR_VALUES, anchor_grid
from cefc_mj.task.config import LEARNED_ADVERSARY
from cefc_mj.task.messages import MessageChannel

PER_STEP_KINDS = ("down:game_sensor", "up:action", "up:message", "down:inbox")
"""The traffic of a game in flight (the startup's hello/welcome/ready and the pings are left out)."""

__all__ = ["GameServer", "GameTrace", "SitlGameResult", "game_sensor_packets", "inbox_frames", "run_sitl_game"]


def game_sensor_packets(step: int, t: float, env, radio_range: float, in_swarm: np.ndarray, uavs: list[int]) -> list:
    """The game sensor packets of low-level step `step` for UAVs `uavs` (env: the task core of one
    env). UAV i's packet holds what its vehicle senses (perceived position, velocity, LiDAR), what it
    observes of the game (the targets and their urgency, the adversary's position and velocity, as
    the CEFC observation reads them), and the state broadcasts of the vehicles within `radio_range`
    of it by true distance (as the low-level SITL-M's `sensor_packets`)."""
    world = env.world
    true_pos = world.agent_pos[0]
    gap = true_pos[:, None, :] - true_pos[None, :, :]
    hears = (np.sqrt((gap * gap).sum(-1)) < radio_range) & np.asarray(in_swarm, dtype=bool)[None, :]
    np.fill_diagonal(hears, False)
    pos_l, vel_l = env.perceived_pos[0].tolist(), world.agent_vel[0].tolist()
    lidar_l = env.lidar[0].tolist()
    targets = np.concatenate([env.targets[0], env.urgency[0][:, None]], axis=1).tolist()
    adversary_pos, adversary_vel = world.adversary_pos[0].tolist(), world.adversary_vel[0].tolist()
    return [
        {
            "type": "game_sensor",
            "seq": step,
            "t": t,
            "pos": pos_l[i],
            "vel": vel_l[i],
            "adversary_pos": adversary_pos,
            "adversary_vel": adversary_vel,
            "targets": targets,
            "lidar": lidar_l[i],
            "neighbours": [[j, *pos_l[j], *vel_l[j]] for j in np.flatnonzero(hears[i]).tolist()],
        }
        for i in uavs
    ]


def inbox_frames(inbox, decision: int, uavs: list[int]) -> dict[int, dict]:
    """The inbox message (wire type "inbox") of each of `uavs` from the channel's `Inbox` of one env:
    the received slots in the channel's order (nearest first), as (sender, true distance, message)."""
    out = {}
    for i in uavs:
        rows = [
            (int(inbox.sender[0, i, s]), float(inbox.distance[0, i, s]), inbox.messages[0, i, s])
            for s in np.flatnonzero(inbox.mask[0, i])
        ]
        out[i] = {"type": "inbox", "seq": decision, "dim": inbox.messages.shape[-1], "rows": rows}
    return out


class GameServer(SitlServer):
    """`SitlServer` plus the game's messages: game sensor packets, ConsMAC messages from the agents
    (validated: size, version, finiteness, sender, decision index, anchor), the channel and the
    inboxes it delivers, and the timing of the high-level decisions."""

    def __init__(
        self,
        *args,
        message_dim: int,
        n_anchors: int,
        comm_range: float,
        decision_interval: int,
        dt: float,
        **kwargs,
    ):
        super().__init__(*args, **kwargs)
        self._dt = dt
        self.message_dim, self.n_anchors = message_dim, n_anchors
        self.comm_range, self.decision_interval = comm_range, decision_interval
        self.channel = MessageChannel(1, self.n_agents, message_dim, comm_range) if message_dim else None
        self.decision = -1
        self.decision_wall: dict[int, float] = {}
        self.arrived: dict[int, dict] = {}
        """UAV -> its message of the open decision (`self.decision`), as received."""
        self.high_latency_ms = [[] for _ in range(self.n_agents)]
        self.high_round_trip_ms = [[] for _ in range(self.n_agents)]
        self.late_messages = np.zeros(self.n_agents, dtype=np.int64)
        self.missing_messages = np.zeros(self.n_agents, dtype=np.int64)
        self.ignored_messages = np.zeros(self.n_agents, dtype=np.int64)
        self.delivered = np.zeros(self.n_agents, dtype=np.int64)
        """Messages each UAV received (inbox rows)."""
        self.anchors: list[list[int]] = []
        """Per decision: each UAV's chosen anchor index (-1: none arrived)."""
        self.messages: list[np.ndarray] = []
        """Per decision: [N, D] float32, each UAV's message as received (a NaN row: none arrived)."""
        self.received_counts: list[list[int]] = []
        """Per decision: how many messages each UAV received."""

    # ------------------------------------------------------------------ receiving
    def _message(self, vehicle, message: dict, wall: float) -> None:
        try:
            wire.check_message(message, self.message_dim, self.n_anchors)
        except wire.WireError as e:
            self._malformed(str(e))
            return
        d = message["seq"]
        if d > self.decision:
            self._malformed("message for a decision never opened")
            return
        if vehicle.state != "flying":
            self.ignored_messages[vehicle.index] += 1
            return
        if d < self.decision:  # its decision's inboxes have gone out without it
            self.late_messages[vehicle.index] += 1
            return
        if vehicle.index in self.arrived:
            self._malformed("duplicate message")
            return
        self.arrived[vehicle.index] = message
        self.high_latency_ms[vehicle.index].append(message["latency_ms"])
        self.high_round_trip_ms[vehicle.index].append((wall - self.decision_wall[d]) * 1e3)

    # ------------------------------------------------------------------ the decisions
    def open_decision(self, decision: int, true_pos: np.ndarray) -> None:
        """Start high-level decision `decision`: wait for the previous decision's messages (within
        the wall-clock budget), deliver them by the channel (range and delay rules), and send every
        flying agent its inbox. Call before the decision step's sensor packets."""
        if decision > 0:
            self._wait_messages(decision)
            self._keep_decision()
            for v in self.flying():
                if v.index not in self.arrived:
                    self.missing_messages[v.index] += 1
        if self.channel is not None:
            if decision > 0:
                messages = np.zeros((1, self.n_agents, self.message_dim), dtype=np.float32)
                sent = np.zeros((1, self.n_agents), dtype=bool)
                for i, m in self.arrived.items():
                    if self.vehicles[i].state == "flying":  # a vehicle in failsafe sends nothing
                        messages[0, i] = m["message"]
                        sent[0, i] = True
                self.channel.send(messages, sent)
            inbox = self.channel.receive(np.asarray(true_pos, dtype=np.float64)[None])
            flying = [v.index for v in self.flying()]
            frames = inbox_frames(inbox, decision, flying)
            self.received_counts.append(inbox.received[0].tolist())
            for i in flying:
                self.delivered[i] += len(frames[i]["rows"])
                self._send(self.vehicles[i], frames[i])
        self.arrived = {}
        self.decision = decision

    def close_decisions(self) -> None:
        """At the game's end: keep the last open decision's anchors and messages, waiting for them as
        `open_decision` would have (within the same wall-clock budget). The game is not changed."""
        if self.decision >= 0 and len(self.anchors) == self.decision:
            self._wait_messages(self.decision + 1)
            self._keep_decision()

    def _keep_decision(self) -> None:
        """Keep the open decision's anchors and messages as they arrived (-1 and a NaN row: none)."""
        anchors = [-1] * self.n_agents
        messages = np.full((self.n_agents, self.message_dim), np.nan, dtype=np.float32)
        for i, m in self.arrived.items():
            anchors[i] = m["anchor"]
            if self.message_dim:
                messages[i] = m["message"]
        self.anchors.append(anchors)
        self.messages.append(messages)

    def _wait_messages(self, decision: int) -> None:
        """Wait for the open decision's messages of the flying agents until the wall clock has
        advanced as far as simulated time has since that decision's packets left."""
        if self.lockstep:
            deadline = self.decision_wall[self.decision] + self.lockstep_timeout_s
        else:
            deadline = self.decision_wall[self.decision] + self.decision_interval * self._dt
        while True:
            waiting = [v for v in self.flying() if v.index not in self.arrived]
            remaining = deadline - time.perf_counter()
            if not waiting or remaining <= 0:
                return
            self.receive(remaining)

    def send_game_sensors(self, step: int, t: float, env, radio_range: float) -> None:
        """Game sensor packet `step` to every flying agent (the bookkeeping of `send_sensors`)."""
        delays, in_swarm, flying = self.open_step(step, t)
        packets = game_sensor_packets(step, t, env, radio_range, in_swarm, [v.index for v in flying])
        if step % self.decision_interval == 0:
            self.decision_wall[step // self.decision_interval] = time.perf_counter()
        self.send_packets(step, t, flying, packets, delays)


class GameTrace:
    """What the simulator saw of one game, for its recording (`SitlGameResult.episode`): the state
    after the reset and after each low-level step (true positions and velocities, the adversary and
    the point its rule chases, urgency, the groups) and each step's reward and weighted parts, as
    `cefc_mj.viz.highlevel_log.play_highlevel_episode` keeps them in the one-process game."""

    def __init__(self, env, task, weights: dict[str, float]):
        self.env, self.weights = env, weights
        self.has_adversary = task.adversary != "none"
        self.goal_rule = "nearest_group" if task.adversary == LEARNED_ADVERSARY else task.adversary
        self.rows: dict[str, list] = collections.defaultdict(list)
        self.reward: list[float] = []
        self.parts: dict[str, list[float]] = {name: [] for name in weights}

    def capture(self) -> None:
        """Keep the env's state now (call after the reset and after each step)."""
        env, rows = self.env, self.rows
        w = env.world
        rows["agent_pos"].append(w.agent_pos[0].copy())
        rows["agent_vel"].append(w.agent_vel[0].copy())
        rows["urgency"].append(env.urgency[0].copy())
        rows["group_label"].append(env.labels[0].copy())
        rows["group_size"].append(np.take_along_axis(env.group_size, env.labels, axis=1)[0].copy())
        if self.has_adversary:
            rows["adversary_pos"].append(w.adversary_pos[0].copy())
            rows["adversary_goal"].append(env.rule_adversary_goal(self.goal_rule)[0].copy())

    def step(self, reward: float, terms: dict) -> None:
        """Keep one low-level step's reward and weighted parts, then the state after it."""
        self.reward.append(float(reward))
        for name, weight in self.weights.items():
            self.parts[name].append(float(weight * terms[name][0]))
        self.capture()

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v) for k, v in self.rows.items() if v}


@dataclass
class SitlGameResult:
    """One SITL-M game: its figures (as the lock-step game reports them) and the deployment's."""

    spec: GameSpec
    figures: dict[str, float]
    """R_H, R_t, R_n, R_e (per-episode sums), E, E_agents, F, C."""
    steps: int
    message_dim: int
    sitl: dict
    """Summary: latency and round-trip p50/p99 (low and high level), bytes per second per UAV, message
    counters, events, startup and loop times."""
    samples: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    """Pooled raw samples: low/high_latency_ms, low/high_round_trip_ms."""
    anchors: list[list[int]] = field(repr=False, default_factory=list)
    """Per decision: each UAV's chosen anchor (-1: its message did not arrive)."""
    messages: np.ndarray | None = field(repr=False, default=None)
    """[K, N, D] float32: each UAV's message at each decision as the simulator received it (a NaN
    row: it did not arrive, or came late); None for a policy without messages."""
    received: list[list[int]] = field(repr=False, default_factory=list)
    """Per decision: how many neighbours' messages each UAV's inbox held."""
    trace: GameTrace | None = field(repr=False, default=None)
    """The states and rewards of the game, step by step (for its recording)."""
    scene: dict = field(repr=False, default_factory=dict)
    """The game's fixed parts for its recording: variant, task, obstacles, targets, metrics."""
    diverged: str | None = None

    def episode(self):
        """The game as a `cefc_mj.viz.highlevel_log.HighLevelEpisode` (what `record_highlevel_episode`
        and the PNG figures draw), from what the simulator kept: the states step by step and, per
        decision, every UAV's anchor and message as received (-1 / NaN where none arrived: a missing
        anchor has NaN coordinates, a missing message a NaN similarity row and column). Imports rerun."""
        from cefc_mj.viz.highlevel_log import HighLevelEpisode, message_similarity

        if self.trace is None:
            raise ConfigError("this SITL-M game kept no trace to record")
        task, scene, rows = self.scene["task"], self.scene, self.trace.arrays()
        index = np.asarray(self.anchors, dtype=np.int64).reshape(-1, self.spec.n_agents)
        grid = anchor_grid(ANCHOR_VALUES)
        anchors = np.where((index >= 0)[..., None], grid[np.clip(index, 0, None)], np.nan)
        messages = self.messages
        return HighLevelEpisode(
            variant=scene["variant"],
            seed=self.spec.seed,
            backend=self.spec.where.backend,
            adversary_rule=task.adversary,
            low_level={"name": HIERARCHY_LOWLEVEL},
            dt=task.dt,
            decision_interval=scene["decision_interval"],
            arena_half_size=task.arena_half_size,
            obstacle_radius=task.obstacle_radius,
            target_radius=task.target_radius,
            alert_distance=task.rewards.evasion_alert_distance,
            obstacles=scene["obstacles"],
            targets=scene["targets"],
            anchor_grid=grid,
            agent_pos=rows["agent_pos"],
            agent_vel=rows["agent_vel"],
            adversary_pos=rows.get("adversary_pos"),
            adversary_goal=rows.get("adversary_goal"),
            urgency=rows["urgency"],
            group_label=rows["group_label"],
            group_size=rows["group_size"],
            reward=np.asarray(self.trace.reward),
            reward_parts={k: np.asarray(v) for k, v in self.trace.parts.items()},
            anchor_index=index,
            anchors=anchors,
            received=np.asarray(self.received, dtype=np.int64) if messages is not None else None,
            messages=messages,
            similarity=None if messages is None else message_similarity(messages),
            metrics=dict(scene["metrics"]),
            returns={m: self.figures[m] for m in ("R_H", "R_t", "R_n", "R_e")},
            condition="SITL-M",
        )

    def faults(self) -> list[str]:
        """Why this game is not a measurement, one line per cause (empty: it is one): diverged physics,
        agents lost or failed safe without being asked to (`unrequested_faults`)."""
        return diverged_faults(self.steps, self.diverged) + unrequested_faults(self.sitl.get("events", []))

    def to_dict(self) -> dict:
        return {
            "policy": self.spec.policy,
            "seed": self.spec.seed,
            "backend": self.spec.where.backend,
            "condition": "SITL-M",
            "steps": self.steps,
            "figures": self.figures,
            "sitl": self.sitl,
            "diverged": self.diverged,
            "faults": self.faults(),
        }


def _check(spec: GameSpec, sitl: SitlConfig):
    sitl.validate()
    if sitl.drop is not None:
        raise ConfigError("drop: the SITL-M game has no dropout yet (use faults)")
    if sitl.remote_agents and any(not isinstance(u, int) or not 0 <= u < spec.n_agents for u in sitl.remote_agents):
        raise ConfigError(f"remote_agents: UAV indices 0..{spec.n_agents - 1}")
    check_faults(sitl, spec.n_agents, spec.steps, "game")


def run_sitl_game(spec: GameSpec, sitl: SitlConfig = SitlConfig()) -> SitlGameResult:
    """Play one game with every UAV's whole hierarchy in its own process (module docstring).
    ConfigError / CheckpointError before any process starts for a bad spec, policy or config;
    AgentError when the agents cannot start. Every agent process is gone when it returns or raises."""
    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy

    _check(spec, sitl)
    task, adversary_policy, _ = spec.game()
    policy, meta = load_highlevel_policy(highlevel_policy_path(spec.policy))  # fails here, not in N processes
    interval = int(meta.get("decision_interval", DECISION_INTERVAL))
    if spec.steps % interval:
        raise ConfigError(f"steps={spec.steps}: must be a multiple of the policy's decision interval {interval}")
    where = spec.where
    tick = control_tick(sitl, where.backend, task.dt)

    def game_env():
        world = make_ticked_world(
            where.backend, task, tick, wind=where.wind, seed=spec.seed, wind_direction=where.wind_direction
        )
        return world, BatchedCEFCEnv(task, n_envs=1, seed=spec.seed, world=world, adversary_policy=adversary_policy)

    _warm_up_kernels(game_env, policy, task, spec.n_agents)
    world, env = game_env()
    welcome = {
        "formation": spec.n_agents,
        "task": task.to_dict(),
        "heartbeat_timeout_s": sitl.heartbeat_timeout_s,
        "game": {"low_level": HIERARCHY_LOWLEVEL, "decision_interval": interval},
    }
    server = GameServer(
        sitl.bind,
        spec.n_agents,
        welcome,
        world.tick_s,
        seed=spec.seed,
        **server_options(sitl),
        message_dim=policy.message_dim,
        n_anchors=len(ANCHOR_VALUES) ** 2,
        comm_range=task.observation_distance,
        decision_interval=interval,
        dt=task.dt,
    )
    fleet = None
    try:
        local = [i for i in range(spec.n_agents) if i not in sitl.remote_agents]
        command = (
            list(sitl.agent_command) if sitl.agent_command else [sys.executable, "-m", "cefc_mj.deploy.agent", "--game"]
        )
        if local:
            fleet = AgentFleet(command, server.local_endpoint, spec.policy, local, sitl.verbose_agents)
            fleet.spawn()
        if sitl.remote_agents:
            print(
                f"SITL-M game: waiting for agents {list(sitl.remote_agents)} at {server.endpoint} "
                f"(cefc-agent --game --connect {server.endpoint} --uav I --policy {spec.policy})",
                file=sys.stderr,
                flush=True,
            )
        startup_s = server.wait_until_ready(sitl.startup_timeout_s, fleet)
        if fleet is not None:
            for uav in local:
                if not fleet.adopt(uav, server.vehicles[uav].info.get("pid", -1)):
                    server.event(uav, "not_adopted", "the agent's pid is not a local agent process")
        return _play(spec, sitl, task, env, world, server, fleet, startup_s, policy, interval)
    finally:  # Ctrl-C waits until every agent process is gone
        previous = block_sigint()
        try:
            server.stop_all("game over")
            if fleet is not None:
                fleet.shutdown()
            server.close()
        finally:
            restore_sigint(previous)


def _warm_up_kernels(game_env, policy, task, n_agents: int) -> None:
    """Compile (a cold numba cache) or load every kernel of the game here, before any agent starts
    (`cefc_mj.deploy.episode.warm_up_kernels` says why): a throwaway game flies two steps, and one UAV's
    hierarchy decides and steps on a probe, so that the agents load from a warm cache."""
    from cefc_mj.deploy.agent import warm_up_hierarchy
    from cefc_mj.hierarchy import AgentHierarchy, load_low_level

    fly_throwaway(*game_env(), n_agents)
    warm_up_hierarchy(AgentHierarchy(policy, load_low_level(HIERARCHY_LOWLEVEL, task), task), task)


def _play(spec, sitl, task, env, world, server: GameServer, fleet, startup_s, policy, interval):
    message_dim, variant = policy.message_dim, policy.variant
    n_ticks = world.n_ticks
    faults = collections.defaultdict(list)
    for fault in sitl.faults:
        faults[fault.step].append(fault)
    step_index = 0

    def controller(j: int) -> np.ndarray:
        accel, hold = server.control(step_index * n_ticks + j)
        if hold.any():
            accel[hold] = world.brake_accel(task.accel_max)[0, hold]
        return accel[None]

    world.controller = controller
    w = task.rewards
    weights = {"R_t": w.task_weight, "R_n": w.navigation_weight_high, "R_e": w.evasion_weight}
    env.reset(seed=spec.seed)
    trace = GameTrace(env, task, weights)
    trace.capture()
    total, parts = 0.0, {name: 0.0 for name in weights}
    block, terms = 0.0, {}
    info: dict = {}
    diverged = None
    start = time.perf_counter()
    steps = 0
    for k in range(spec.steps):
        step_index = k
        t = k * task.dt
        server.step, server.t_now = k, t
        note_exits_and_faults(server, fleet, faults.get(k, []))
        if k % interval == 0:
            server.open_decision(k // interval, world.agent_pos[0])
        server.send_game_sensors(k, t, env, task.observation_distance)
        server.await_replies()
        try:
            _, reward, done, info = env.step(np.zeros((1, spec.n_agents, 2)))  # the controller supplies the setpoints
        except SimulationDiverged as e:
            diverged = str(e)
            break
        steps += 1
        trace.step(reward[0], info["reward_terms"])
        block += reward[0]  # summed as the lock-step game sums: per decision, then over decisions
        for name in weights:
            terms[name] = terms.get(name, 0.0) + info["reward_terms"][name][0]
        if done[0] or (k + 1) % interval == 0:
            total += block
            for name, weight in weights.items():
                parts[name] += weight * terms[name]
            block, terms = 0.0, {}
        if done[0]:
            break
    loop_wall = time.perf_counter() - start
    server.receive(0.0)
    server.close_decisions()  # the last decision's messages, kept for the recording
    metrics = info.get("metrics") or env.episode_metrics()
    figures = game_figures(total, parts, metrics)
    vehicles = server.vehicles
    sim_s = steps * task.dt
    pooled = {
        "low_latency_ms": np.concatenate([np.asarray(v.latency_ms, dtype=np.float64) for v in vehicles]),
        "high_latency_ms": np.concatenate([np.asarray(x, dtype=np.float64) for x in server.high_latency_ms]),
        "low_round_trip_ms": np.concatenate([np.asarray(v.round_trip_ms, dtype=np.float64) for v in vehicles]),
        "high_round_trip_ms": np.concatenate([np.asarray(x, dtype=np.float64) for x in server.high_round_trip_ms]),
        "command_age_ms": np.concatenate([np.asarray(v.age_ms, dtype=np.float64) for v in vehicles]),
    }
    per_uav_bytes = [sum(v.wire_bytes[k] for k in PER_STEP_KINDS) / sim_s if sim_s else 0.0 for v in vehicles]
    message_bytes = [
        (v.wire_bytes["up:message"] + v.wire_bytes["down:inbox"]) / sim_s if sim_s else 0.0 for v in vehicles
    ]
    by_kind: collections.Counter = collections.Counter()
    for v in vehicles:
        by_kind.update({k: v.wire_bytes[k] for k in PER_STEP_KINDS})
    summary = {
        **{name: _percentiles(values) for name, values in pooled.items()},
        "bytes_per_s_per_uav": float(np.mean(per_uav_bytes)),
        "message_bytes_per_s_per_uav": float(np.mean(message_bytes)),
        "bytes_per_s_by_kind_per_uav": {k: v / sim_s / spec.n_agents for k, v in sorted(by_kind.items())}
        if sim_s
        else {},
        "bytes_per_s_per_uav_each": per_uav_bytes,
        "late_commands": [v.late for v in vehicles],
        "skipped_packets": [v.skipped + len(v.outstanding) for v in vehicles],
        "ignored_replies": [v.ignored for v in vehicles],
        "late_messages": server.late_messages.tolist(),
        "missing_messages": server.missing_messages.tolist(),
        "ignored_messages": server.ignored_messages.tolist(),
        "messages_delivered": server.delivered.tolist(),
        "malformed": server.malformed,
        "malformed_reasons": dict(server.malformed_reasons),
        "events": list(server.events),
        "control_tick_s": world.tick_s,
        "startup_s": startup_s,
        "loop_wall_s": loop_wall,
        "sim_s": sim_s,
        "real_time_factor": sim_s / loop_wall if loop_wall > 0 else math.nan,
        "agents": [{**v.info, "local": fleet is not None and v.index in fleet.uavs} for v in vehicles],
        "final_states": [v.state for v in vehicles],
        "final_speed": np.linalg.norm(world.agent_vel[0], axis=-1).tolist(),
    }
    return SitlGameResult(
        spec=spec,
        figures=figures,
        steps=steps,
        message_dim=message_dim,
        sitl=summary,
        samples=pooled,
        anchors=list(server.anchors),
        messages=np.stack(server.messages) if message_dim and server.messages else None,
        received=list(server.received_counts),
        trace=trace,
        scene={
            "task": task,
            "variant": variant,
            "decision_interval": interval,
            "obstacles": env.obstacles[0].copy(),
            "targets": env.targets[0].copy(),
            "metrics": {m: float(np.asarray(metrics[m]).reshape(-1)[0]) for m in ("F", "N", "C", "E")},
        },
        diverged=diverged,
    )
