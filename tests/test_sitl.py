"""SITL-M: agents as real OS processes over ZeroMQ (cefc_mj.deploy; docs/sitl_m.md).

Every test that starts agents checks afterwards that no process it started survives.
"""

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import time

import numpy as np
import psutil
import pytest
import zmq

from cefc_mj.deploy import (
    AgentFault,
    SitlConfig,
    parse_drop,
    run_dropout_episode,
    run_latency_model_episode,
    run_sitl_episode,
    wire,
)
from cefc_mj.deploy.agent import EXIT_LOST, observation_from_packet
from cefc_mj.deploy.dropout import DropoutCEFCEnv
from cefc_mj.deploy.sim_server import sensor_packets
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CefcError, ConfigError
from cefc_mj.eval.runner import EpisodeSpec, run_episode
from cefc_mj.task.config import TaskConfig

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _wait_gone(pids, timeout=10.0) -> list[int]:
    """The pids still alive after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        alive = [p for p in pids if not _gone(p)]
        if not alive:
            return []
        time.sleep(0.05)
    return [p for p in pids if not _gone(p)]


@pytest.fixture(autouse=True)
def no_orphans():
    """No process started by a test may outlive it."""
    yield
    children = psutil.Process().children(recursive=True)
    assert _wait_gone([c.pid for c in children], timeout=5.0) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _agent_pids(result) -> list[int]:
    return [a["pid"] for a in result.sitl.agents]


# ---------------------------------------------------------------- no processes
def test_agent_builds_the_lockstep_observation_from_its_packet():
    """The packet (through JSON and validation) rebuilds the lock-step runner's observation row bit
    for bit whenever the radio (true distance) and the observation (perceived distance) agree on the
    neighbours: always with exact sensing, and for most rows under sensing deviation."""
    for deviation in (0.0, 0.3):
        rows = agreeing = 0
        cfg = TaskConfig(n_agents=8, mode="formation", obstacle_density=0.03, deviation=deviation, start_half_size=3.0)
        env = BatchedCEFCEnv(cfg, n_envs=1, seed=3)
        env.reset()
        rng = np.random.default_rng(0)
        for _ in range(6):
            obs, *_ = env.step(rng.uniform(-2, 2, (1, 8, 2)))
            world = env.world
            packets = sensor_packets(
                7,
                0.7,
                env.perceived_pos[0],
                world.agent_vel[0],
                env.lidar[0],
                env.anchor[0],
                world.agent_pos[0],
                cfg.observation_distance,
                np.ones(8, bool),
                list(range(8)),
            )
            for i, packet in enumerate(packets):
                packet = wire.decode(wire.encode({"v": wire.WIRE_VERSION, **packet}), wire.SIM_TO_AGENT)
                wire.check_sensor(packet, cfg.n_lidar_rays, cfg.n_agents, i)
                true_d = np.linalg.norm(world.agent_pos[0] - world.agent_pos[0, i], axis=-1)
                seen_d = np.linalg.norm(env.perceived_pos[0] - env.perceived_pos[0, i], axis=-1)
                same = np.array_equal((true_d < 3.0), (seen_d < 3.0))
                rows += 1
                if same:
                    agreeing += 1
                    assert np.array_equal(observation_from_packet(cfg, packet), obs[0, i])
        assert agreeing == rows if deviation == 0 else agreeing >= rows / 2


def _binary_garbage(good_action: bytes, good_sensor: bytes) -> list[bytes]:
    """Binary frames that must be refused: truncated, another version, an unknown kind, a length that
    disagrees with the header, NaN, a fractional neighbour id."""
    nan = struct.pack("<d", float("nan"))
    header = 12
    return [
        good_action[:8],
        good_action[:2] + b"\x01" + good_action[3:],
        good_action[:3] + b"\x09" + good_action[4:],
        good_action + b"\x00" * 8,
        good_action[:header] + nan + good_action[header + 8 :],
        good_sensor[:-40] + struct.pack("<d", 1.5) + good_sensor[-32:],  # the last neighbour's id
        good_sensor,
    ]  # a sensor packet is not a message an agent sends


def test_wire_validation_refuses_garbage():
    v = wire.WIRE_VERSION
    good = {"v": v, "type": "action", "uav": 1, "seq": 3, "accel": [0.1, -2.0], "latency_ms": 0.3}
    frame = wire.encode(good)
    assert frame[:2] == wire.BINARY_MAGIC and len(frame) == 36
    assert wire.decode(frame, wire.AGENT_TO_SIM) == good
    as_json = json.dumps(good).encode()  # the same message as JSON is accepted too
    assert wire.decode(as_json, wire.AGENT_TO_SIM) == good
    packet = {
        "v": v,
        "type": "sensor",
        "seq": 0,
        "t": 0.0,
        "pos": [0.5, 0.0],
        "vel": [0.0, 0.25],
        "anchor": [1.0, 1.0],
        "lidar": [3.0] * 24,
        "neighbours": [[2, 1.0, 0.0, 0.0, 0.0], [5, -1.0, 2.0, 0.5, 0.0]],
    }
    sensor = wire.encode(packet)
    assert wire.decode(sensor, wire.SIM_TO_AGENT) == packet and len(sensor) == 12 + 8 * (7 + 24 + 10)
    bad = [
        b"\xff\xfe",
        b"not json",
        b"[1, 2]",
        b'{"v": 1, "type": "action", "uav": 1, "seq": 3, "accel": [0, 0], "latency_ms": 0.3}',
        b'{"v": 2, "type": "action"}',
        b'{"v": 2, "type": "launch"}',
        b'{"v": 2, "type": "action", "uav": 1, "seq": 3, "accel": [NaN, 0], "latency_ms": 0.3}',
        b'{"v": 2, "type": "action", "uav": 1, "seq": 3, "accel": [1e999, 0], "latency_ms": 0.3}',
        b'{"v": 2, "type": "action", "uav": true, "seq": 3, "accel": [0, 0], "latency_ms": 0.3}',
        b'{"v": 2, "type": "action", "uav": 1, "seq": -1, "accel": [0, 0], "latency_ms": 0.3}',
        b'{"v": 2, "type": "action", "uav": 1, "seq": 3, "accel": [0], "latency_ms": 0.3}',
        b" " * (wire.MAX_FRAME_BYTES + 1),
    ] + _binary_garbage(frame, sensor)
    for frame in bad:
        with pytest.raises(wire.WireError):
            wire.decode(frame, wire.AGENT_TO_SIM)
    with pytest.raises(wire.WireError, match="neighbours id"):
        wire.decode(_binary_garbage(frame, sensor)[5], wire.SIM_TO_AGENT)
    with pytest.raises(ValueError):
        wire.encode({**good, "latency_ms": float("inf")})
    packet["neighbours"] = [[2, 1, 0, 0, 0], [2, 1, 0, 0, 0]]
    with pytest.raises(wire.WireError):
        wire.check_sensor(wire.decode(wire.encode(packet), wire.SIM_TO_AGENT), 24, 8, 0)


def test_bad_config_fails_before_any_process_starts():
    spec = EpisodeSpec(formation=5, seed=0, steps=50)
    for sitl, needle in (
        (SitlConfig(link_delay_ms=-1), "link_delay_ms"),
        (SitlConfig(drop=(3, 10)), "drop"),
        (SitlConfig(drop=(1, 50)), "drop"),
        (SitlConfig(bind="localhost"), "bind"),
        (SitlConfig(faults=(AgentFault(7, 3),)), "faults"),
    ):
        with pytest.raises(ConfigError, match=needle):
            run_sitl_episode(spec, sitl)
    with pytest.raises(CefcError, match="no_such_policy"):  # CheckpointError, as in the lock-step runner
        run_sitl_episode(EpisodeSpec(formation=5, seed=0, steps=5, policy="no_such_policy"), SitlConfig())
    assert parse_drop("2@500") == (2, 500)
    with pytest.raises(ConfigError, match="K@STEP"):
        parse_drop("2x500")


@pytest.mark.parametrize("backend", ["particle", "mujoco"])
def test_lockstep_dropout_reforms_with_the_smaller_group(backend):
    """k UAVs leave: they are parked out of the arena and the group (and its template) becomes c - k;
    before the drop the run is exactly the plain lock-step episode."""
    spec = EpisodeSpec(formation=7, seed=2, backend=backend, steps=120, policy="student")
    result = run_dropout_episode(spec, (2, 60))
    before = result.dropout.phases["before"]
    plain = run_episode(EpisodeSpec(formation=7, seed=2, backend=backend, steps=60, policy="student"))
    assert (before["F"], before["N"], before["C"]) == (plain.F, plain.N, plain.C)
    after = result.dropout.phases["after"]
    assert before["group_size"] == 7 and after["group_size"] == 5 and after["steps"] == 60
    assert len(result.dropout.uavs) == 2 and result.steps == 120
    assert json.loads(json.dumps(result.to_dict()))["dropout"]["phases"]["after"]["group_size"] == 5
    # the 5 re-form: the student reaches the c = 5 template (HD error < 1 m) within the 6 s left
    assert np.nanmin(result.dropout.hd_error[100:]) < 1.0


def test_dropout_env_without_dropout_is_the_task_core():
    cfg = TaskConfig(n_agents=5, mode="formation", obstacle_density=0.03)
    a, b = BatchedCEFCEnv(cfg, n_envs=2, seed=1), DropoutCEFCEnv(cfg, n_envs=2, seed=1)
    oa, ob = a.reset(), b.reset()
    rng = np.random.default_rng(1)
    for _ in range(20):
        act = rng.uniform(-2, 2, (2, 5, 2))
        (oa, ra, _, _), (ob, rb, _, _) = a.step(act), b.step(act)
        assert np.array_equal(oa, ob) and np.array_equal(ra, rb)
    for key, value in a.episode_metrics().items():
        assert np.array_equal(value, b.episode_metrics()[key])


# ---------------------------------------------------------------- real agent processes
def test_sitl_episode_close_to_lockstep_and_garbage_is_dropped():
    """c = 5 on MuJoCo, 50 steps: five agent processes fly it asynchronously with F, N, C close to
    the lock-step run. Meanwhile a raw socket throws garbage at the simulator: every frame is
    dropped and counted, the run is unaffected. (The policy alone: the closeness bound was measured
    for it; the agents' guard has its own test in tests/test_guard.py.)"""
    spec = EpisodeSpec(formation=5, seed=0, steps=50, guard=False)
    lockstep = run_episode(spec)
    port = _free_port()
    context = zmq.Context()
    rogue = context.socket(zmq.DEALER)
    rogue.setsockopt(zmq.LINGER, 0)
    rogue.connect(f"tcp://127.0.0.1:{port}")  # frames wait in the queue until the simulator binds
    action = wire.encode({"type": "action", "uav": 0, "seq": 0, "accel": [0.0, 0.0], "latency_ms": 1.0})
    garbage = [
        [b"\xff\xfe"],
        [b"not json"],
        [b'{"v": 1, "type": "ready", "uav": 0}'],
        [b'{"v": 2, "type": "launch", "uav": 0}'],
        [action],  # not registered
        [action[:2] + b"\x01" + action[3:]],
        [action[:20]],
        [b'{"v": 2, "type": "hello", "uav": 99, "policy": "x", "pid": 1, "host": "h"}'],
        [b'{"v": 2, "type": "action", "uav": 0, "seq": 0, "accel": [NaN, 0], "latency_ms": 1}'],
        [b"two", b"frames"],
    ]
    for frames in garbage:
        rogue.send_multipart(frames)
    try:
        result = run_sitl_episode(spec, SitlConfig(bind=f"tcp://127.0.0.1:{port}"))
        reject = rogue.poll(2000) and json.loads(rogue.recv())
    finally:
        rogue.close(0)
        context.term()
    assert result.mode == "SITL-M" and result.steps == 50 and result.diverged is None
    assert result.sitl.malformed == len(garbage), result.sitl.malformed_reasons
    assert reject["type"] == "reject" and "99" in reject["reason"]
    assert abs(result.F - lockstep.F) <= 12 and abs(result.N - lockstep.N) <= 12 and abs(result.C - lockstep.C) <= 2
    stats = result.sitl
    if stats.late_commands.sum() == 0 and np.all(np.concatenate(stats.command_age_ms) == 10.0):
        # every command took effect one tick after its packet: exactly the one-process latency model
        model = run_latency_model_episode(spec, latency_ticks=1)
        assert (result.F, result.N, result.C) == (model.F, model.N, model.C)
    assert [e["event"] for e in stats.events] == []
    for uav in range(5):  # every agent answered (nearly) every packet, each command took effect
        assert stats.decision_latency_ms[uav].size >= 45 and stats.command_age_ms[uav].size >= 45
        assert np.all(stats.command_age_ms[uav] >= 10.0 - 1e-6)  # at least one control tick after its packet
    summary = json.loads(json.dumps(result.to_dict()))  # JSON-ready
    assert summary["condition"] == "SITL-M" and summary["sitl"]["round_trip_ms"]["all"]["p50"] > 0
    assert _wait_gone(_agent_pids(result)) == []


def test_lockstep_over_the_wire_with_a_remote_agent_and_a_dropout():
    """UAV 3's agent is started by hand, as on another machine (`--connect`, no parent); the others
    are spawned. In lock-step mode the wire carries the one-process episode exactly, here with a
    dropout: UAV 3 leaves at step 20 (its agent is told to stop), the other three re-form."""
    spec = EpisodeSpec(formation=4, seed=0, steps=40, policy="student")
    reference = run_dropout_episode(spec, (1, 20))
    assert reference.dropout.uavs == [3]
    port = _free_port()
    remote = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cefc_mj.deploy.agent",
            "--connect",
            f"tcp://127.0.0.1:{port}",
            "--uav",
            "3",
            "--policy",
            "student",
        ],
        cwd=REPO,
        stderr=subprocess.PIPE,
    )
    try:
        result = run_sitl_episode(
            spec, SitlConfig(bind=f"tcp://127.0.0.1:{port}", remote_agents=(3,), lockstep=True, drop=(1, 20))
        )
        assert remote.wait(timeout=10) == 0  # told to stop when it dropped out
    finally:
        if remote.poll() is None:
            remote.kill()
            remote.wait()
    assert (result.F, result.N, result.C) == (reference.F, reference.N, reference.C)
    assert result.dropout.phases == reference.dropout.phases
    assert [a["local"] for a in result.sitl.agents] == [True, True, True, False]
    assert result.sitl.agents[3]["pid"] == remote.pid
    assert [(e["uav"], e["event"]) for e in result.sitl.events] == [(3, "removed")]
    assert np.all(np.concatenate(result.sitl.command_age_ms) == 0.0)  # applied at the packet's own step
    assert result.sitl.command_age_ms[3].size == 20


