"""A SITL-M agent: one UAV's low-level policy in its own process (the `cefc-agent` command).

    python -m cefc_mj.deploy.agent --connect tcp://HOST:PORT --uav 3 --policy atm_c6_step3

The agent connects a ZeroMQ DEALER socket to the simulator's ROUTER, says `hello` (its UAV index
and policy), receives `welcome` (the game's TaskConfig and the formation size c), loads its own copy
of the policy exactly as the lock-step evaluator does (`load_policy_for`: "atm", "student", a name
in policies/ or a .pt path), warms it up and says `ready`. Then, for every sensor packet: it builds
its observation from the packet with the same code as the lock-step runner
(`build_low_level_observation`), runs the policy, and replies with the acceleration setpoint and
its measured decision latency (packet received -> reply ready, wall clock). If several packets
queued up while it was busy, it answers only the newest (a queue of one, like a ROS topic with
queue size 1); the simulator counts the skipped ones.

With --game the agent runs its UAV's whole CI-HRL hierarchy in the SITL-M game (`GameAgent`,
`cefc_mj.deploy.game`): --policy is then the high-level policy (e.g. cihrl_consmac_a); ConsMAC and
the anchor selector decide every 10 steps from its own game sensor packet and the inbox of
neighbours' messages, the game's low level flies toward the chosen anchor every step, and the agent
sends its 64-number message after each decision.

It exits on its own when the simulator says `stop`, when the simulator has been silent for the
heartbeat timeout, when the process given with --parent-pid (the simulator) is gone, or on
SIGINT/SIGTERM. With several `--uav` indices the process is a launcher: it does the heavy imports
once and forks one agent process per UAV, which the kernel kills when the launcher dies (Linux
PR_SET_PDEATHSIG); a launcher spawned by the simulator gets SIGTERM when the simulator dies.
Malformed packets are dropped and counted (logged with --verbose). Bad command-line input: one
line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import socket
import sys
import time

import numpy as np

from cefc_mj.deploy import wire
from cefc_mj.errors import ExamplesHelpFormatter, help_epilog
from cefc_mj.eval import DEFAULT_POLICY

EXIT_USAGE = 2
EXIT_LOST = 3
"""Exit code when the simulator went silent (heartbeat timeout) or the parent process died."""
DEFAULT_WAIT_S = 60.0
HELLO_PERIOD_S = 1.0
WARMUP_CALLS = 20


def observation_from_packet(cfg, packet: dict) -> np.ndarray:
    """The agent's observation [D] (float32) from its sensor packet: row 0 of the lock-step runner's
    `build_low_level_observation` for a small local swarm [self, neighbours in increasing UAV index]
    (the lock-step runner's tie order), bit for bit, in one compiled call
    (`local_observation_kernel`). It is the lock-step runner's row for this agent as long as the same
    neighbours are in the packet (always with exact sensing; see docs/sitl_m.md)."""
    from cefc_mj.task.kernels import local_observation_kernel

    rows = np.array(sorted(packet["neighbours"]), dtype=np.float64).reshape(-1, 5)
    own = np.array([*packet["pos"], *packet["vel"]], dtype=np.float64)
    anchor = np.array(packet["anchor"], dtype=np.float64)
    lidar = np.array(packet["lidar"], dtype=np.float64)
    return local_observation_kernel(own, anchor, lidar, rows, cfg.neighbour_slots, float(cfg.observation_distance))


def low_level_act(policy, cfg):
    """The agent's decision function, obs [1, 1, D] -> setpoint [1, 1, 2]: the lock-step runner's bits
    for this row (the compiled forward; the guard, when the game asks for it, reads the row alone)."""
    from cefc_mj.task.guard import guarded

    return guarded(policy.actor.inference_weights().actions, cfg)


def warm_up_low_level(act, cfg, uav: int = 0) -> None:
    """Run `act` on a probe packet WARMUP_CALLS times: the first calls compile (cold numba cache) or
    load the kernels, so that the agent says ready only when a decision takes its usual time. The
    simulator runs this too before it starts any agent, so that the agents find the cache warm."""
    probe = {
        "pos": [0.0, 0.0],
        "vel": [0.0, 0.0],
        "anchor": [1.0, 1.0],
        "lidar": [cfg.lidar_range] * cfg.n_lidar_rays,
        "neighbours": [[(uav + 1) % cfg.n_agents, 1.0, 0.0, 0.0, 0.0]],
    }
    for _ in range(WARMUP_CALLS):
        act(observation_from_packet(cfg, probe)[None, None])


def warm_up_hierarchy(hierarchy, cfg, uav: int = 0) -> None:
    """`warm_up_low_level` for a UAV's whole hierarchy (`cefc_mj.hierarchy.AgentHierarchy`): decisions
    and low-level steps on a probe (numba kernels, the TorchScript trace), then its memory and
    anchor cleared, so that the warm-up leaves nothing behind."""
    from cefc_mj.hierarchy import agent_cefc_observation

    own, lidar = [0.0, 0.0, 0.0, 0.0], [cfg.lidar_range] * cfg.n_lidar_rays
    neighbours = [[(uav + 1) % cfg.n_agents, 1.0, 0.0, 0.0, 0.0]]
    targets = [[1.0, 1.0, 0.5]] * cfg.n_targets
    probe = {"pos": own[:2], "vel": own[2:], "anchor": [1.0, 1.0], "lidar": lidar, "neighbours": neighbours}
    for _ in range(WARMUP_CALLS):
        obs = agent_cefc_observation(cfg, own, neighbours, targets, [2.0, 2.0, 0.0, 0.0], lidar)
        hierarchy.decide(obs, [(uav + 1) % cfg.n_agents], [1.0], np.zeros((1, hierarchy.message_dim)))
        hierarchy.act(observation_from_packet(cfg, probe))
    hierarchy.own[:] = 0.0
    hierarchy.anchor_index, hierarchy.anchor = None, np.zeros(2)


def _die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> None:
    """Linux: ask the kernel for `sig` when the parent exits (prctl PR_SET_PDEATHSIG); a no-op
    elsewhere or when the given pid is not our direct parent (the pid watch still covers it)."""
    if not sys.platform.startswith("linux") or os.getppid() != parent_pid:
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, int(sig), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        raise SystemExit(EXIT_LOST)


def _parent_alive(parent_pid: int | None) -> bool:
    if parent_pid is None:
        return True
    try:
        os.kill(parent_pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


class Agent:
    """The agent's state machine over one DEALER socket (see the module docstring)."""

    SENSOR_KIND = "sensor"

    def __init__(
        self,
        connect: str,
        uav: int,
        policy: str,
        parent_pid: int | None,
        wait_s: float,
        heartbeat_timeout_s: float | None,
        verbose: bool,
    ):
        import zmq

        self.zmq = zmq
        self.uav, self.policy_choice, self.parent_pid = uav, policy, parent_pid
        self.wait_s, self.heartbeat_override, self.verbose = wait_s, heartbeat_timeout_s, verbose
        self.context = zmq.Context.instance()
        self.sock = self.context.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(connect)
        self.cfg = None
        self.policy = None
        self.act = None
        self.heartbeat_timeout_s = heartbeat_timeout_s or wait_s
        self.malformed = 0
        self.answered = 0

    def log(self, text: str) -> None:
        if self.verbose:
            print(f"cefc-agent uav {self.uav}: {text}", file=sys.stderr, flush=True)

    def send(self, message: dict) -> None:
        message = {"v": wire.WIRE_VERSION, **message}
        try:
            self.sock.send(wire.encode(message), self.zmq.NOBLOCK)
        except self.zmq.Again:  # the simulator is gone and the queue is full: nothing to do
            pass

    def _receive_all(self) -> list[tuple[dict, float]]:
        """Every queued message (validated) with its wall-clock arrival time; malformed ones counted."""
        out = []
        events, pollin = self.zmq.EVENTS, self.zmq.POLLIN
        while self.sock.getsockopt(events) & pollin:  # (cheaper than a NOBLOCK recv that raises Again)
            try:
                frames = self.sock.recv_multipart(self.zmq.NOBLOCK)
            except self.zmq.Again:
                break
            arrived = time.perf_counter()
            try:
                if len(frames) != 1:
                    raise wire.WireError("multipart frame")
                message = wire.decode(frames[0], wire.SIM_TO_AGENT)
                self._check(message)
            except wire.WireError as e:
                self.malformed += 1
                self.log(f"dropped a malformed message ({e})")
                continue
            out.append((message, arrived))
        return out

    def _check(self, message: dict) -> None:
        """The checks of a decoded message that need the game (WireError)."""
        if message["type"] in ("game_sensor", "inbox"):
            raise wire.WireError("game frame to a low-level agent")
        if message["type"] == "sensor" and self.cfg is not None:
            wire.check_sensor(message, self.cfg.n_lidar_rays, self.cfg.n_agents, self.uav)

    def _welcome(self, message: dict) -> int | None:
        """Load the policy for the game in `welcome`; an exit code if the agent cannot fly it."""
        from cefc_mj.errors import CefcError
        from cefc_mj.eval.runner import load_policy_for
        from cefc_mj.task.config import TaskConfig

        if message["uav"] != self.uav:
            return self._fail("the simulator welcomed another UAV index")
        try:
            self.cfg = TaskConfig.from_dict(message["task"])
            if self.cfg.mode != "formation" or not 0 <= self.uav < self.cfg.n_agents:
                raise CefcError(f"uav {self.uav}: not an agent of this formation-mode game")
            self.policy = load_policy_for(self.policy_choice, message["formation"])
        except (CefcError, TypeError, ValueError) as e:
            return self._fail(str(e).splitlines()[0] if str(e) else type(e).__name__)
        if self.heartbeat_override is None:
            self.heartbeat_timeout_s = message["heartbeat_timeout_s"]
        self.act = low_level_act(self.policy, self.cfg)
        warm_up_low_level(self.act, self.cfg, self.uav)
        self.send({"type": "ready", "uav": self.uav})
        self.log(f"flying {self.policy.name} in formation c = {message['formation']}")
        return None

    def _fail(self, reason: str) -> int:
        self.send({"type": "error", "uav": self.uav, "reason": reason[:500]})
        print(f"cefc-agent uav {self.uav}: {reason}", file=sys.stderr, flush=True)
        time.sleep(0.1)  # let the error frame leave before the socket closes
        return EXIT_USAGE

    def _inbox(self, message: dict) -> None:  # only the game agent receives inboxes
        pass

    def _act(self, packet: dict, arrived: float) -> None:
        obs = observation_from_packet(self.cfg, packet)
        accel = self.act(obs[None, None])[0, 0]
        latency_ms = (time.perf_counter() - arrived) * 1e3
        self.send(
            {
                "type": "action",
                "uav": self.uav,
                "seq": packet["seq"],
                "accel": [float(accel[0]), float(accel[1])],
                "latency_ms": latency_ms,
            }
        )
        self.answered += 1

    def run(self) -> int:
        """The agent's main loop; returns the process exit code."""
        hello = {
            "type": "hello",
            "uav": self.uav,
            "policy": self.policy_choice,
            "pid": os.getpid(),
            "host": socket.gethostname()[:200],
        }
        self.send(hello)
        last_hello = last_heard = time.monotonic()
        while True:
            messages = self._receive_all() if self.sock.poll(200) else []
            newest = None
            for message, arrived in messages:
                kind = message["type"]
                if kind == "stop":
                    self.log(
                        f"stopped by the simulator ({message['reason']}); {self.answered} packets answered, "
                        f"{self.malformed} malformed dropped"
                    )
                    return 0
                if kind == "reject":
                    return self._fail(f"rejected by the simulator: {message['reason']}")
                if kind == "welcome" and self.cfg is None:
                    code = self._welcome(message)
                    if code is not None:
                        return code
                elif kind == self.SENSOR_KIND and self.cfg is not None:
                    newest = (message, arrived)
                elif kind == "inbox" and self.cfg is not None:
                    self._inbox(message)
            if newest is not None:  # the reply first, the housekeeping after it
                self._act(*newest)
            now = time.monotonic()
            if messages:
                last_heard = now  # (after a welcome: after loading the policy, which took a while)
            limit = self.heartbeat_timeout_s if self.cfg is not None else self.wait_s
            if now - last_heard > limit:
                print(
                    f"cefc-agent uav {self.uav}: no message from the simulator for {limit:g} s; exiting",
                    file=sys.stderr,
                    flush=True,
                )
                return EXIT_LOST
            if not _parent_alive(self.parent_pid):
                print(
                    f"cefc-agent uav {self.uav}: parent process {self.parent_pid} is gone; exiting",
                    file=sys.stderr,
                    flush=True,
                )
                return EXIT_LOST
            if self.cfg is None and now - last_hello > HELLO_PERIOD_S:  # the simulator may have (re)started
                self.send(hello)
                last_hello = now

    def close(self) -> None:
        self.sock.close(0)


class GameAgent(Agent):
    """One UAV's whole CI-HRL hierarchy (`cefc-agent --game`): at each high-level decision (every
    `decision_interval` low-level steps) ConsMAC and the anchor selector on its own CEFC observation
    and the inbox of neighbours' messages it received (`AgentHierarchy`, the in-process game's code),
    then, every step, the low level toward its chosen anchor. It answers each game sensor packet
    with the acceleration setpoint (its latency covers the whole decision) and, after each
    high-level decision, sends its message (with the anchor it chose and the high-level latency).
    An inbox that did not arrive (dropped, malformed, late) reads as no neighbour in range."""

    SENSOR_KIND = "game_sensor"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.hierarchy = None
        self.interval = 10
        self.inboxes: dict[int, dict] = {}
        self.decided = -1
        self.missing_inboxes = 0
        self.late_inboxes = 0

    def _check(self, message: dict) -> None:
        kind, cfg = message["type"], self.cfg
        if kind == "sensor":
            raise wire.WireError("low-level sensor packet to a game agent")
        if cfg is None or self.hierarchy is None:
            return
        if kind == "game_sensor":
            wire.check_game_sensor(message, cfg.n_lidar_rays, cfg.n_targets, cfg.n_agents, self.uav)
        elif kind == "inbox":
            wire.check_inbox(message, self.hierarchy.message_dim, cfg.n_agents, self.uav, cfg.observation_distance)

    def _welcome(self, message: dict) -> int | None:
        from cefc_mj.errors import CefcError
        from cefc_mj.hierarchy import AgentHierarchy, load_low_level
        from cefc_mj.nn.highlevel_policy import highlevel_policy_path, load_highlevel_policy
        from cefc_mj.task.config import TaskConfig

        if message["uav"] != self.uav:
            return self._fail("the simulator welcomed another UAV index")
        game = message.get("game")
        try:
            if not isinstance(game, dict) or not isinstance(game.get("low_level"), str):
                raise CefcError("the simulator runs no game (a low-level SITL-M episode?): drop --game")
            interval = game.get("decision_interval")
            if not isinstance(interval, int) or isinstance(interval, bool) or interval < 1:
                raise CefcError("welcome: decision_interval must be an integer >= 1")
            cfg = TaskConfig.from_dict(message["task"])
            if cfg.mode != "cefc" or not 0 <= self.uav < cfg.n_agents:
                raise CefcError(f"uav {self.uav}: not an agent of this CEFC game")
            policy, _ = load_highlevel_policy(highlevel_policy_path(self.policy_choice))
            hierarchy = AgentHierarchy(policy, load_low_level(game["low_level"], cfg), cfg)
        except (CefcError, TypeError, ValueError) as e:
            return self._fail(str(e).splitlines()[0] if str(e) else type(e).__name__)
        if self.heartbeat_override is None:
            self.heartbeat_timeout_s = message["heartbeat_timeout_s"]
        self.cfg, self.hierarchy, self.interval = cfg, hierarchy, interval
        warm_up_hierarchy(hierarchy, cfg, self.uav)
        self.send({"type": "ready", "uav": self.uav})
        self.log(f"playing {policy.variant} ({self.policy_choice}) over {game['low_level']}, N = {cfg.n_agents}")
        return None

    def _inbox(self, message: dict) -> None:
        if message["seq"] <= self.decided:
            self.late_inboxes += 1
            return
        self.inboxes[message["seq"]] = message
        for old in [d for d in self.inboxes if d < message["seq"] - 4]:  # never more than a few kept
            del self.inboxes[old]

    def _act(self, packet: dict, arrived: float) -> None:
        from cefc_mj.hierarchy import agent_cefc_observation

        hierarchy, cfg = self.hierarchy, self.cfg
        decision = packet["seq"] // self.interval
        sent_message = None
        if decision > self.decided:  # a high-level decision (late if its packet was skipped)
            neighbours = sorted(packet["neighbours"])
            obs = agent_cefc_observation(
                cfg,
                [*packet["pos"], *packet["vel"]],
                neighbours,
                packet["targets"],
                [*packet["adversary_pos"], *packet["adversary_vel"]],
                packet["lidar"],
            )
            box = self.inboxes.pop(decision, None)
            if box is None and hierarchy.communicates:
                self.missing_inboxes += 1
            if box is None:
                index, message = hierarchy.decide(obs)
            else:
                index, message = hierarchy.decide(obs, box["sender"], box["distance"], box["messages"])
            high_ms = (time.perf_counter() - arrived) * 1e3
            self.decided = decision
            for old in [d for d in self.inboxes if d <= decision]:
                del self.inboxes[old]
            sent_message = {
                "type": "message",
                "seq": decision,
                "uav": self.uav,
                "latency_ms": high_ms,
                "anchor": index,
                "message": message if message is not None else np.zeros(0, dtype=np.float32),
            }
        if hierarchy.anchor_index is None:  # no decision yet (cannot happen: packet 0 is a decision)
            return
        low_packet = {
            "pos": packet["pos"],
            "vel": packet["vel"],
            "anchor": hierarchy.anchor.tolist(),
            "lidar": packet["lidar"],
            "neighbours": packet["neighbours"],
        }
        accel = hierarchy.act(observation_from_packet(cfg, low_packet))
        latency_ms = (time.perf_counter() - arrived) * 1e3
        self.send(
            {
                "type": "action",
                "uav": self.uav,
                "seq": packet["seq"],
                "accel": [float(accel[0]), float(accel[1])],
                "latency_ms": latency_ms,
            }
        )
        self.answered += 1
        if sent_message is not None:
            self.send(sent_message)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (the project's convention)
        print(f"cefc-agent: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="cefc-agent",
        description="Run UAV policies as SITL-M agent processes (one process per UAV), for a simulator that "
        "waits for agents on other machines (SitlConfig(bind=..., remote_agents=...)); `cefc-eval --sitl-m` "
        "starts its local agents itself.",
        formatter_class=ExamplesHelpFormatter,
        epilog=help_epilog(
            [
                "cefc-agent --connect tcp://SIM_HOST:5555 --uav 3 --policy atm_c6_step3   # UAV 3, AT-M Step 3",
                "cefc-agent --connect tcp://SIM_HOST:5555 --uav 3 4 5      # UAVs 3-5, AT-M-Nav (the default)",
                "cefc-agent --game --connect tcp://SIM_HOST:5555 --uav 3 --policy cihrl_consmac_a   # the game",
            ],
            "docs/sitl_m.md (SITL-M: the processes, the wire format, agents on other machines)",
        ),
    )
    p.add_argument(
        "--connect",
        required=True,
        metavar="ENDPOINT",
        help="the simulator's ZeroMQ endpoint, e.g. tcp://192.168.1.10:5555",
    )
    p.add_argument(
        "--uav",
        required=True,
        type=int,
        nargs="+",
        metavar="I",
        help="this agent's UAV index (0-based); several indices fork one agent process per UAV "
        "after the shared imports",
    )
    p.add_argument(
        "--policy",
        default=DEFAULT_POLICY,
        metavar="NAME|PATH",
        help=f"nav, atm, safe, clm, student, a name in policies/ or a .pt path (default {DEFAULT_POLICY})",
    )
    p.add_argument("--parent-pid", type=int, metavar="PID", help="exit when this process (the simulator) is gone")
    p.add_argument(
        "--wait",
        type=float,
        default=DEFAULT_WAIT_S,
        metavar="S",
        help=f"how long to wait for the simulator's welcome (default {DEFAULT_WAIT_S:g} s)",
    )
    p.add_argument(
        "--heartbeat-timeout",
        type=float,
        metavar="S",
        help="exit after this long without a message from the simulator (default: the simulator's value)",
    )
    p.add_argument(
        "--game",
        action="store_true",
        help="run the UAV's whole CI-HRL hierarchy in the game (--policy: the high-level policy, e.g. "
        "cihrl_consmac_a): ConsMAC + anchor selector every decision, the low level every step",
    )
    p.add_argument("--verbose", action="store_true", help="log to stderr")
    return p


def _run_agent(args, uav: int) -> int:
    """One agent in this process until it exits; returns its exit code."""
    agent = None
    try:
        try:
            agent = (GameAgent if args.game else Agent)(
                args.connect, uav, args.policy, args.parent_pid, args.wait, args.heartbeat_timeout, args.verbose
            )
        except Exception as e:  # zmq.ZMQError: a malformed endpoint
            print(f"cefc-agent: error: --connect {args.connect}: {e}", file=sys.stderr)
            return EXIT_USAGE
        return agent.run()
    except KeyboardInterrupt:
        return 130
    finally:
        if agent is not None:
            agent.close()


def _fork_agents(args) -> int:
    """Fork one agent process per UAV (they share the imports, each loads its own policy copy) and
    supervise them: reap each as it exits, pass SIGTERM/SIGINT on, kill them if the simulator goes.
    The children die with this process (PR_SET_PDEATHSIG = SIGKILL, which also ends a stopped one)."""
    import traceback

    launcher = os.getpid()
    children: dict[int, int] = {}
    for uav in args.uav:
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                _die_with_parent(launcher, signal.SIGKILL)
                code = _run_agent(args, uav)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
            except BaseException:
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
        children[pid] = uav
    stop_since: list[float] = []

    def stop_children(*_):
        if not stop_since:
            stop_since.append(time.monotonic())
        for child in children:
            for sig in (signal.SIGCONT, signal.SIGTERM):
                try:
                    os.kill(child, sig)
                except ProcessLookupError:
                    pass

    signal.signal(signal.SIGTERM, stop_children)
    signal.signal(signal.SIGINT, stop_children)
    while children:
        pid, status = os.waitpid(-1, os.WNOHANG)
        if pid:
            uav = children.pop(pid, None)
            if args.verbose or os.waitstatus_to_exitcode(status) not in (0, 130, 143):
                print(
                    f"cefc-agent uav {uav}: process {pid} exited with code {os.waitstatus_to_exitcode(status)}",
                    file=sys.stderr,
                    flush=True,
                )
            continue
        if not stop_since and not _parent_alive(args.parent_pid):
            stop_children()
        if stop_since and time.monotonic() - stop_since[0] > 2.0:
            for child in children:
                try:
                    os.kill(child, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        time.sleep(0.02)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if any(uav < 0 for uav in args.uav) or len(set(args.uav)) != len(args.uav):
        build_parser().error(f"--uav {' '.join(map(str, args.uav))}: indices must be distinct and >= 0")
    for flag, value in (("--wait", args.wait), ("--heartbeat-timeout", args.heartbeat_timeout)):
        if value is not None and not (np.isfinite(value) and value > 0):
            build_parser().error(f"{flag} {value}: must be a finite number > 0")
    if "://" not in args.connect:
        build_parser().error(f"--connect {args.connect}: not a ZeroMQ endpoint (e.g. tcp://HOST:PORT)")
    if args.parent_pid is not None:
        _die_with_parent(args.parent_pid)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwind: close the socket
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        import torch

        import cefc_mj.eval.runner  # noqa: F401 - the heavy imports (torch, numba kernels) before saying hello

        if args.game:
            import cefc_mj.game_protocol  # noqa: F401 - the game's networks and observation code
        from cefc_mj.task.config import TaskConfig

        torch.set_num_threads(1)
        cfg = TaskConfig(n_agents=3, mode="formation")  # load the compiled observation kernels once, before any fork
        observation_from_packet(
            cfg,
            {
                "pos": [0.0, 0.0],
                "vel": [0.0, 0.0],
                "anchor": [1.0, 1.0],
                "lidar": [cfg.lidar_range] * cfg.n_lidar_rays,
                "neighbours": [[1, 1.0, 0, 0, 0]],
            },
        )
    except KeyboardInterrupt:
        return 130
    if len(args.uav) > 1 and hasattr(os, "fork"):
        return _fork_agents(args)
    if len(args.uav) > 1:
        build_parser().error("--uav: several indices need os.fork; start one process per UAV")
    return _run_agent(args, args.uav[0])


if __name__ == "__main__":
    raise SystemExit(main())
