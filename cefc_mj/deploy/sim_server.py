"""The simulator side of SITL-M: the agents' processes and the ROUTER socket they talk to.

`AgentFleet` starts, signals and reaps the local agent processes (no orphans: see `shutdown`).
`SitlServer` owns the ZeroMQ ROUTER socket: it registers agents (hello -> welcome -> ready), sends
each flying agent its sensor packet, reads and validates every reply (a malformed message is dropped
and counted, never acted on), and decides at every control tick which setpoint each vehicle flies.

Timing model (docs/research/sitl_m.md, "Timing", has the full story). Simulated time runs faster than wall time, so a
decision's wall-clock latency is carried over into simulated time:

- the packet for decision step k leaves at simulated time t_k; each direction of the link adds
  `link_delay_ms` plus a uniform draw from [0, jitter_ms] (seeded, drawn when the packet is sent);
- the agent reports its decision latency L (its own wall clock, packet in -> reply out);
- the command takes effect at e = t_k + down + L + up, i.e. at the first control tick >= e, and is
  held until a newer one takes effect (zero-order hold);
- the simulator never runs ahead of a decision that could be due: at a tick T >= t_k + down + up
  it waits for the reply until the wall clock has advanced as far as simulated time has since the
  packet left (wall_sent + (T - t_k)). A reply that comes later than that was late in real time
  too: it takes effect at the first tick after it is read ("a late command is applied late").
  The simulator therefore runs as fast as it can but never faster than the agents really decide.
- PX4's offboard-loss failsafe: a vehicle without a new setpoint for `offboard_loss_timeout_s` of
  simulated time (COM_OF_LOSS_T, default 1 s) switches to hold (zero velocity setpoint, braking
  within the acceleration limit) for the rest of the episode; a dead or hung agent thus costs at
  most that much simulated time of real-time pacing.
"""

from __future__ import annotations

import collections
import math
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cefc_mj.deploy import wire
from cefc_mj.errors import CefcError

EPS = 1e-9
PING_PERIOD_S = 0.5
OFFBOARD_LOSS_TIMEOUT_S = 1.0
"""PX4's COM_OF_LOSS_T as SITL-M and the MAVLink link use it: simulated seconds without a new
setpoint before a vehicle holds."""


def offboard_lost(t: float, last_setpoint_t: float, timeout_s: float) -> bool:
    """PX4's offboard-loss test: no new setpoint for more than `timeout_s` at simulated time `t`."""
    return t - last_setpoint_t > timeout_s + EPS


class AgentError(CefcError, RuntimeError):
    """An agent could not start or reported that it cannot fly (the message says which and why)."""