def test_killed_agent_fails_safe_and_a_hung_agent_does_not_hang_the_simulator():
    """c = 4: uav 1's agent is killed (SIGKILL) and uav 2's stopped (SIGSTOP) at step 10. Both
    vehicles enter PX4's offboard-loss hold 1 s (simulated) after their last setpoint and stay put;
    the run completes; the simulator's wall time grows by about the timeout, not more."""
    spec = EpisodeSpec(formation=4, seed=1, steps=50)
    faults = (AgentFault(1, 10, "kill"), AgentFault(2, 10, "stop"))
    result = run_sitl_episode(spec, SitlConfig(faults=faults), record=True)
    assert result.steps == 50
    events = {(e["uav"], e["event"]): e for e in result.sitl.events}
    assert (1, "agent_exited") in events
    for uav in (1, 2):
        hold = events[(uav, "offboard_loss_hold")]
        assert 1.9 <= hold["t"] <= 2.2  # last setpoint ~0.91-1.01 s + COM_OF_LOSS_T 1 s
        moved = np.linalg.norm(result.record.agent_pos[-1, uav, :2] - result.record.agent_pos[-10, uav, :2])
        assert moved < 0.05  # braked to a stop and holds
        assert np.linalg.norm(result.record.agent_vel[-1, uav]) < 0.05
    assert result.wall_s < 1.0 + 5.0  # about 1 s of real-time pacing for the hung agent
    assert events.get((0, "offboard_loss_hold")) is None and events.get((3, "offboard_loss_hold")) is None
    assert _wait_gone(_agent_pids(result)) == []