# ====================================================================== local processes
class AgentFleet:
    """The local agents of one episode: one launcher process (`command --uav I J ...`) that imports
    torch once and forks one agent process per UAV (with a single UAV it is the agent itself).

    The simulator learns each agent's pid from its hello and adopts it only if it is the launcher
    or the launcher's child (checked in /proc), so a pid received over the network can never make
    it signal a foreign process. Children die with the launcher (PR_SET_PDEATHSIG = SIGKILL), the
    launcher with this process (SIGTERM) and with its own watch of this process's pid."""

    def __init__(self, command: list[str], endpoint: str, policy: str, uavs: list[int], verbose: bool = False):
        self.command, self.endpoint, self.policy, self.verbose = list(command), endpoint, policy, verbose
        self.uavs = list(uavs)
        self.launcher: subprocess.Popen | None = None
        self.agent_pids: dict[int, int] = {}
        self._logs = tempfile.TemporaryDirectory(prefix="cefc-sitl-")
        self._reported: set[int] = set()

    def spawn(self) -> None:
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        argv = (
            self.command
            + [
                "--connect",
                self.endpoint,
                "--uav",
                *map(str, self.uavs),
                "--policy",
                self.policy,
                "--parent-pid",
                str(os.getpid()),
            ]
            + (["--verbose"] if self.verbose else [])
        )
        with open(self.log_path, "wb") as log:
            self.launcher = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env)

    @property
    def log_path(self) -> Path:
        return Path(self._logs.name) / "agents.log"

    def log_tail(self, lines: int = 3) -> str:
        try:
            text = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])

    def launcher_exit_code(self) -> int | None:
        return None if self.launcher is None else self.launcher.poll()

    def adopt(self, uav: int, pid: int) -> bool:
        """Record UAV `uav`'s agent pid if it is ours (see the class docstring)."""
        if self.launcher is None or uav not in self.uavs:
            return False
        if pid == self.launcher.pid or _parent_pid(pid) == self.launcher.pid:
            self.agent_pids[uav] = pid
            return True
        return False

    def _alive(self, pid: int) -> bool:
        if self.launcher is not None and pid == self.launcher.pid:
            return self.launcher.poll() is None
        return _alive(pid)

    def poll_exits(self) -> list[int]:
        """UAVs whose agent process has gone since the last call."""
        out = []
        for uav, pid in self.agent_pids.items():
            if uav not in self._reported and not self._alive(pid):
                self._reported.add(uav)
                out.append(uav)
        return out

    def signal(self, uav: int, sig: int) -> bool:
        """Send `sig` to UAV `uav`'s agent; False if it has no running local process."""
        pid = self.agent_pids.get(uav)
        if pid is None or not self._alive(pid):
            return False
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            return False
        return True

    def shutdown(self, grace_s: float = 1.0) -> None:
        """Make sure every agent process is gone and reaped: give them `grace_s` to exit after the
        simulator's stop message, then SIGKILL the agents still there (a stopped one included) and
        SIGTERM, then SIGKILL, the launcher. Ctrl-C is held off meanwhile so that an impatient
        second Ctrl-C cannot leave orphans behind."""
        previous = block_sigint()
        try:
            if self.launcher is not None:
                _wait(self.launcher, grace_s)
            for pid in self.agent_pids.values():
                if self._alive(pid):
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
            if self.launcher is not None and self.launcher.poll() is None:
                self.launcher.terminate()
                _wait(self.launcher, 2.5)
                if self.launcher.poll() is None:
                    self.launcher.kill()
                    self.launcher.wait()
            self._logs.cleanup()
        finally:
            restore_sigint(previous)