_SIGINT_PARENT = textwrap.dedent("""
    import sys
    import cefc_mj.deploy.sim_server as sim_server
    from cefc_mj.deploy import SitlConfig, run_sitl_episode
    from cefc_mj.eval.runner import EpisodeSpec

    ready = sim_server.SitlServer.wait_until_ready
    def announce(self, *args):
        startup = ready(self, *args)
        print("ready", flush=True)
        return startup
    sim_server.SitlServer.wait_until_ready = announce
    try:
        run_sitl_episode(EpisodeSpec(formation=3, seed=0, steps=3000), SitlConfig(realtime=True))
    except KeyboardInterrupt:
        sys.exit(130)
""")

_BARE_PARENT = textwrap.dedent("""
    import sys
    from cefc_mj.deploy.sim_server import AgentFleet, SitlServer
    from cefc_mj.task.config import TaskConfig

    cfg = TaskConfig(n_agents=3, mode="formation", obstacle_density=0.03)
    server = SitlServer("tcp://127.0.0.1:*", 3, {"formation": 3, "task": cfg.to_dict(), "heartbeat_timeout_s": 120.0}, 0.01)
    fleet = AgentFleet([sys.executable, "-m", "cefc_mj.deploy.agent"], server.local_endpoint, "atm", [0, 1, 2])
    fleet.spawn()
    server.wait_until_ready(120, fleet)
    print("ready", flush=True)
    while True:
        server.receive(1.0)
""")  # noqa: E501 (the script's text is kept as it was)