def _parent_pid(pid: int) -> int | None:
    """The parent of `pid` from /proc (Linux); None when unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return int(stat[stat.rindex(")") + 2 :].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2] != "Z"
    except (OSError, ValueError, IndexError):
        return True


def _wait(proc: subprocess.Popen, timeout: float) -> None:
    try:
        proc.wait(timeout=max(timeout, 0.0))
    except subprocess.TimeoutExpired:
        pass


def block_sigint():
    """Hold off SIGINT in this thread (it stays pending); returns what `restore_sigint` needs."""
    if not hasattr(signal, "pthread_sigmask"):
        return None
    try:
        return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    except (ValueError, OSError):
        return None


def restore_sigint(previous) -> None:
    """Undo `block_sigint`; a Ctrl-C that came meanwhile is raised now."""
    if previous is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


# ====================================================================== the socket and the schedule
def sensor_packets(
    step: int,
    t: float,
    perceived_pos: np.ndarray,
    velocity: np.ndarray,
    lidar: np.ndarray,
    anchor: np.ndarray,
    true_pos: np.ndarray,
    radio_range: float,
    in_swarm: np.ndarray,
    uavs: list[int],
) -> list[dict]:
    """The sensor packets of decision step `step` for UAVs `uavs` (arrays [N, ...] of one env).

    UAV i's packet holds what its own vehicle measures (perceived position, velocity, LiDAR cast
    from the perceived position), the anchor it flies to, and the state broadcasts (perceived
    position, velocity) of the other vehicles of the swarm (`in_swarm` [N]) within `radio_range` of
    it in true distance: the simulator plays the radio and forwards what each neighbour's vehicle
    broadcasts. The agent builds its observation from it (`observation_from_packet`)."""
    gap = true_pos[:, None, :] - true_pos[None, :, :]
    hears = (np.sqrt((gap * gap).sum(-1)) < radio_range) & np.asarray(in_swarm, dtype=bool)[None, :]
    np.fill_diagonal(hears, False)
    pos_l, vel_l, lidar_l, anchor_l = perceived_pos.tolist(), velocity.tolist(), lidar.tolist(), anchor.tolist()
    return [
        {
            "type": "sensor",
            "seq": step,
            "t": t,
            "pos": pos_l[i],
            "vel": vel_l[i],
            "anchor": anchor_l,
            "lidar": lidar_l[i],
            "neighbours": [[j, *pos_l[j], *vel_l[j]] for j in np.flatnonzero(hears[i]).tolist()],
        }
        for i in uavs
    ]


@dataclass
class _Request:
    """One sensor packet sent to one agent."""

    seq: int
    t_obs: float
    wall_sent: float
    delay_s: float
    """Down- plus up-link delay drawn for this packet (simulated seconds)."""


@dataclass
class _Reply:
    seq: int
    t_obs: float
    effective_t: float
    accel: np.ndarray


class _Vehicle:
    """The simulator's view of one UAV: its agent's connection, its offboard setpoint, its stats."""

    def __init__(self, index: int):
        self.index = index
        self.identity: bytes | None = None
        self.state = "waiting"
        """waiting -> connected (welcomed) -> flying (ready) -> failsafe | exited | removed."""
        self.agent_exited = False
        self.info: dict = {}
        self.outstanding: collections.deque[_Request] = collections.deque()
        self.replies: list[_Reply] = []
        self.setpoint = np.zeros(2)
        self.setpoint_seq = -1
        self.last_setpoint_t = 0.0
        self.latency_ms: list[float] = []
        self.round_trip_ms: list[float] = []
        self.age_ms: list[float] = []
        self.late = self.skipped = self.ignored = 0
        self.wire_bytes: collections.Counter = collections.Counter()
        """Bytes on the wire by direction and message type ("up:action", "down:sensor", ...)."""


class SitlServer:
    """The ROUTER socket and the command schedule of one SITL-M episode (see the module docstring).

    Args:
        bind: ZeroMQ endpoint to bind ("tcp://127.0.0.1:*" picks a free port; `endpoint` tells which).
        n_agents: N, the UAV count.
        welcome: the "welcome" fields every agent gets (task config dict, formation, heartbeat).
        tick_s: the control tick (s).
        link_delay_ms, jitter_ms: one-way link delay and its uniform jitter bound (simulated ms).
        offboard_loss_timeout_s: COM_OF_LOSS_T (simulated s).
        realtime: pace the simulation to the wall clock.
        lockstep: wait for every flying agent's reply to packet k and apply it for the whole of step k
            (verification mode: the lock-step runner over the wire).
        lockstep_timeout_s: in lock-step mode, how long (wall) to wait before the vehicle fails safe.
        seed: seeds the jitter draws.
        lockstep_delay_s: in lock-step mode, each command takes effect this long after its packet.
    """

    def __init__(
        self,
        bind: str,
        n_agents: int,
        welcome: dict,
        tick_s: float,
        link_delay_ms: float = 0.0,
        jitter_ms: float = 0.0,
        offboard_loss_timeout_s: float = OFFBOARD_LOSS_TIMEOUT_S,
        realtime: bool = False,
        lockstep: bool = False,
        lockstep_timeout_s: float = 10.0,
        seed: int = 0,
        lockstep_delay_s: float = 0.0,
    ):
        import zmq

        self.zmq = zmq
        self.context = zmq.Context()
        self.sock = self.context.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.SNDHWM, 10000)
        self.sock.setsockopt(zmq.RCVHWM, 10000)
        self.sock.setsockopt(zmq.MAXMSGSIZE, 4 * wire.MAX_FRAME_BYTES)  # the transport drops giant frames
        try:
            self.sock.bind(bind)
        except zmq.ZMQError as e:
            self.close()
            raise AgentError(f"cannot bind {bind}: {e}") from None
        self.endpoint = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.n_agents = n_agents
        self.welcome = dict(welcome)
        self.tick_s = tick_s
        self.link_delay_s, self.jitter_s = link_delay_ms / 1e3, jitter_ms / 1e3
        self.offboard_loss_timeout_s = offboard_loss_timeout_s
        self.realtime, self.lockstep, self.lockstep_timeout_s = realtime, lockstep, lockstep_timeout_s
        self.lockstep_delay_s = lockstep_delay_s
        self.rng = np.random.default_rng([int(seed), 0x5171])
        self.vehicles = [_Vehicle(i) for i in range(n_agents)]
        self.by_identity: dict[bytes, _Vehicle] = {}
        self.malformed = 0
        self.malformed_reasons: collections.Counter = collections.Counter()
        self.events: list[dict] = []
        self.errors: list[str] = []
        self.step = 0
        self.t_now = 0.0
        """Simulated time of the last tick or packet (s)."""
        self.seq = -1
        self.wall0: float | None = None

    @property
    def local_endpoint(self) -> str:
        """The endpoint a local process connects to (a wildcard address made loopback)."""
        return self.endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")

    # ------------------------------------------------------------------ bookkeeping
    def event(self, uav: int | None, event: str, detail: str = "", t: float | None = None) -> None:
        self.events.append(
            {
                "step": self.step,
                "t": round(self.t_now if t is None else t, 6),
                "uav": uav,
                "event": event,
                "detail": detail,
            }
        )

    def _malformed(self, reason: str) -> None:
        self.malformed += 1
        self.malformed_reasons[reason] += 1

    def _send(self, vehicle: _Vehicle, message: dict) -> None:
        if vehicle.identity is None:
            return
        vehicle.wire_bytes["down:" + message["type"]] += self._send_to(vehicle.identity, message)

    def _send_to(self, identity: bytes, message: dict) -> int:
        """Send one message; returns its frame's size in bytes (0 if the socket refused it)."""
        frame = wire.encode({"v": wire.WIRE_VERSION, **message})
        try:  # ROUTER never blocks: it drops frames for a peer that is gone or whose queue is full
            self.sock.send_multipart([identity, frame], self.zmq.NOBLOCK)
        except self.zmq.ZMQError:
            return 0
        return len(frame)

    # ------------------------------------------------------------------ receiving
    def receive(self, timeout_s: float = 0.0) -> int:
        """Handle every message that arrives within `timeout_s` (returns after the first batch);
        returns how many frames were read."""
        if timeout_s > 0 and not self.sock.poll(max(1, int(np.ceil(timeout_s * 1e3)))):
            return 0
        count = 0
        while True:
            try:
                frames = self.sock.recv_multipart(self.zmq.NOBLOCK)
            except self.zmq.Again:
                return count
            count += 1
            self._handle(frames, time.perf_counter())

    def _handle(self, frames: list[bytes], wall: float) -> None:
        if len(frames) != 2:
            self._malformed("multipart frame")
            return
        identity, payload = frames
        try:
            message = wire.decode(payload, wire.AGENT_TO_SIM)
        except wire.WireError as e:
            self._malformed(str(e))
            return
        kind, uav = message["type"], message["uav"]
        if not 0 <= uav < self.n_agents:
            self._malformed("uav out of range")
            if kind == "hello":
                self._send_to(
                    identity, {"type": "reject", "reason": f"uav {uav}: this game has UAVs 0..{self.n_agents - 1}"}
                )
            return
        if kind == "hello":
            self._hello(identity, message)
            return
        vehicle = self.by_identity.get(identity)
        if vehicle is None or vehicle.index != uav:
            self._malformed("uav does not match the sender")
            return
        vehicle.wire_bytes["up:" + kind] += len(payload)
        if kind == "ready":
            if vehicle.state == "connected":
                vehicle.state = "flying"
        elif kind == "error":
            self.errors.append(f"uav {uav}: {message['reason']}")
            self.event(uav, "agent_error", message["reason"])
        elif kind == "action":
            self._action(vehicle, message, wall)
        elif kind == "message":
            self._message(vehicle, message, wall)

    def _message(self, vehicle: _Vehicle, message: dict, wall: float) -> None:
        """A ConsMAC message: only the game's server (`cefc_mj.deploy.game`) expects them."""
        self._malformed("message outside a game")

    def _hello(self, identity: bytes, message: dict) -> None:
        vehicle = self.vehicles[message["uav"]]
        registered = self.by_identity.get(identity)
        if registered is not None and registered is not vehicle:
            self._malformed("sender already flies another uav")
            return
        if vehicle.identity not in (None, identity):
            self._malformed("uav already connected")
            self._send_to(identity, {"type": "reject", "reason": f"uav {vehicle.index} is already connected"})
            return
        if vehicle.identity is None:
            vehicle.identity = identity
            vehicle.state = "connected"
            vehicle.info = {
                "uav": vehicle.index,
                "policy": message["policy"],
                "pid": message["pid"],
                "host": message["host"],
            }
            self.by_identity[identity] = vehicle
        self._send(vehicle, {"type": "welcome", "uav": vehicle.index, **self.welcome})  # again on a repeated hello

    def _action(self, vehicle: _Vehicle, message: dict, wall: float) -> None:
        seq = message["seq"]
        if seq > self.seq:
            self._malformed("seq never sent")
            return
        if message["latency_ms"] < 0:
            self._malformed("latency_ms: negative")
            return
        if vehicle.state != "flying":
            vehicle.ignored += 1
            return
        request = None
        while vehicle.outstanding and vehicle.outstanding[0].seq <= seq:
            r = vehicle.outstanding.popleft()
            if r.seq == seq:
                request = r
            else:
                vehicle.skipped += 1
        if request is None:  # a duplicate or an answer to a packet already given up on
            vehicle.ignored += 1
            return
        rtt_s = wall - request.wall_sent
        latency_s = max(0.0, min(message["latency_ms"] / 1e3, rtt_s))  # a decision cannot outlast its round trip
        vehicle.latency_ms.append(message["latency_ms"])
        vehicle.round_trip_ms.append(rtt_s * 1e3)
        effective = request.t_obs + (self.lockstep_delay_s if self.lockstep else request.delay_s + latency_s)
        vehicle.replies.append(_Reply(seq, request.t_obs, effective, np.asarray(message["accel"], dtype=np.float64)))

    # ------------------------------------------------------------------ startup
    def wait_until_ready(self, timeout_s: float, fleet: AgentFleet | None) -> float:
        """Run the hello/welcome/ready exchange until every UAV's agent is ready; returns the wall
        seconds it took. AgentError if an agent reports an error, exits, or the time runs out."""
        start = last_ping = time.monotonic()
        while True:
            if self.errors:
                raise AgentError(f"agent failed: {self.errors[0]}")
            if fleet is not None and fleet.launcher_exit_code() is not None:
                tail = fleet.log_tail()
                raise AgentError(
                    f"the agent processes exited with code {fleet.launcher_exit_code()} during startup"
                    + (f": {tail}" if tail else "")
                )
            if all(v.state == "flying" for v in self.vehicles):
                return time.monotonic() - start
            now = time.monotonic()
            if now - start > timeout_s:
                missing = [v.index for v in self.vehicles if v.state != "flying"]
                raise AgentError(f"agents for uav {missing} not ready after {timeout_s:g} s (endpoint {self.endpoint})")
            if now - last_ping > PING_PERIOD_S:  # keep connected agents from timing out
                for v in self.vehicles:
                    self._send(v, {"type": "ping", "t": 0.0})
                last_ping = now
            self.receive(0.1)

    # ------------------------------------------------------------------ the episode
    def flying(self) -> list[_Vehicle]:
        return [v for v in self.vehicles if v.state == "flying"]

    def send_sensors(
        self,
        step: int,
        t: float,
        perceived_pos: np.ndarray,
        velocity: np.ndarray,
        lidar: np.ndarray,
        anchor: np.ndarray,
        true_pos: np.ndarray,
        radio_range: float,
    ) -> None:
        """Sensor packet `step` (see `sensor_packets`) to every flying agent."""
        delays, in_swarm, flying = self.open_step(step, t)
        packets = sensor_packets(
            step, t, perceived_pos, velocity, lidar, anchor, true_pos, radio_range, in_swarm, [v.index for v in flying]
        )
        self.send_packets(step, t, flying, packets, delays)

    def open_step(self, step: int, t: float) -> tuple[np.ndarray, np.ndarray, list[_Vehicle]]:
        """Start step `step` at simulated time `t`: (each UAV's link delays [N, 2] in s, which UAVs are
        in the swarm [N], the flying vehicles) for the packets about to go out."""
        self.step = self.seq = step
        self.t_now = t
        if self.wall0 is None:
            self.wall0 = time.perf_counter() - t
        delays = self.link_delay_s + (
            self.rng.uniform(0.0, self.jitter_s, size=(self.n_agents, 2))
            if self.jitter_s
            else np.zeros((self.n_agents, 2))
        )
        in_swarm = np.array([v.state != "removed" for v in self.vehicles])
        return delays, in_swarm, self.flying()

    def send_packets(self, step: int, t: float, flying: list[_Vehicle], packets, delays: np.ndarray) -> None:
        """Send each flying vehicle its packet of step `step` and keep the request its reply answers."""
        for v, packet in zip(flying, packets):
            v.outstanding.append(_Request(step, t, time.perf_counter(), float(delays[v.index].sum())))
            self._send(v, packet)

    def await_replies(self) -> None:
        """Right after `send_sensors`: read replies to the packets just sent until every flying agent
        has answered, or until the first of them could be due (the wall-clock budget `_wait_due`
        would give it). Only when replies are read changes, not when they take effect (that follows
        from the reported latency): the simulator sleeps while the agents decide instead of
        competing with them for a core, and a reply is read the moment it arrives."""
        if self.lockstep or self.realtime:
            return
        while True:
            deadline = None
            for v in self.flying():
                for r in v.outstanding:
                    if r.seq == self.seq:
                        first_tick = (math.floor((r.t_obs + r.delay_s) / self.tick_s + EPS) + 1) * self.tick_s
                        due_wall = r.wall_sent + (first_tick - r.t_obs)
                        deadline = due_wall if deadline is None else min(deadline, due_wall)
            if deadline is None:
                return
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            self.receive(remaining)

    def control(self, tick: int) -> tuple[np.ndarray, np.ndarray]:
        """The setpoints [N, 2] in force at control tick `tick` (simulated time tick * tick_s), and
        which vehicles are in hold [N] bool (failsafe or removed: the caller brakes them)."""
        t = self.t_now = tick * self.tick_s
        if self.realtime and self.wall0 is not None:
            lag = self.wall0 + t - time.perf_counter()
            if lag > 0:
                time.sleep(lag)
        self.receive(0.0)
        if self.lockstep:
            self._wait_lockstep()
        else:
            self._wait_due(t)
        accel = np.zeros((self.n_agents, 2))
        hold = np.zeros(self.n_agents, dtype=bool)
        for v in self.vehicles:
            if v.state == "flying" and v.replies:
                self._apply(v, t)
            if v.state in ("flying", "exited") and offboard_lost(t, v.last_setpoint_t, self.offboard_loss_timeout_s):
                v.state = "failsafe"
                v.outstanding.clear()
                self.event(
                    v.index,
                    "offboard_loss_hold",
                    f"no setpoint for {self.offboard_loss_timeout_s:g} s: hold (zero velocity setpoint)",
                    t,
                )
            accel[v.index] = v.setpoint
            hold[v.index] = v.state in ("failsafe", "removed")
        return accel, hold

    def _wait_due(self, t: float) -> None:
        """Wait for replies that could take effect by `t` until the wall clock catches up with them."""
        while True:
            deadline = 0.0
            for v in self.flying():
                for r in v.outstanding:
                    if r.t_obs + r.delay_s > t + EPS:
                        break  # later packets cannot be due either
                    deadline = max(deadline, r.wall_sent + (t - r.t_obs))
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            self.receive(remaining)

    def _wait_lockstep(self) -> None:
        while True:
            waiting = [v for v in self.flying() if any(r.seq == self.seq for r in v.outstanding)]
            if not waiting:
                return
            remaining = (
                min(r.wall_sent for v in waiting for r in v.outstanding) + self.lockstep_timeout_s - time.perf_counter()
            )
            if remaining <= 0:
                for v in waiting:
                    v.state = "failsafe"
                    v.outstanding.clear()
                    self.event(
                        v.index, "offboard_loss_hold", f"no reply within {self.lockstep_timeout_s:g} s (lock-step)"
                    )
                return
            self.receive(remaining)

    def _apply(self, v: _Vehicle, t: float) -> None:
        due = [r for r in v.replies if r.effective_t <= t + EPS]
        if not due:
            return
        newest = max(due, key=lambda r: r.seq)
        v.replies = [r for r in v.replies if r.effective_t > t + EPS and r.seq > newest.seq]
        if newest.seq <= v.setpoint_seq:
            return
        v.setpoint = newest.accel
        v.setpoint_seq = newest.seq
        v.last_setpoint_t = t
        v.age_ms.append(round((t - newest.t_obs) * 1e3, 6))  # to the ns: ticks are exact multiples
        first_tick = np.ceil((newest.effective_t - EPS) / self.tick_s) * self.tick_s
        if t > first_tick + EPS:
            v.late += 1

    def agent_exited(self, uav: int) -> None:
        v = self.vehicles[uav]
        v.agent_exited = True
        v.outstanding.clear()
        if v.state == "flying":
            v.state = "exited"  # the vehicle flies its last setpoint until the offboard-loss timeout
        self.event(uav, "agent_exited", "process gone")

    def remove(self, uav: int, reason: str) -> None:
        v = self.vehicles[uav]
        v.state = "removed"
        v.outstanding.clear()
        v.replies.clear()
        self._send(v, {"type": "stop", "reason": reason})
        self.event(uav, "removed", reason)

    def stop_all(self, reason: str) -> None:
        for v in self.vehicles:
            self._send(v, {"type": "stop", "reason": reason})

    def close(self) -> None:
        self.sock.close(0)
        self.context.term()