def _start_parent(script):
    """A simulator process running `script`, once its agents are ready, and all its descendants."""
    parent = subprocess.Popen(
        [sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    line = parent.stdout.readline()  # blocks until "ready" (or EOF if the parent failed)
    if line.strip() != "ready":
        parent.kill()
        raise AssertionError(f"the simulator did not get its agents ready: {parent.stderr.read()}")
    kids = [k.pid for k in psutil.Process(parent.pid).children(recursive=True)]
    assert len(kids) == 4  # the launcher and one agent per UAV
    return parent, kids


def test_sigint_to_the_simulator_ends_every_process():
    parent, kids = _start_parent(_SIGINT_PARENT)
    time.sleep(0.5)  # flying in real time
    parent.send_signal(signal.SIGINT)
    assert parent.wait(timeout=20) == 130
    assert _wait_gone(kids, timeout=5.0) == []


def test_agents_exit_when_the_simulator_is_killed():
    """SIGKILL leaves the simulator no chance to clean up, and its heartbeat timeout is 2 minutes:
    the agents notice on their own within seconds (the kernel's parent-death signal, the pid watch)."""
    parent, kids = _start_parent(_BARE_PARENT)
    parent.kill()
    parent.wait(timeout=10)
    assert _wait_gone(kids, timeout=10.0) == []


def test_remote_agent_exits_when_the_simulator_goes_silent():
    """An agent with no parent to watch (started by hand, e.g. on another machine) exits after the
    heartbeat timeout once the simulator stops talking."""
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.setsockopt(zmq.LINGER, 0)
    port = router.bind_to_random_port("tcp://127.0.0.1")
    agent = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cefc_mj.deploy.agent",
            "--connect",
            f"tcp://127.0.0.1:{port}",
            "--uav",
            "1",
            "--policy",
            "atm",
            "--heartbeat-timeout",
            "1",
        ],
        cwd=REPO,
        stderr=subprocess.PIPE,
    )
    try:
        assert router.poll(60000)
        identity, frame = router.recv_multipart()
        assert wire.decode(frame, wire.AGENT_TO_SIM)["type"] == "hello"
        welcome = {
            "v": wire.WIRE_VERSION,
            "type": "welcome",
            "uav": 1,
            "formation": 3,
            "heartbeat_timeout_s": 30.0,
            "task": EpisodeSpec(formation=3, seed=0).task_config().to_dict(),
        }
        router.send_multipart([identity, wire.encode(welcome)])
        assert router.poll(60000)
        assert wire.decode(router.recv_multipart()[1], wire.AGENT_TO_SIM)["type"] == "ready"
        silent_since = time.monotonic()
        code = agent.wait(timeout=20)
        assert code == EXIT_LOST and 0.9 <= time.monotonic() - silent_since < 10
        assert "no message from the simulator" in agent.stderr.read().decode()
    finally:
        if agent.poll() is None:
            agent.kill()
            agent.wait()
        router.close(0)
        context.term()


def test_agent_command_line_errors_are_one_line():
    out = subprocess.run(
        [sys.executable, "-m", "cefc_mj.deploy.agent", "--connect", "nowhere", "--uav", "1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "--connect" in out.stderr
